"""A policy behind a global plan, as a navigation stack deploys a learned local planner (TARE's
global planner, Nav2's planner server): the policy's goal input is a waypoint
``WaypointConfig.distance_m`` ahead on an A* path, advanced as the robot goes.

``GlobalPlan`` needs only a planner (``plan(start, goal) -> path``), a path and a pose, so the ROS 2
node (``curlnav.ros2.node``) follows a ``/plan`` with it too; ``GlobalPlanAgent`` puts a policy behind
the oracle's A* path on the static map (``curlnav eval POLICY+global-plan``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from curlnav.layout import goal_frame
from curlnav.planners.oracle import GridPlanner
from curlnav.sim import EnvConfig, StartGoal, World


@dataclass(frozen=True)
class WaypointConfig:
    """How a global plan feeds a local policy (m)."""

    distance_m: float = 3.0  # the waypoint lies this far ahead along the path (the final goal when nearer)
    replan_deviation_m: float = 2.0  # plan again from the robot's place when it is this far off the path
    line_of_sight: bool = True  # pull the waypoint back until the straight line to it keeps off walls (no corner cutting)


class GlobalPlan:
    """An A* path on a static map and the waypoint ahead on it: ``waypoint(x, y) -> (wx, wy)``
    (m, map frame), advanced as the robot goes; planned again from where the robot stands when
    it strays more than ``replan_deviation_m`` (pushed round by a door, a detour round a ball)."""

    def __init__(self, planner: GridPlanner, start: tuple[float, float], goal: tuple[float, float],
                 config: WaypointConfig | None = None) -> None:
        self.planner, self.goal = planner, (float(goal[0]), float(goal[1]))
        self.config = config or WaypointConfig()
        self._set(planner.plan(start, goal))

    def _set(self, path: np.ndarray | None) -> None:
        self.path = path  # (n, 2) m, the goal last; None: no path on the static map
        self._index = 0
        if path is not None:
            self._along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])

    def waypoint(self, x: float, y: float) -> tuple[float, float]:
        """The point ``distance_m`` ahead along the path of the path point nearest ``(x, y)``
        (searched among the next few metres, so the index only moves forward), pulled back
        along the path until the straight line from ``(x, y)`` to it crosses no blocked cell of
        the planner's grid (the robot's half-width from every wall); the goal when the map has
        no path."""
        if self.path is None:
            return self.goal
        cfg = self.config
        window = int(np.searchsorted(self._along, self._along[self._index] + cfg.distance_m + 2.0))
        ahead = self.path[self._index:max(window, self._index + 1)]
        d = np.hypot(ahead[:, 0] - x, ahead[:, 1] - y)
        k = int(np.argmin(d))
        if d[k] > cfg.replan_deviation_m:
            path = self.planner.plan((x, y), self.goal)
            if path is not None:
                self._set(path)
                return self.waypoint(x, y)
        self._index += k
        j = min(int(np.searchsorted(self._along, self._along[self._index] + cfg.distance_m)), len(self.path) - 1)
        if cfg.line_of_sight:
            here = np.array([x, y])
            while j > self._index + 1 and not self.planner._line_free(here, self.path[j]):
                j -= 1
        return tuple(self.path[j])


class GlobalPlanAgent:
    """A policy (``obs -> action``) behind a global plan: its observation's goal block (the last
    ``goal_frames`` frames, as ``NamoEnv`` builds them) is rewritten each step to describe the
    ``GlobalPlan`` waypoint instead of the final goal. The plan is the oracle's A* path on the
    static map (the inflated ``GridPlanner``), made at ``reset``."""

    def __init__(self, policy, env_config: EnvConfig | None = None, config: WaypointConfig | None = None,
                 label: str = "policy") -> None:
        self.policy = policy
        self.env_config = env_config or EnvConfig()
        self.config = config or WaypointConfig()
        self.label = f"{label} + global plan"
        self._planners: dict[int, GridPlanner] = {}
        self.plan: GlobalPlan | None = None
        self._goals: np.ndarray | None = None  # (goal_frames, 3)

    def reset(self, world: World, pair: StartGoal) -> None:
        key = id(world)
        if key not in self._planners or self._planners[key].world is not world:
            self._planners = {key: GridPlanner(world, self.env_config.robot.base_width / 2)}
        self.plan = GlobalPlan(self._planners[key], (pair.x, pair.y), (pair.gx, pair.gy), self.config)
        self._goals = None
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise TypeError("GlobalPlanAgent needs the pose: call act(observation, info) after reset(world, pair)")

    def observation(self, observation: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``observation`` with its goal block describing the waypoint ahead of ``pose`` (the
        frames before the first step all the same, as the environment fills them on reset)."""
        x, y, yaw = pose
        frame = goal_frame(x, y, yaw, *self.plan.waypoint(x, y))
        frames = self.env_config.goal_frames
        if self._goals is None:
            self._goals = np.repeat(frame[None, :], frames, axis=0)
        else:
            self._goals = np.vstack([self._goals[1:], frame[None, :]])
        out = np.array(observation, dtype=np.float32, copy=True)
        out[-3 * frames:] = self._goals.ravel()
        return out

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        shown = self.observation(observation, info["pose"])
        inner = getattr(self.policy, "act", None)  # a planner (dwa) needs the odometry too
        return self.policy(shown) if inner is None else inner(shown, info)

    def commanded(self, action: np.ndarray) -> None:
        """The command the robot was sent this step, passed on to the agent behind the plan
        (``DynamicWindowPlanner.commanded``) when it takes it."""
        inner = getattr(self.policy, "commanded", None)
        if callable(inner):
            inner(action)
