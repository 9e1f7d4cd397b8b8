"""curlnav proto: message schemas (`messages`), the msgpack codec (`codec`), raw buffers for bulk
arrays (`rawbuf`), frame layout (`frames`) and every Zenoh key expression of the run (`topology`).
Imports nothing of the services."""

__all__ = ["codec", "frames", "messages", "rawbuf", "topology"]
