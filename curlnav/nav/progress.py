"""The one progress checker (Nav2's ``nav2_core::ProgressChecker``): whether the robot still comes
nearer its goal. The rescue (``curlnav.nav.recovery.rescue``) takes over when it says the
controller stalls; the ROS 2 node (``curlnav.ros2.node``) gives a goal up when it says so.
"""

from __future__ import annotations

import math


class ProgressChecker:
    """Progress: the distance to go falls ``progress_m`` (m) below the least distance so far.
    Stalled: no progress for ``patience`` units of the caller's clock (control steps for the
    rescue, seconds for the node). ``update(distance, now)`` once per step, then ``stalled(now)``."""

    def __init__(self, progress_m: float, patience: float) -> None:
        if not (math.isfinite(progress_m) and progress_m > 0 and patience > 0):
            raise ValueError(f"progress checker: progress_m and patience must be positive, got {progress_m}, {patience}")
        self.progress_m = progress_m
        self.patience = patience
        self.reset()

    def reset(self, now: float = 0.0) -> None:
        """A new goal: no distance seen yet; the clock of no progress starts at ``now``."""
        self.best = math.inf  # m, the least distance to go so far
        self.best_at = now  # when it was made

    def update(self, distance_to_goal_m: float, now: float) -> bool:
        """Record the distance to go at ``now``; True when it is progress (the first finite one is)."""
        if math.isfinite(distance_to_goal_m) and (distance_to_goal_m < self.best - self.progress_m
                                                  or not math.isfinite(self.best)):
            self.best, self.best_at = distance_to_goal_m, now
            return True
        return False

    def stalled(self, now: float) -> bool:
        """No progress for ``patience`` or more up to ``now``."""
        return now - self.best_at >= self.patience

    def restart(self, at: float) -> None:
        """Count no progress again from ``at`` (after a recovery has had its turn)."""
        self.best_at = at

    def check(self, distance_to_goal_m: float, now: float) -> bool:
        """``update`` then: True while the robot still makes progress (the ``ProgressChecker`` role)."""
        return self.update(distance_to_goal_m, now) or not self.stalled(now)
