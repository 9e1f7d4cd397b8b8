"""How hard a world is to navigate: the five BARN navigation-difficulty metrics (`metrics`)
and the ranking by them that orders a curriculum (`rank`). Imports only `core` of
`curlnav.worlds`. Submodules are imported on use."""

__all__ = ["metrics", "rank"]
