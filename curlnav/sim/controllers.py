"""A reactive goal-seeking controller: the classical stand-in used for demos and tests.

It reads only the observation (no map): turn toward the goal bearing, slow down when the
LiDAR sees something close ahead, keep the arm extended so the end effector meets movable
obstacles first. It is *not* a planner and gets trapped behind walls; it exists so the
simulator can be shown and tested before any policy is trained.
"""

from __future__ import annotations

import numpy as np

from .config import EnvConfig


class GoalSeekingController:
    """``act(observation) -> action`` (shape (3,), inside the action space)."""

    def __init__(self, config: EnvConfig | None = None, slow_range: float = 1.2) -> None:
        self.config = config or EnvConfig()
        self.slow_range = slow_range  # m: below this ahead, drive slowly

    def act(self, observation: np.ndarray) -> np.ndarray:
        cfg = self.config
        beams = cfg.lidar_beams
        newest_ranges = observation[(cfg.range_frames - 1) * beams: cfg.range_frames * beams]
        newest_labels = observation[(cfg.range_frames + cfg.label_frames - 1) * beams:
                                    (cfg.range_frames + cfg.label_frames) * beams]
        goal = observation[-3:]
        bearing = float(goal[2])
        centre = beams // 2
        cone = slice(max(centre - 15, 0), centre + 16)
        ahead_static = np.where(newest_labels[cone] > 0.5, np.inf, newest_ranges[cone]).min()
        turn = float(np.clip(1.5 * bearing, -1.0, 1.0))
        speed = 0.8 * max(0.0, np.cos(bearing))
        if ahead_static < self.slow_range:
            speed *= 0.3
        return np.array([speed, turn, 1.0], dtype=np.float32)
