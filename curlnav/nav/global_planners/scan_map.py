"""A map built from the robot's own scans, and a policy behind a plan on it (map-less: no prior map).

The BARN Challenge's baseline is ``move_base``: a global planner on a costmap that the robot fills
from its LiDAR as it drives (unknown space free), and DWA following that plan. A reactive policy
alone turns back and forth in front of a field too dense to see through, or drives into a pocket
that closes; a plan on what has been seen so far takes it round. ``ScanMapPlanAgent`` gives a
policy that plan, with nothing a robot lacks: the scans, their labels, the goal of the
observation and odometry.

- ``ScanMap``: an occupancy grid in the odometry frame, sized at the first step to hold the robot,
  the goal and ``padding_m`` round them. Each static return (label 0, short of the maximum range)
  adds ``hit`` to its cell's score; each cell a beam passes through on its way to a return (up to
  ``clear_range_m``; a beam that returned nothing clears nothing) loses ``miss``; scores stay in
  ``[score_min, score_max]``; a cell is occupied above ``occupied`` (hit in two scans). Movable
  returns (label 1) clear and mark nothing: a NAMO policy pushes them; each scan takes ``movable``
  once from every cell a movable return ends in, so that a ball the segmenter missed in a scan or
  two does not become a wall. ``ScanMapPlanAgent`` does not trust the segmenter where it knows
  better (``curlnav.nav.safety.push_check``, ``PushCheck.static``): a return labelled movable within
  ``PushConfig.near_m`` is laid down as static on a robot without an arm (it pushes nothing: a
  pillar called movable in every frame is a pillar), and on one with an arm where pushes held it
  static (it stayed put under the arm). A movable object the arm may still push is left to the
  shield, which holds the base off it unless it is pushed at pushing speed: the plan must route
  through the doors it pushes open (laying every unpushed door and ball near the Husky down as
  static took ``policies/namo-robust`` from 84 % to 70 % of the unseen suite, exact senses). A
  scan that arrives ``latency_steps`` late is laid down from the odometry pose of then.
- ``ScanMapPlan``: A* (``curlnav.nav.global_planners.oracle.astar``, unknown cells free) on the grid with
  every cell nearer than the robot's half-width plus ``margin_m`` to an occupied one blocked (no
  path: 0.8 of the half-width, as a gap the coarse grid narrows may still let the base through)
  and a cost rising toward the walls within ``inflation_m``, planned again every ``replan_steps``
  steps from where the robot is, and sooner (2 steps after the last plan at the earliest) when a wall
  seen since comes nearer the path's next ``distance_m`` than it was planned with;
  the waypoint is ``distance_m`` ahead along the path, pulled back until the straight line to it
  crosses no blocked cell. Without a path the last one stands; before
  the first, the waypoint is the goal itself. With ``goal_distance`` the policy is shown the
  waypoint's direction at the goal's distance: a policy trained on far goals slows near one.
- ``ScanMapPlanAgent``: the policy's goal block rewritten to describe the waypoint
  (``GlobalPlanAgent.observation``), as behind the oracle's plan. With ``engage_after_steps`` (0 by
  default; set in Python, ``ScanMapConfig``) the policy keeps its own goal until it has come no
  nearer to it, by ``progress_m``, for that many steps, and the waypoints take over from then on.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from curlnav.layout import ObservationLayout, beam_angles
from curlnav.nav.geometry import goal_in_robot_frame, odometry
from curlnav.nav.global_planners.global_plan import GlobalPlanAgent
from curlnav.nav.global_planners.oracle import astar
from curlnav.nav.safety.push_check import PushCheck, PushConfig
from curlnav.sim import EnvConfig, StartGoal, World


@dataclass(frozen=True)
class ScanMapConfig:
    """The scan map's and its plan's settings (m, steps, scores)."""

    resolution_m: float = 0.1  # cell side (coarsened so that the grid stays within max_cells a side)
    max_cells: int = 600  # cells along the longer side of the grid at most
    padding_m: float = 6.0  # room round the robot and the goal
    hit: float = 1.0  # score added by a static return in a cell
    miss: float = 0.3  # score taken by a beam passing through a cell
    score_min: float = -2.0
    score_max: float = 5.0
    occupied: float = 1.5  # a cell above this score is occupied: hit in two scans (a spurious return is not)
    #: score taken, once a scan, from each cell a movable return ends in (a ball the segmenter missed once is no wall)
    movable: float = 1.0
    clear_range_m: float = 4.0  # beams clear the cells they pass up to this range
    margin_m: float = 0.05  # added to the half-width: cells nearer an occupied one are blocked for the plan
    inflation_m: float = 0.6  # from an occupied cell, within which a step costs more
    inflation_weight: float = 3.0  # extra cost per unit of step length at the blocked boundary
    distance_m: float = 2.0  # the waypoint lies this far ahead along the path
    goal_distance: bool = True  # the policy sees the waypoint's direction at the goal's distance
    replan_steps: int = 5  # plan again every this many control steps, and whenever the path ahead is blocked
    engage_after_steps: int = 0  # 0: waypoints from the start; else once the goal came no nearer for this many steps
    progress_m: float = 0.5  # "nearer": by this much (m) than the best so far

    def __post_init__(self) -> None:
        for name in ("resolution_m", "padding_m", "hit", "miss", "movable", "clear_range_m", "inflation_m", "distance_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"scan map: {name} must be a positive number, got {value!r}")
        if not (isinstance(self.max_cells, int) and 16 <= self.max_cells <= 4000):
            raise ValueError(f"scan map: max_cells must be a whole number 16-4000, got {self.max_cells!r}")
        if not (isinstance(self.engage_after_steps, int) and self.engage_after_steps >= 0):
            raise ValueError(f"scan map: engage_after_steps must be a whole number of at least 0, "
                             f"got {self.engage_after_steps!r}")
        if not (isinstance(self.replan_steps, int) and self.replan_steps >= 1):
            raise ValueError(f"scan map: replan_steps must be a whole number of at least 1, got {self.replan_steps!r}")
        if not self.score_min < self.occupied < self.score_max:
            raise ValueError("scan map: score_min < occupied < score_max is needed")


class ScanMap:
    """An occupancy grid in the odometry frame, filled from scans (module docstring). Cell
    ``(iy, ix)`` covers ``origin + (ix, iy) * resolution`` to one cell further (m)."""

    def __init__(self, centre: tuple[float, float], span_m: float, config: ScanMapConfig,
                 beam_angles: np.ndarray, max_range: float) -> None:
        self.config = config
        self.resolution = max(config.resolution_m, span_m / config.max_cells)
        self.cells = int(math.ceil(span_m / self.resolution))
        self.origin = np.array([centre[0] - self.cells * self.resolution / 2,
                                centre[1] - self.cells * self.resolution / 2])
        self.score = np.zeros((self.cells, self.cells), dtype=np.float32)
        self.beam_angles = np.asarray(beam_angles, dtype=np.float64)
        self.max_range = float(max_range)
        steps = int(math.ceil(config.clear_range_m / (0.5 * self.resolution)))
        self._distances = (np.arange(steps) + 0.5) * (config.clear_range_m / steps)  # m along each beam

    def cell_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(iy, ix, inside)`` of map-frame points ``(n, 2)`` (m)."""
        ij = np.floor((points - self.origin) / self.resolution).astype(np.int64)
        inside = (ij >= 0).all(axis=1) & (ij < self.cells).all(axis=1)
        return ij[:, 1], ij[:, 0], inside

    def flat_cells(self, points: np.ndarray) -> np.ndarray:
        """The distinct flat indices (into ``score.ravel()``) of the cells holding map-frame points
        ``(n, 2)`` (m); points off the grid are left out."""
        iy, ix, inside = self.cell_index(points)
        return np.unique(iy[inside] * self.cells + ix[inside])

    def centre_of(self, iy: int, ix: int) -> tuple[float, float]:
        return (float(self.origin[0] + (ix + 0.5) * self.resolution), float(self.origin[1] + (iy + 0.5) * self.resolution))

    def add_scan(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> None:
        """Lay one scan (ranges m, labels 0 static / 1 movable) down from ``pose`` (x, y, yaw; m, rad)."""
        cfg = self.config
        x, y, yaw = pose
        r = np.asarray(ranges, dtype=np.float64)
        angles = self.beam_angles + yaw
        direction = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        returned = r < self.max_range - 1e-3
        # clearing: cells passed on the way to a return (not the return's own cell); a beam that returned
        # nothing clears nothing (a dropout must not open a wall, as in curlnav.nav.perception.scan_filter)
        reach = np.where(returned, np.minimum(r - self.resolution, cfg.clear_range_m), -1.0)
        along = np.broadcast_to(self._distances[None, :], (len(r), len(self._distances)))
        along = np.where(along <= reach[:, None], along, np.nan)
        pts = np.stack([x + along * direction[:, 0:1], y + along * direction[:, 1:2]], axis=-1).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        self.score.ravel()[self.flat_cells(pts)] -= cfg.miss
        labels = np.asarray(labels)
        ends = np.stack([x + r * direction[:, 0], y + r * direction[:, 1]], axis=1)  # where each beam returned
        # marking: static returns; unmarking: movable ones (the segmenter's vote against a wall in that cell)
        self.score.ravel()[self.flat_cells(ends[returned & (labels < 0.5)])] += cfg.hit
        self.score.ravel()[self.flat_cells(ends[returned & (labels >= 0.5)])] -= cfg.movable
        np.clip(self.score, cfg.score_min, cfg.score_max, out=self.score)

    @property
    def occupied(self) -> np.ndarray:
        return self.score > self.config.occupied


class ScanMapPlan:
    """A* on a ``ScanMap`` to a fixed goal (odometry frame), and the waypoint ahead on it."""

    def __init__(self, scan_map: ScanMap, goal: tuple[float, float], half_width: float) -> None:
        self.map = scan_map
        self.goal = (float(goal[0]), float(goal[1]))
        self.half_width = half_width
        self.path: np.ndarray | None = None  # (n, 2) m, odometry frame, the goal last
        self._blocked: np.ndarray | None = None
        self._lethal = half_width  # m, the clearance the current path was planned with
        self._along = np.zeros(0)  # m along the path at each point

    def replan(self, x: float, y: float) -> None:
        """Plan again from ``(x, y)`` on the map as it is now."""
        m, cfg = self.map, self.map.config
        occupied = m.occupied
        if occupied.any():
            clearance = ndimage.distance_transform_edt(~occupied) * m.resolution - 0.5 * m.resolution
        else:
            clearance = np.full(occupied.shape, np.inf)
        start = self._free_cell(x, y)
        goal = self._free_cell(*self.goal)
        for lethal in (self.half_width + cfg.margin_m, 0.8 * self.half_width):  # then squeezed: a gap the map makes too narrow
            blocked = clearance <= lethal
            span = max(cfg.inflation_m - lethal, 1e-6)
            cost = cfg.inflation_weight * np.clip((cfg.inflation_m - clearance) / span, 0.0, 1.0) ** 2
            search = blocked.copy()
            search[start] = False  # the robot's own cell is where it is, however near a wall
            search[goal] = False  # a goal beside a wall is still the goal
            # A* steps diagonally only past a free side cell, so it reaches exactly the 4-connected
            # free region of the start: when the goal lies outside it, say so at once instead of
            # searching the whole grid (up to a second of pure Python on a 300 x 300 grid)
            region, _ = ndimage.label(~search)
            cells = astar(search, start, goal, cost) if region[start] == region[goal] else None
            if cells is not None:
                break
        if cells is None:
            return  # no way through so far as the map knows: the last path stands (none: the goal itself)
        self._blocked, self._lethal = blocked, lethal
        points = np.array([m.centre_of(int(r), int(c)) for r, c in cells], dtype=np.float64)
        self.path = np.vstack([[x, y], points[1:], [self.goal]]) if len(points) > 1 else np.array([[x, y], self.goal])
        self._along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.path, axis=0).T))])

    def blocked_ahead(self, x: float, y: float) -> bool:
        """Whether the path's next ``distance_m`` from the point nearest ``(x, y)`` now passes nearer
        to an occupied cell than the clearance it was planned with (walls seen since)."""
        if self.path is None:
            return False
        m, cfg = self.map, self.map.config
        occupied = m.occupied
        k = self._nearest(x, y)
        within = self._along[k:] <= self._along[k] + cfg.distance_m
        ahead = self.path[k:][within]
        if within[-1]:
            ahead = ahead[:-1]  # the goal itself may lie beside a wall (it is planned to regardless)
        if not occupied.any() or len(ahead) < 2:
            return False
        iy, ix, inside = m.cell_index(ahead[1:])
        lethal = self._lethal  # as the path was planned: a squeezed path is not blocked by its own squeeze
        r = int(math.ceil(lethal / m.resolution))
        for a, b in zip(iy[inside], ix[inside]):
            y0, x0 = max(a - r, 0), max(b - r, 0)
            wy, wx = np.nonzero(occupied[y0:a + r + 1, x0:b + r + 1])
            if len(wy) and (np.hypot(wy + y0 - a, wx + x0 - b) * m.resolution - 0.5 * m.resolution <= lethal).any():
                return True
        return False

    def _free_cell(self, x: float, y: float) -> tuple[int, int]:
        iy, ix, _ = self.map.cell_index(np.array([[x, y]]))
        n = self.map.cells
        return int(min(max(iy[0], 0), n - 1)), int(min(max(ix[0], 0), n - 1))

    def _line_free(self, a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(math.ceil(np.hypot(*(b - a)) / (0.5 * self.map.resolution))) + 1)
        pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        iy, ix, inside = self.map.cell_index(pts)
        return bool(inside.all()) and not self._blocked[iy, ix][1:].any()

    def waypoint(self, x: float, y: float) -> tuple[float, float]:
        """The point ``distance_m`` ahead along the path from ``(x, y)``, pulled back to a line of
        sight; the goal when there is no path."""
        if self.path is None:
            return self.goal
        k = self._nearest(x, y)
        j = min(int(np.searchsorted(self._along, self._along[k] + self.map.config.distance_m)), len(self.path) - 1)
        here = np.array([x, y])
        while j > k + 1 and not self._line_free(here, self.path[j]):
            j -= 1
        return float(self.path[j][0]), float(self.path[j][1])

    def _nearest(self, x: float, y: float) -> int:
        """The index of the path point nearest ``(x, y)``."""
        return int(np.argmin(np.hypot(self.path[:, 0] - x, self.path[:, 1] - y)))


class _StretchedPlan:
    """A plan whose waypoint is moved along its direction from the robot to the goal's distance."""

    def __init__(self, plan: ScanMapPlan) -> None:
        self.plan = plan

    def waypoint(self, x: float, y: float) -> tuple[float, float]:
        wx, wy = self.plan.waypoint(x, y)
        near = math.hypot(wx - x, wy - y)
        far = math.hypot(self.plan.goal[0] - x, self.plan.goal[1] - y)
        if near < 1e-6 or far <= near:
            return wx, wy
        k = far / near
        return x + k * (wx - x), y + k * (wy - y)


class ScanMapPlanAgent(GlobalPlanAgent):
    """A policy behind a plan on the map of its own scans (module docstring):
    ``act(observation, info) -> action``; ``info["odometry"]`` (else ``info["pose"]``) is the only
    pose it uses. ``push``: the push check's settings (default ``PushConfig()``; the arm's extension
    is the command sent last: ``commanded``, else the action it returned)."""

    control_role = "scan-map"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    def __init__(self, policy, env_config: EnvConfig | None = None, config: ScanMapConfig | None = None,
                 label: str = "policy", push: PushConfig | None = None) -> None:
        super().__init__(policy, env_config, label=label)
        self.push = PushCheck(self.env_config, push)
        self.label = f"{label} + scan-map plan"
        self.map_config = config or ScanMapConfig()
        self.layout = ObservationLayout.from_env_config(self.env_config)
        self.beam_angles = beam_angles(self.env_config.lidar_fov, self.env_config.lidar_beams)
        latency = getattr(getattr(self.env_config, "sensor_noise", None), "latency_steps", 0) or 0
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=int(latency) + 1)
        self.map: ScanMap | None = None
        self._steps = 0
        self._planned_at = -1
        self._best = (math.inf, 0)  # (least distance to the goal so far (m), the step it was reached)
        self.engaged_at: int | None = None  # the step the waypoints took over (None: not yet)

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        """Start an episode: an empty map, made at the first step (the world and pair are not used)."""
        self.plan = None
        self.map = None
        self._goals = None
        self._poses.clear()
        self._steps = 0
        self._planned_at = -1  # the step of the last plan (-1: none yet)
        self._best = (math.inf, 0)
        self.engaged_at = None
        self.push.reset()
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)

    def commanded(self, action: np.ndarray) -> None:
        """The command the robot was sent this step (``DynamicWindowPlanner.commanded``), passed
        on to the agent behind the plan when it takes it; the push check's arm."""
        self.push.commanded(action)
        inner = getattr(self.policy, "commanded", None)
        if callable(inner):
            inner(action)

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        action = self._act(observation, info)
        self.push.commanded(action)  # what it asked for; a stack that sends another says so (commanded)
        return action

    def _act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        pose = odometry(info)
        self._poses.append(pose)
        seen_from = self._poses[0]
        ranges, labels, goal_frame = self.layout.newest_frame(np.asarray(observation))
        if self.plan is None:
            gx, gy = goal_in_robot_frame(goal_frame)
            c, s = math.cos(seen_from[2]), math.sin(seen_from[2])
            goal = (seen_from[0] + c * gx - s * gy, seen_from[1] + s * gx + c * gy)
            span = 2 * self.map_config.padding_m + max(abs(goal[0] - pose[0]), abs(goal[1] - pose[1]))
            centre = ((goal[0] + pose[0]) / 2, (goal[1] + pose[1]) / 2)
            self.map = ScanMap(centre, span, self.map_config, self.beam_angles, self.env_config.lidar_max_range)
            self.plan = ScanMapPlan(self.map, goal, self.env_config.robot.base_width / 2)
        self.push.update(ranges, labels, seen_from)  # follows the pushes, so that it holds what stays put
        static = self.push.static(ranges, labels, seen_from)
        self.map.add_scan(ranges, np.where(static, 0.0, labels), seen_from)  # movable, but known not to be: static
        cfg = self.map_config
        if self.engaged_at is None:
            to_go = math.hypot(self.plan.goal[0] - pose[0], self.plan.goal[1] - pose[1])
            if to_go < self._best[0] - cfg.progress_m:
                self._best = (to_go, self._steps)
            if self._steps - self._best[1] >= cfg.engage_after_steps:
                self.engaged_at = self._steps
            else:
                self._steps += 1
                act = getattr(self.policy, "act", None)
                return self.policy(observation) if act is None else act(observation, info)
        due = self._steps - self._planned_at >= self.map_config.replan_steps
        if self._planned_at < 0 or due or (self._steps - self._planned_at >= 2 and self.plan.blocked_ahead(pose[0], pose[1])):
            self.plan.replan(pose[0], pose[1])
            self._planned_at = self._steps
        self._steps += 1
        planned = self.plan
        if self.map_config.goal_distance:
            self.plan = _StretchedPlan(planned)
        try:
            inner = self.observation(observation, pose)
        finally:
            self.plan = planned
        act = getattr(self.policy, "act", None)
        return self.policy(inner) if act is None else act(inner, info)
