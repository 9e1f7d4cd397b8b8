"""Worlds from outside: Gazebo SDF worlds rasterised onto the grid (`sdf`) and real buildings'
vendored SLAM maps with the real suite's tasks (`real_maps`; the files are in
`curlnav/worlds/data/real/`). Imports only `core`, `difficulty` and `procedural` of
`curlnav.worlds`. Submodules are imported on use."""

__all__ = ["real_maps", "sdf"]
