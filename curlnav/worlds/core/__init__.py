"""The world model under everything else in `curlnav.worlds`: a world and its files (`world`),
start/goal pairs (`pairs`), the held-out seeds no training run may use (`heldout`) and a
world's top-down picture (`picture`). Imports nothing else of `curlnav.worlds`. Submodules
are imported on use."""

__all__ = ["heldout", "pairs", "picture", "world"]
