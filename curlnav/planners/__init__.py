"""Planners that drive the robot without learning: the oracle (A* on the true map and pose) and the
global plan a policy can follow (`oracle`), and the map-less local planners tare-l and dwa on the
same scan as a policy (`local`). Used by evaluation and by the ROS 2 node."""

__all__ = ["local", "oracle"]
