"""The BARN Challenge: its 300 vendored worlds (`barn`; the files are in
`curlnav/worlds/data/barn/`) and the `barn-course` training family laid out like them
(`barn_course`). Imports only the sub-packages below it (`core`, `procedural`, `real`).
Submodules are imported on use."""

__all__ = ["barn", "barn_course"]
