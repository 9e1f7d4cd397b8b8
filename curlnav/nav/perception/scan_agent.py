"""What every agent that plans on the scan shares (the map-less controllers, the safety shield): the
beams, the footprint, the short scan memory and the goal, in the robot frame of now.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from curlnav.layout import ObservationLayout, beam_angles
from curlnav.nav.geometry import from_frame, goal_in_robot_frame, odometry, to_frame
from curlnav.nav.perception.scan_filter import ScanFilterConfig, ScanMemory
from curlnav.sim import EnvConfig, StartGoal, World


class ScanAgent:
    """What both map-less planners share: the beams, the footprint and the static points they
    plan against. ``act(observation, info) -> [v, w, L]`` (fractions of the robot's limits).

    ``scan_filter``: the short memory of marked and cleared cells the scans go through
    (``curlnav.nav.perception.scan_filter``), as a real stack's costmap; None plans against the raw
    newest scan (the baselines before issue 37, which collapse under sensor noise)."""

    label = "scan agent"

    def __init__(self, env_config: EnvConfig | None = None,
                 scan_filter: ScanFilterConfig | None = ScanFilterConfig()) -> None:
        self.env_config = env_config or EnvConfig()
        self.layout = ObservationLayout.from_env_config(self.env_config)
        robot = self.env_config.robot
        self.half_length, self.half_width = robot.base_length / 2, robot.base_width / 2  # m
        self.beam_angles = beam_angles(self.env_config.lidar_fov, self.env_config.lidar_beams)  # rad, beam 0 on the right
        self.memory = None if scan_filter is None else ScanMemory(self.beam_angles, self.env_config.lidar_max_range,
                                                                   scan_filter)
        latency = getattr(getattr(self.env_config, "sensor_noise", None), "latency_steps", 0) or 0
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=int(latency) + 1)  # odometry, oldest first

    def reset(self, world: World, pair: StartGoal) -> None:
        """Start an episode. The world and pair are not used: no map, no goal but the observation's;
        the scan memory and the odometry history are emptied."""
        self._poses.clear()
        if self.memory is not None:
            self.memory.reset()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise TypeError(f"{type(self).__name__} needs odometry: call act(observation, info)")

    def static_points(self, observation: np.ndarray) -> np.ndarray:
        """``(n, 2)`` robot-frame points (m) of the newest scan's beams that hit a static obstacle
        (label 0, short of the maximum range)."""
        ranges, labels, _ = self.layout.newest_frame(np.asarray(observation))
        static = (labels < 0.5) & (ranges < self.env_config.lidar_max_range - 1e-3)
        r = ranges[static].astype(np.float64)
        a = self.beam_angles[static]
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    def sense(self, observation: np.ndarray, info: dict) -> tuple[np.ndarray, float, float]:
        """What to plan against now: ``(points, gx, gy)``, the static obstacle points ``(n, 2)``
        and the goal, in the robot frame of now (m). Call once per control step: the scan goes
        into the memory (without one: the newest scan's static points).

        An observation late by ``latency_steps`` control periods (``EnvConfig.sensor_noise``; a
        robot reads it from the scan's stamp) was seen from the odometry pose of that many steps
        ago: its points and goal are moved into the frame of the odometry now, as a stack's
        transform buffer does."""
        pose = odometry(info)
        self._poses.append(pose)
        seen_from = self._poses[0]
        ranges, labels, _ = self.layout.newest_frame(np.asarray(observation))
        if self.memory is None:
            points = self.static_points(observation)
        else:
            points = self.memory.update(ranges, labels, seen_from)
        goal = np.array([self.goal(observation)])
        if seen_from != pose:
            points = from_frame(to_frame(points, seen_from), pose)
            goal = from_frame(to_frame(goal, seen_from), pose)
        return points, float(goal[0, 0]), float(goal[0, 1])

    def goal(self, observation: np.ndarray) -> tuple[float, float]:
        """The goal ``(dx, dy)`` in the robot frame (m), from the newest goal frame."""
        _, _, goal = self.layout.newest_frame(np.asarray(observation))
        return goal_in_robot_frame(goal)

    def action(self, v: float, w: float) -> np.ndarray:
        """``[v, w, 0]`` from m/s and rad/s, clipped to the robot's limits (arm retracted; backing
        up only as far as the robot can)."""
        robot = self.env_config.robot
        return np.array([float(np.clip(v / robot.max_linear_speed, -robot.reverse_fraction, 1.0)),
                         float(np.clip(w / robot.max_angular_speed, -1.0, 1.0)), 0.0], dtype=np.float32)
