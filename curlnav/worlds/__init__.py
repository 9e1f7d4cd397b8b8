"""World families (`generators`, `namo`, `slam_like`, `scatter`), the BARN navigation-difficulty
metrics (`metrics`) and the ranking that orders a curriculum (`rank`). Submodules are imported on use."""

__all__ = ["generators", "metrics", "namo", "rank", "scatter", "slam_like"]
