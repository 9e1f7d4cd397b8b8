"""The worlds library, below the simulator: the world model and its files (`world`), start/goal
pairs (`pairs`), the resolver of world specs and the built-in worlds (`builtin`), world families
(the registry `families`; `generators`, `namo`, `tmaze`, `slam_like`, `scatter`), distributions of
worlds (`distribution`), the held-out seeds (`heldout`), curriculum levels (`levels`), the BARN
navigation-difficulty metrics (`metrics`) and the ranking that orders a curriculum (`rank`). Submodules are imported on use."""

__all__ = ["builtin", "distribution", "families", "generators", "heldout", "levels", "metrics", "namo", "pairs", "rank",
           "scatter", "slam_like", "tmaze", "world"]
