"""Worlds from outside: Gazebo SDF worlds rasterised onto the grid (`sdf`), real buildings'
vendored SLAM maps with the real suite's tasks (`real_maps`; the files are in
`curlnav/worlds/data/real/`) and a user's own map made a training task, its pairs split into
training and held-out ones (`own_map`). Imports only `core`, `difficulty` and `procedural` of
`curlnav.worlds`. Submodules are imported on use."""

__all__ = ["own_map", "real_maps", "sdf"]
