"""curlnav proto: message schemas, msgpack codec, Zenoh key expressions (topology.py)."""
