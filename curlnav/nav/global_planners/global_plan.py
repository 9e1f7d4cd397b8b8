"""A policy behind a global plan, as a navigation stack deploys a learned local planner (TARE's
global planner, Nav2's planner server): the policy's goal input is a waypoint
``WaypointConfig.distance_m`` ahead on an A* path, advanced as the robot goes.

``GlobalPlan`` needs only a planner (``plan(start, goal) -> path``), a path and a pose (and the
planner's ``world`` where tight cells are given), so the ROS 2 node (``curlnav.ros2.node``) follows a
``/plan`` with it too (without tight cells: the node has no map and no tracker); ``GlobalPlanAgent`` puts a policy behind
the oracle's A* path on the static map (``curlnav eval POLICY+global-plan``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from curlnav.layout import goal_frame
from curlnav.nav.global_planners.oracle import GridPlanner, PlannerConfig, StaticMapPlanner
from curlnav.sim import EnvConfig, StartGoal, World
from curlnav.worlds.core.pairs import clearance_map


@dataclass(frozen=True)
class WaypointConfig:
    """How a global plan feeds a local policy (m)."""

    distance_m: float = 3.0  # the waypoint lies this far ahead along the path (the final goal when nearer)
    replan_deviation_m: float = 2.0  # plan again from the robot's place when it is this far off the path
    line_of_sight: bool = True  # pull the waypoint back until the straight line to it keeps off walls (no corner cutting)
    #: a tight spot: where the path passes nearer a wall than the robot's half-width plus this (a
    #: doorway narrower than the robot's width plus twice this, a corner the path cuts close);
    #: 0: none is tight
    passage_margin_m: float = 0.1
    #: from this far before a tight spot on the path (m along it) ...
    passage_approach_m: float = 2.0
    #: ... until this far past it the plan's path tracker drives (``GlobalPlanAgent``), not the
    #: policy: the Husky's half-length (0.495 m) and a margin, so that its rear is out of the
    #: doorway before the policy turns (a longer robot needs more)
    passage_exit_m: float = 0.7
    #: the tracker's pure-pursuit lookahead (m) and the heading error beyond which it turns in
    #: place (rad): short and small, so that it follows the path into the passage lined up
    passage_lookahead_m: float = 0.4
    passage_turn_rad: float = math.radians(20.0)

    def __post_init__(self) -> None:
        optional = ("passage_margin_m", "passage_approach_m", "passage_exit_m")  # 0 allowed
        for name in ("distance_m", "replan_deviation_m", *optional, "passage_lookahead_m", "passage_turn_rad"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value >= 0 and (value > 0 or name in optional)):
                kind = "non-negative" if name in optional else "positive"
                raise ValueError(f"waypoints: {name} must be a {kind} "
                                 f"number, got {value!r}")
        if not isinstance(self.line_of_sight, bool):
            raise ValueError(f"waypoints: line_of_sight must be true or false, got {self.line_of_sight!r}")


class GlobalPlan:
    """An A* path on a static map and the waypoint ahead on it: ``waypoint(x, y) -> (wx, wy)``
    (m, map frame), advanced as the robot goes; planned again from where the robot stands when
    it strays more than ``replan_deviation_m`` (pushed round by a door, a detour round a ball)."""

    def __init__(self, planner: GridPlanner, start: tuple[float, float], goal: tuple[float, float],
                 config: WaypointConfig | None = None, tight: np.ndarray | None = None) -> None:
        """``tight``: which of the planner world's cells (bool, the world's grid) are tight (free for
        the robot, nearer a wall than its half-width plus ``passage_margin_m``), or None."""
        self.planner, self.goal = planner, (float(goal[0]), float(goal[1]))
        self.config = config or WaypointConfig()
        self._replanned_from: tuple[float, float] | None = None  # m, where the path was last planned again
        self._tight_cells = tight
        self._set(planner.plan(start, goal))

    def _set(self, path: np.ndarray | None) -> None:
        self.path = path  # (n, 2) m, the goal last; None: no path on the static map
        self._index = 0
        if path is not None:
            self._along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
            self._tight = self._tight_at(path)

    def _tight_at(self, points: np.ndarray) -> np.ndarray:
        """``(n,)`` whether each of ``points`` (``(n, 2)``, m) lies on a tight cell (off the grid:
        its nearest edge cell)."""
        if self._tight_cells is None:
            return np.zeros(len(points), dtype=bool)
        iy, ix = self.planner.world.cells_of(points[:, 0], points[:, 1])
        rows, cols = self._tight_cells.shape
        return self._tight_cells[np.clip(iy, 0, rows - 1), np.clip(ix, 0, cols - 1)]

    @property
    def index(self) -> int:
        """The path point nearest the robot at the last ``waypoint`` call."""
        return self._index

    @property
    def tight(self) -> np.ndarray:
        """``(n,)`` which of the path's points are tight (all False without a path or tight cells)."""
        return self._tight if self.path is not None else np.zeros(0, dtype=bool)

    def near_passage(self, x: float, y: float) -> bool:
        """Whether the robot at ``(x, y)`` (m) stands on a tight cell, or a tight point of the path
        lies between ``passage_exit_m`` behind and ``passage_approach_m`` ahead of its place on
        the path (as of the last ``waypoint`` call)."""
        if self.path is None or self._tight_cells is None:
            return False
        if self._tight_at(np.array([[x, y]], dtype=np.float64))[0]:
            return True
        here = self._along[self._index]
        start = int(np.searchsorted(self._along, here - self.config.passage_exit_m, side="left"))
        end = int(np.searchsorted(self._along, here + self.config.passage_approach_m, side="right"))
        return bool(self._tight[start:end].any())

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
        if d[k] <= cfg.replan_deviation_m:
            self._replanned_from = None
        elif self._replanned_from is None or math.hypot(
                x - self._replanned_from[0], y - self._replanned_from[1]) > cfg.replan_deviation_m / 4:
            # once per place: a robot in a pocket of the map that no free cell within
            # replan_deviation_m of it reaches gets a path starting further off (the planner starts
            # at the nearest free cell), planned again only once it has moved
            self._replanned_from = (x, y)
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
    static map (the inflated ``GridPlanner``), made at ``reset``.

    Through a tight spot (``WaypointConfig.passage_margin_m``: where the path passes nearer a wall
    than the robot's half-width plus that margin, as through a doorway the robot fits with less than
    the margin to spare on either side), from ``passage_approach_m`` before it until
    ``passage_exit_m`` past it, the plan's path tracker drives instead (``passage_tracker``, a
    ``StaticMapPlanner``: regulated pure pursuit of the A* path on the same map and pose, with a
    short lookahead, turning in place where the path lies more than 20 degrees off). A policy
    steering for a waypoint in such a doorway's mouth drives at it as it is headed and wedges its
    corner on the jamb, where neither the shield nor a rescue can turn it; the tracker lines up
    first, as the path does. ``tracker`` (the oracle's settings but the plan's re-plan distance) is
    what a rescue in front drives (``track``,
    ``curlnav.nav.recovery.rescue.global_plan_fallback``); both follow the plan itself, from the robot's
    place on it. ``passage_steps`` counts the steps the tight spots' command was chosen over the
    policy's in the current episode (a rescue in front may still have sent its own, from
    ``tracker``); ``tracking`` says whether the last step's was (``replaced`` too,
    ``curlnav.nav.roles.chooser``)."""

    control_role = "true-map"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    replaced = False

    def __init__(self, policy, env_config: EnvConfig | None = None, config: WaypointConfig | None = None,
                 label: str = "policy") -> None:
        self.policy = policy
        self.env_config = env_config or EnvConfig()
        self.config = config or WaypointConfig()
        self.label = f"{label} + global plan"
        self._planners: dict[int, tuple[GridPlanner, np.ndarray | None]] = {}  # the grid and its tight cells
        self.plan: GlobalPlan | None = None
        self._goals: np.ndarray | None = None  # (goal_frames, 3)
        # the plan's path trackers: one a rescue in front may drive (the oracle's settings), one
        # for tight spots (a short lookahead, turning in place sooner: lined up with the path)
        self.tracker = StaticMapPlanner(self.env_config, PlannerConfig(replan_deviation_m=self.config.replan_deviation_m))
        self.passage_tracker = StaticMapPlanner(self.env_config, PlannerConfig(
            lookahead_m=self.config.passage_lookahead_m, turn_in_place_rad=self.config.passage_turn_rad,
            replan_deviation_m=self.config.replan_deviation_m))
        self.passage_steps = 0
        self.tracking = False  # whether the last act gave the tracker's command for a tight spot
        self._episode: tuple[World, StartGoal, GridPlanner] | None = None

    def reset(self, world: World, pair: StartGoal) -> None:
        key = id(world)
        if key not in self._planners or self._planners[key][0].world is not world:
            half_width = self.env_config.robot.base_width / 2
            clearance = clearance_map(world)
            planner, tight = GridPlanner(world, half_width, clearance=clearance), None
            if self.config.passage_margin_m > 0:  # free for the robot, but not with the margin to spare
                tight = ~planner.blocked & (clearance <= half_width + self.config.passage_margin_m)
            self._planners = {key: (planner, tight)}
        planner, tight = self._planners[key]
        self.plan = GlobalPlan(planner, (pair.x, pair.y), (pair.gx, pair.gy), self.config, tight)
        self._goals = None
        self.passage_steps = 0
        self.tracking = False
        self._episode = (world, pair, planner)
        for tracker in (self.tracker, self.passage_tracker):
            tracker.clear()
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)

    @property
    def episode(self) -> tuple[World, StartGoal, GridPlanner] | None:
        """The current episode's world, pair and planner (None before ``reset``)."""
        return self._episode

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
        own = self.policy(shown) if inner is None else inner(shown, info)
        self.tracking = self.plan.near_passage(*info["pose"][:2])
        self.replaced = self.tracking  # the plan's tracker drives a tight spot (``roles.chooser``)
        if self.tracking:
            self.passage_steps += 1
            return self.track(observation, info, passage=True)
        return own

    def track(self, observation: np.ndarray, info: dict, passage: bool = False) -> np.ndarray:
        """A tracker's command for this step (``passage``: the tight spots' one), on the plan as it
        stands (its path and the robot's place on it): regulated pure pursuit of the same path the
        policy's waypoints come from."""
        if self._episode is None:
            raise RuntimeError("GlobalPlanAgent.track before reset(world, pair)")
        world, pair, planner = self._episode
        tracker = self.passage_tracker if passage else self.tracker
        tracker.follow(world, pair, planner, self.plan.path, self.plan.index)
        return tracker.act(observation, info)

    def commanded(self, action: np.ndarray) -> None:
        """The command the robot was sent this step, passed on to the agent behind the plan
        (``DynamicWindowPlanner.commanded``) when it takes it."""
        inner = getattr(self.policy, "commanded", None)
        if callable(inner):
            inner(action)
