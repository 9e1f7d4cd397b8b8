"""Global planners: ``oracle`` (A* on the true map and pose; the ``oracle`` controller), ``global_plan``
(waypoints on that path for the controller, ``true-map``) and ``scan_map`` (waypoints on A* on a
map of the robot's own scans, ``scan-map``)."""

__all__ = ["global_plan", "oracle", "scan_map"]
