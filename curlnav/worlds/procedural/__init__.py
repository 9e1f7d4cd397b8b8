"""The generated world families: BARN grids, T-Mazes, caves, forests, garages, indoor floors,
campuses and auditoriums (`generators`), the NAMO worlds (`namo`), T-Mazes whose pairs push
doors (`tmaze`), worlds as a SLAM stack maps them (`slam_like`, degraded by `degrade`) and
movable balls scattered on a map's shortest paths (`scatter`). Their names are registered in
`curlnav.worlds.families`. Imports only `core` and `difficulty` of `curlnav.worlds`.
Submodules are imported on use."""

__all__ = ["degrade", "generators", "namo", "scatter", "slam_like", "tmaze"]
