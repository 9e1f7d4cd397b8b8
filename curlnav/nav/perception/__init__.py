"""Perception and localisation: what the roles behind see. ``scan_filter`` (a short memory of marked
and cleared cells, as a costmap), ``scan_agent`` (the scan, footprint and goal every scan-planning
role shares), ``stage`` (what a stage in front of an agent shares), ``label_filter`` (movable labels
voted over the last scans, ``label-vote``) and ``scan_match`` (laser odometry, ``laser-odometry``)."""

__all__ = ["label_filter", "scan_agent", "scan_filter", "scan_match", "stage"]
