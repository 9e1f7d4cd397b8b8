"""The classical upper bound in the same simulator: ``oracle``, A* on the true map, tracked on
the true pose.

``StaticMapPlanner`` (``curlnav eval oracle``; ``planner`` is the old name) was the stand-in for
TARE's local planner until the map-less baselines (``curlnav.nav.controllers.local``:
``tare-l``, ``dwa``) were written; it knows the static map and its pose exactly, so it bounds what
a local planner could do from above. It drives the same robot through the same ``NamoEnv``
interface, with the same action limits and the same observation:

- **Global planner** (``GridPlanner``): A* on the world's static occupancy grid, 8-connected. A cell is free
  when its centre lies more than the robot's half-width (plus
  ``clearance_margin_m``) from every obstacle cell (the inscribed radius, as a cost map's lethal
  layer: the circumscribed radius, 0.6 m for the Husky, would close the 1.1 m doorways); closer
  than ``inflation_m`` to a wall a step costs more (the inflation layer), so paths keep to the
  middle of corridors and doorways. Balls, boxes and door panels are not in the grid (door gaps
  are free there): the planner does not know them and pushes them with its base.
- **Local planner** (``StaticMapPlanner.act``): regulated pure pursuit of that path from the
  ground-truth pose (``info["pose"]``): steer along the arc through the point
  ``lookahead_m`` ahead on the path, turn in place when it lies more than ``turn_in_place_rad``
  off the heading, and cap the speed so that the footprint swept along the arc in
  ``horizon_s`` stops ``stop_margin_m`` short of every LiDAR hit on a *static* obstacle
  (beams labelled 0 in the newest frame; beams whose first hit is movable are ignored). When
  that arc is blocked (a wall right ahead), it takes the free arc nearest the path's direction,
  and when every arc is blocked it turns in place toward the path (it used to stop there for
  good: ``w = v * curvature`` is 0 when ``v`` is). It plans again from where it stands when
  pushed more than ``replan_deviation_m`` off the path.
- The arm stays retracted (L = 0).

Use it like a policy: ``agent.reset(world, pair)`` at the start of an episode, then
``agent.act(observation, info) -> action`` each step (``curlnav.evaluation.protocol.evaluate`` does both).

The same A* path feeds a learned local planner in ``curlnav.nav.global_planners.global_plan``
(``GlobalPlanAgent``, ``GlobalPlan``).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from curlnav.layout import ObservationLayout, beam_angles
from curlnav.sim import EnvConfig, StartGoal, World
from curlnav.worlds.core.pairs import clearance_map

ORACLE_LABEL = "oracle"
PLANNER_LABEL = ORACLE_LABEL  # the old name
SQRT2 = math.sqrt(2.0)
_STEPS = ((0, 1, 1.0), (1, 0, 1.0), (0, -1, 1.0), (-1, 0, 1.0),
          (1, 1, SQRT2), (1, -1, SQRT2), (-1, 1, SQRT2), (-1, -1, SQRT2))


@dataclass(frozen=True)
class PlannerConfig:
    """The oracle's settings (m, s, rad; speeds as fractions of the robot's limits)."""

    clearance_margin_m: float = 0.0  # added to the half-width: cells closer to a wall are blocked
    inflation_m: float = 0.9  # from a wall's edge, within which a step costs more
    inflation_weight: float = 3.0  # extra cost per unit of step length at the blocked boundary
    lookahead_m: float = 0.8  # pure-pursuit lookahead along the path
    speed: float = 1.0  # cruise speed, fraction of the robot's max linear speed
    turn_in_place_rad: float = math.radians(60.0)  # turn in place when the lookahead is further off
    horizon_s: float = 1.0  # look this far ahead along the commanded arc for static hits
    stop_margin_m: float = 0.1  # stop this short of a static hit
    replan_deviation_m: float = 1.0  # plan again when this far from the path
    min_speed: float = 0.05  # below this fraction of the max speed the pursuit arc counts as blocked
    max_curvature: float = 2.0  # 1/m, the sharpest arc tried when the pursuit arc is blocked
    min_free_m: float = 0.15  # an arc with less free length counts as blocked


def astar(blocked: np.ndarray, start: tuple[int, int], goal: tuple[int, int],
          cost: np.ndarray | None = None) -> np.ndarray | None:
    """A* over the free cells of ``blocked`` (bool, rows x cols), 8-connected, no diagonal step
    between two blocked cells. A step's cost is its length in cells times ``1 + cost[target cell]``
    (``cost >= 0``); the octile heuristic is admissible for it. Returns the ``(n, 2)`` cell path
    ``(iy, ix)`` from ``start`` to ``goal``, or None when there is none."""
    rows, cols = blocked.shape
    free = (~np.asarray(blocked, dtype=bool)).ravel().tolist()
    extra = cost.ravel().tolist() if cost is not None else None
    s, g = start[0] * cols + start[1], goal[0] * cols + goal[1]
    if not (free[s] and free[g]):
        return None
    gy, gx = goal

    def h(r: int, c: int) -> float:
        dr, dc = abs(r - gy), abs(c - gx)
        return (SQRT2 - 1.0) * min(dr, dc) + max(dr, dc)

    best = {s: 0.0}
    parent = {s: -1}
    closed = bytearray(rows * cols)
    heap = [(h(*start), 0.0, s)]
    while heap:
        _, cost_u, u = heapq.heappop(heap)
        if closed[u]:
            continue
        if u == g:
            break
        closed[u] = 1
        r, c = divmod(u, cols)
        for dr, dc, length in _STEPS:
            nr, nc = r + dr, c + dc
            if not (0 <= nr < rows and 0 <= nc < cols):
                continue
            v = nr * cols + nc
            if closed[v] or not free[v]:
                continue
            if dr and dc and not (free[r * cols + nc] or free[nr * cols + c]):
                continue  # no diagonal step between two blocked cells (as ``GridGraph``)
            cost_v = cost_u + length * (1.0 + extra[v] if extra is not None else 1.0)
            if cost_v < best.get(v, math.inf):
                best[v] = cost_v
                parent[v] = u
                heapq.heappush(heap, (cost_v + h(nr, nc), cost_v, v))
    if g not in parent:
        return None
    cells = [g]
    while cells[-1] != s:
        cells.append(parent[cells[-1]])
    cells.reverse()
    return np.array([divmod(n, cols) for n in cells], dtype=np.int64)


def polyline_length(points) -> float:
    """Length (m) of a polyline of ``(x, y)`` points (m)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return float(np.hypot(*np.diff(p, axis=0).T).sum()) if len(p) > 1 else 0.0


class GridPlanner:
    """Paths on one world's static grid for a robot of half-width ``half_width`` (m); see the
    module docstring. Points are map-frame metres."""

    def __init__(self, world: World, half_width: float, config: PlannerConfig | None = None,
                 clearance: np.ndarray | None = None) -> None:
        """``clearance``: the world's ``clearance_map``, where the caller has it already."""
        cfg = config or PlannerConfig()
        self.world = world
        clearance = clearance_map(world) if clearance is None else clearance
        lethal = half_width + cfg.clearance_margin_m
        self.blocked = clearance <= lethal
        span = max(cfg.inflation_m - lethal, 1e-6)
        self.cost = cfg.inflation_weight * np.clip((cfg.inflation_m - clearance) / span, 0.0, 1.0) ** 2
        self._nearest: np.ndarray | None = None

    def _free_cell(self, x: float, y: float) -> tuple[int, int]:
        """The cell of ``(x, y)``, or the nearest free cell when it is blocked or off the map."""
        rows, cols = self.blocked.shape
        iy, ix = self.world.cell_of(x, y)
        iy, ix = min(max(iy, 0), rows - 1), min(max(ix, 0), cols - 1)
        if self.blocked[iy, ix]:
            if self._nearest is None:
                _, self._nearest = ndimage.distance_transform_edt(self.blocked, return_indices=True)
            iy, ix = int(self._nearest[0, iy, ix]), int(self._nearest[1, iy, ix])
        return iy, ix

    def plan(self, start: tuple[float, float], goal: tuple[float, float], keep_off_walls: bool = True
             ) -> np.ndarray | None:
        """Points ``(n, 2)`` from the start's cell centre to ``goal`` itself, or None when the
        goal cannot be reached on the static grid. ``keep_off_walls``: with the inflation cost
        (tracking), else the shortest path on the grid."""
        cells = astar(self.blocked, self._free_cell(*start), self._free_cell(*goal),
                      self.cost if keep_off_walls else None)
        if cells is None:
            return None
        points = np.array([self.world.cell_centre(int(r), int(c)) for r, c in cells], dtype=np.float64)
        return np.vstack([points, [goal]])

    def _line_free(self, a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(math.ceil(np.hypot(*(b - a)) / (0.25 * self.world.resolution))) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        pts = a + t * (b - a)
        iy, ix = self.world.cells_of(pts[:, 0], pts[:, 1])
        rows, cols = self.blocked.shape
        if iy.min() < 0 or ix.min() < 0 or iy.max() >= rows or ix.max() >= cols:
            return False
        return not self.blocked[iy, ix].any()

    def shortest_path(self, start: tuple[float, float], goal: tuple[float, float]) -> np.ndarray | None:
        """The shortest path on the grid with its corners pulled tight along lines of sight
        (close to the any-angle shortest path): points ``(n, 2)``, or None when there is none."""
        path = self.plan(start, goal, keep_off_walls=False)
        if path is None:
            return None
        taut, i = [path[0]], 1
        while i < len(path):
            j = i
            while j + 1 < len(path) and self._line_free(taut[-1], path[j + 1]):
                j += 1
            taut.append(path[j])
            i = j + 1
        return np.array(taut)

    def shortest_length(self, start: tuple[float, float], goal: tuple[float, float]) -> float:
        """Length (m) of ``shortest_path``; ``nan`` when there is none."""
        path = self.shortest_path(start, goal)
        return float("nan") if path is None else polyline_length(path)


class StaticMapPlanner:
    """The oracle: A* on the true static map, pure pursuit on the true pose. ``reset(world, pair)``,
    then ``act(observation, info) -> action [v, w, L]`` (see the module docstring)."""

    control_role = "oracle"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    label = ORACLE_LABEL

    def __init__(self, env_config: EnvConfig | None = None, config: PlannerConfig | None = None) -> None:
        self.env_config = env_config or EnvConfig()
        self.config = config or PlannerConfig()
        self.layout = ObservationLayout.from_env_config(self.env_config)
        robot = self.env_config.robot
        self._half_length, self._half_width = robot.base_length / 2, robot.base_width / 2
        self._beam_angles = beam_angles(self.env_config.lidar_fov, self.env_config.lidar_beams)
        self._planners: dict[int, GridPlanner] = {}
        self.world: World | None = None
        self.pair: StartGoal | None = None
        self.path: np.ndarray | None = None  # (n, 2) map points, the goal last
        self._along: np.ndarray | None = None  # (n,) arc length from the first point (m)
        self._index = 0
        self._last_turn = 1.0  # the side of the last turn in place, kept while the path lies dead ahead

    def planner_for(self, world: World) -> GridPlanner:
        """The world's global planner (made once per world)."""
        key = id(world)
        if key not in self._planners or self._planners[key].world is not world:
            self._planners[key] = GridPlanner(world, self._half_width, self.config)
        return self._planners[key]

    def reset(self, world: World, pair: StartGoal) -> None:
        """Plan the episode's global path from the pair's start to its goal."""
        self.world, self.pair = world, pair
        self._last_turn = 1.0
        self._set_path(self.planner_for(world).plan((pair.x, pair.y), (pair.gx, pair.gy)))

    def clear(self) -> None:
        """Forget the episode (its path, place on it and side of the last turn in place), as
        ``reset`` does, without planning: a tracker of another agent's plan between episodes."""
        self._set_path(None)
        self._last_turn = 1.0

    def follow(self, world: World, pair: StartGoal, planner: GridPlanner, path: np.ndarray | None, index: int) -> None:
        """Track another agent's plan instead of planning its own: ``path`` (``(n, 2)`` map points,
        m, made by ``planner`` on ``world`` for ``pair``) from its point ``index`` on (call before
        each ``act``). A path the tracker planned again on its own is replaced by the given one."""
        self.world, self.pair = world, pair
        self._planners = {id(world): planner}
        if self.path is not path:
            self._set_path(path)
        if path is not None:
            self._index = min(max(int(index), 0), len(path) - 1)

    def _set_path(self, path: np.ndarray | None) -> None:
        self.path = path
        self._index = 0
        if path is not None:
            self._along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])  # m

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise TypeError("StaticMapPlanner needs the pose: call act(observation, info) after reset(world, pair)")

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        x, y, yaw = info["pose"]
        if self.path is None:
            return np.zeros(3, dtype=np.float32)  # the goal is unreachable on the static map: stay
        target = self._lookahead_point(x, y)
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = target[0] - x, target[1] - y
        fx, fy = c * dx + s * dy, -s * dx + c * dy  # the target in the robot frame
        alpha = math.atan2(fy, fx)
        robot = self.env_config.robot
        cfg = self.config
        if abs(alpha) > cfg.turn_in_place_rad:
            w = math.copysign(min(1.0, 1.5 * abs(alpha)), alpha)
            return np.array([0.0, w, 0.0], dtype=np.float32)
        curvature = 2.0 * fy / max(fx * fx + fy * fy, 1e-6)  # 1/m
        v = cfg.speed * robot.max_linear_speed  # m/s
        if abs(curvature) > 1e-9:
            v = min(v, robot.max_angular_speed / abs(curvature))
        ranges, labels, _ = self.layout.newest_frame(np.asarray(observation))
        v = min(v, self._free_arc(ranges, labels, curvature) / cfg.horizon_s)
        if v < cfg.min_speed * robot.max_linear_speed:
            v, curvature = self._way_round(ranges, labels, alpha)
            if v <= 0.0:  # every arc is blocked: turn in place toward the path (it froze here before)
                turn = alpha if abs(alpha) > 1e-3 else self._last_turn
                self._last_turn = math.copysign(1.0, turn)
                return np.array([0.0, math.copysign(min(1.0, max(0.5, 1.5 * abs(alpha))), turn), 0.0],
                                dtype=np.float32)
        w = v * curvature
        return np.array([v / robot.max_linear_speed, float(np.clip(w / robot.max_angular_speed, -1.0, 1.0)), 0.0],
                        dtype=np.float32)

    def _way_round(self, ranges: np.ndarray, labels: np.ndarray, alpha: float) -> tuple[float, float]:
        """When the pursuit arc is blocked: ``(v m/s, curvature 1/m)`` of the free arc whose
        direction after a metre lies nearest the path's (``alpha``, rad, robot frame); ``v = 0``
        when no arc is free for ``min_free_m``."""
        cfg = self.config
        robot = self.env_config.robot
        best, best_off = (0.0, 0.0), math.inf
        for curvature in np.linspace(-cfg.max_curvature, cfg.max_curvature, 13):
            free = self._free_arc(ranges, labels, float(curvature))
            if free < cfg.min_free_m:
                continue
            off = abs(math.atan2(math.sin(curvature - alpha), math.cos(curvature - alpha)))
            if off < best_off:
                v = min(cfg.speed * robot.max_linear_speed, free / cfg.horizon_s)
                if abs(curvature) > 1e-9:
                    v = min(v, robot.max_angular_speed / abs(curvature))
                best, best_off = (v, float(curvature)), off
        return best

    def _lookahead_point(self, x: float, y: float) -> np.ndarray:
        """Advance along the path to the point nearest the robot (within a window ahead, so a
        path that passes close to itself is not skipped), plan again when far off it, and return
        the point ``lookahead_m`` further along."""
        cfg = self.config
        k, distance = self._nearest_ahead(x, y)
        if distance > cfg.replan_deviation_m:
            replanned = self.planner_for(self.world).plan((x, y), (self.pair.gx, self.pair.gy))
            if replanned is not None:
                self._set_path(replanned)
                k, _ = self._nearest_ahead(x, y)
        self._index += k
        j = int(np.searchsorted(self._along, self._along[self._index] + cfg.lookahead_m))
        return self.path[min(j, len(self.path) - 1)]

    def _nearest_ahead(self, x: float, y: float) -> tuple[int, float]:
        """The path point nearest ``(x, y)`` among the next few metres: offset from the current
        index, distance (m)."""
        window = np.searchsorted(self._along, self._along[self._index] + 3.0 * self.config.lookahead_m + 1.0)
        ahead = self.path[self._index:max(window, self._index + 1)]
        d = np.hypot(ahead[:, 0] - x, ahead[:, 1] - y)
        k = int(np.argmin(d))
        return k, float(d[k])

    def _free_arc(self, ranges: np.ndarray, labels: np.ndarray, curvature: float) -> float:
        """How far (m) the base can drive along the arc of ``curvature`` before its footprint
        comes within ``stop_margin_m`` of a static LiDAR hit (hits already inside the footprint
        do not count: moving on is the way out)."""
        cfg = self.config
        static = (labels < 0.5) & (ranges < self.env_config.lidar_max_range - 1e-3)
        if not static.any():
            return math.inf
        r = ranges[static].astype(np.float64)
        a = self._beam_angles[static]
        px, py = r * np.cos(a), r * np.sin(a)  # hits in the robot frame (m)
        reach = cfg.speed * self.env_config.robot.max_linear_speed * cfg.horizon_s + cfg.stop_margin_m
        inside_now = self._in_front_footprint(px, py)
        step = 0.05
        for d in np.arange(step, reach + step, step):
            if abs(curvature) < 1e-6:
                ox, oy, th = d, 0.0, 0.0
            else:
                th = curvature * d
                ox, oy = math.sin(th) / curvature, (1.0 - math.cos(th)) / curvature
            c, s = math.cos(th), math.sin(th)
            qx, qy = c * (px - ox) + s * (py - oy), -s * (px - ox) + c * (py - oy)
            if (self._in_front_footprint(qx, qy) & ~inside_now).any():
                return max(d - step - cfg.stop_margin_m, 0.0)
        return math.inf

    def _in_front_footprint(self, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:
        """Which points (robot frame, m) lie in the front half of the base's footprint."""
        return (qx >= 0.0) & (qx <= self._half_length) & (np.abs(qy) <= self._half_width)
