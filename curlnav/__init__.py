"""curlnav: curriculum reinforcement learning for navigation among movable obstacles."""

__version__ = "0.1.0"
