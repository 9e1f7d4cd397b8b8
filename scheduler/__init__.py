"""curlnav scheduler: the curriculum core (`curriculum`: the curriculum file, its checks, the state
that switches stages) and its service shell (`service`: assignments, episode reports, `/status`).
Submodules are imported on use."""

__all__ = ["curriculum", "service"]
