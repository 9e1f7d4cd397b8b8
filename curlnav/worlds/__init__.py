"""The worlds library, below the simulator: the world model and its files (`world`), start/goal
pairs (`pairs`), the resolver of world specs and the built-in worlds (`builtin`), world families
(the registry `families`; `generators`, `namo`, `tmaze`, `slam_like`, `barn_course`, `scatter`), a world
degraded into what a SLAM map of it looks like (`degrade`), distributions of
worlds (`distribution`), the held-out seeds (`heldout`), curriculum levels (`levels`), the BARN
navigation-difficulty metrics (`metrics`), the ranking that orders a curriculum (`rank`), a world's
picture (`picture`), Gazebo SDF worlds read onto the grid (`sdf`), the BARN Challenge's vendored
worlds (`barn`), real buildings' vendored SLAM maps and the real suite's tasks (`real_maps`) and the
`curlnav worlds` commands (`commands`). Submodules are imported on use."""

__all__ = ["barn", "barn_course", "builtin", "commands", "degrade", "distribution", "families", "generators", "heldout",
           "levels", "metrics", "namo", "pairs", "picture", "rank", "real_maps", "scatter", "sdf", "slam_like", "tmaze",
           "world"]
