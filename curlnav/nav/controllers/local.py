"""Map-less classical local planners: the baselines that see what the policy sees.

Both drive the robot from the policy's own inputs and nothing else: the newest LiDAR scan
(241 beams, -120..+120 deg), its labels, the goal in the robot frame (decoded from the
observation's goal block) and odometry (``info["odometry"]``, the drifting estimate under sensor
noise, else ``info["pose"]``; used only as the motion over a few steps). They keep no map and
nothing between episodes; ``reset(world, pair)`` ignores both arguments (the protocol's
``EpisodeAgent`` interface). Beams labelled movable are ignored, as the paper forced TARE-L to:
the planners push balls, boxes and doors with the base. The arm stays retracted (L = 0).

Their scans go through a short memory of marked and cleared cells in the odometry frame
(``curlnav.nav.perception.scan_filter.ScanMemory``: spatial support, voting over the last 5 scans,
clearing by the beams that pass), as a real stack's costmap: range noise, dropouts and spurious
returns do not stop them. ``scan_filter=None`` gives the raw-scan planners of before issue 37.

- ``TareLocalPlanner`` (``tare-l``), after the local planner of CMU's
  autonomous_exploration_development_environment (TARE's local planner, "TARE-L" in the paper):

  - a precomputed library of path primitives (``PathLibrary``): 7 groups of 49 paths of 3 m,
    fanned ahead of the robot, the whole fan rotated in steps of 10 deg;
  - a path is blocked when a static obstacle point falls in the footprint swept along it (a
    lookup table from a cell to the paths whose swept footprint covers it, built once);
  - the free paths are scored by how close their end direction lies to the goal's and by how
    little the robot must turn first, and summed per group: a group with many free paths (room
    on both sides: clearance) beats one that grazes a wall; the best group's first metre is the
    path to follow. When no path is free the range shrinks (3 m down to 1 m), then it stops;
  - a path follower on odometry: pure pursuit of the point ``lookahead_m`` ahead, turning in
    place when the path's direction lies more than ``turn_in_place_rad`` off the heading, never
    turning into a static point within its circumscribed circle.

- ``DynamicWindowPlanner`` (``dwa``): the dynamic window approach (Fox, Burgard and Thrun 1997,
  as ROS's ``dwa_local_planner``): velocities reachable within one control period under the
  acceleration limits are sampled, each simulated for ``sim_time_s``, those whose footprint
  meets a static scan point dropped, the rest scored by heading to the goal, progress toward
  it (ROS's goal distance, map-less), clearance and speed.

Both are defeated by a trap deeper than their range (a U between start and goal), as the
paper's TARE-L was; ``curlnav.nav.global_planners.oracle.StaticMapPlanner`` (``oracle``), with the true
map and pose, is the upper bound.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from curlnav.nav.geometry import arc_poses, footprint_clearance, odometry, wrap
from curlnav.nav.perception.scan_agent import ScanAgent
from curlnav.nav.perception.scan_filter import ScanFilterConfig
from curlnav.sim import EnvConfig, StartGoal, World

TARE_LABEL = "tare-l"
DWA_LABEL = "dwa"


# -- TARE's local planner ------------------------------------------------------------------------------
@dataclass(frozen=True)
class TareConfig:
    """``tare-l``'s settings (m, rad; the values of CMU's local_planner where they carry over)."""

    segment_m: float = 1.0  # each path: three segments of this length
    fan_deg: float = 27.0  # the first segment's end spans +-fan_deg in 7 steps; later ones +-fan*scale**k
    fan_scale: float = 0.65
    rotation_step_deg: float = 10.0  # the fan is rotated in these steps all round
    direction_threshold_deg: float = 90.0  # rotations further than this from the goal's direction are not tried
    direction_weight: float = 0.02  # score (1 - (w * |end direction - goal direction| in deg) ** 0.25)
    direction_floor: float = 0.05  # ... but at least this: blocked toward the goal, it follows the wall
    path_range_m: float = 3.0  # scan points further than this are ignored
    min_path_range_m: float = 1.0  # when no path is free the range shrinks, in steps, down to this
    path_range_step_m: float = 0.5
    goal_clear_m: float = 0.5  # scan points further than the goal plus this are ignored
    margin_m: float = 0.15  # the swept footprint: the base plus this on every side
    cell_m: float = 0.1  # the lookup table's cells
    lookahead_m: float = 0.5  # path follower
    turn_in_place_rad: float = math.radians(25.0)  # turn in place when the path lies further off
    yaw_gain: float = 2.5  # rad/s per rad of heading error
    slow_down_m: float = 1.0  # slow down within this of the path's end
    rotation_margin_m: float = 0.05  # never turn a corner of the base into a point this close


@dataclass(frozen=True)
class PathLibrary:
    """The precomputed path primitives and their lookup table (see ``build_library``).

    ``paths``: ``(P, S, 2)`` points (m) of P paths along the +x axis, S samples each;
    ``group``: ``(P,)`` group of each path (the direction of its first segment);
    ``end_direction``: ``(P,)`` direction (rad) of each path's end point;
    ``starts``: ``(G, S0, 2)`` each group's first segment, the path the follower tracks;
    ``blocks``: ``(rows * cols, P)`` bool, which paths a point in a cell of the table blocks;
    ``origin`` / ``shape`` / ``cell``: the table's lower-left corner (m), ``(rows, cols)``, cell (m).
    """

    paths: np.ndarray
    group: np.ndarray
    end_direction: np.ndarray
    starts: np.ndarray
    blocks: np.ndarray
    origin: tuple[float, float]
    shape: tuple[int, int]
    cell: float

    def cells_of(self, points: np.ndarray) -> np.ndarray:
        """Flat table index of each point ``(..., 2)`` (m), -1 outside the table."""
        ix = np.floor((points[..., 0] - self.origin[0]) / self.cell).astype(np.int64)
        iy = np.floor((points[..., 1] - self.origin[1]) / self.cell).astype(np.int64)
        rows, cols = self.shape
        inside = (ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)
        return np.where(inside, iy * cols + ix, -1)


def _polar_path(shifts_deg: list[float], segment: float, step: float = 0.05) -> np.ndarray:
    """Points of a path whose polar angle goes linearly from 0 at the robot through
    ``shifts_deg[k]`` at ``(k + 1) * segment`` m."""
    r = np.arange(0.0, segment * len(shifts_deg) + 1e-9, step)
    theta = np.radians(np.interp(r, segment * np.arange(len(shifts_deg) + 1), [0.0, *shifts_deg]))
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1)


@functools.lru_cache(maxsize=8)
def build_library(config: TareConfig, half_length: float, half_width: float) -> PathLibrary:
    """The path library of ``config`` for a base of ``half_length`` x ``half_width`` (m),
    built once per process (about 0.3 s)."""
    fan = np.linspace(-1.0, 1.0, 7)
    paths, groups, starts = [], [], []
    for g, s1 in enumerate(config.fan_deg * fan):
        starts.append(_polar_path([s1], config.segment_m))
        for s2 in s1 + config.fan_deg * config.fan_scale * fan:
            for s3 in s2 + config.fan_deg * config.fan_scale ** 2 * fan:
                paths.append(_polar_path([s1, s2, s3], config.segment_m))
                groups.append(g)
    paths_a = np.stack(paths)  # (P, S, 2)
    end_direction = np.arctan2(paths_a[:, -1, 1], paths_a[:, -1, 0])
    # the footprint's poses along each path, every 0.1 m, heading along the path
    poses = paths_a[:, ::2]
    tangent = np.gradient(paths_a, axis=1)[:, ::2]
    heading = np.arctan2(tangent[..., 1], tangent[..., 0])
    heading[:, 0] = 0.0  # the robot starts along the fan's axis
    reach = config.segment_m * 3 + half_length + half_width + config.margin_m
    x0, y0 = -(half_length + config.margin_m + config.cell_m), -reach
    cols = int(math.ceil((reach - x0) / config.cell_m))
    rows = int(math.ceil(2 * reach / config.cell_m))
    cx = x0 + (np.arange(cols) + 0.5) * config.cell_m
    cy = y0 + (np.arange(rows) + 0.5) * config.cell_m
    centres = np.stack(np.meshgrid(cx, cy), axis=-1).reshape(-1, 2)  # row-major, as cells_of
    hl = half_length + config.margin_m + config.cell_m / 2  # a cell blocks when any of it may be inside
    hw = half_width + config.margin_m + config.cell_m / 2
    blocks = np.zeros((len(centres), len(paths_a)), dtype=bool)
    for p in range(len(paths_a)):
        c, s = np.cos(heading[p]), np.sin(heading[p])  # (K,)
        dx = centres[:, None, 0] - poses[p, None, :, 0]
        dy = centres[:, None, 1] - poses[p, None, :, 1]
        inside = (np.abs(c * dx + s * dy) <= hl) & (np.abs(-s * dx + c * dy) <= hw)
        blocks[:, p] = inside.any(axis=1)
    return PathLibrary(paths_a, np.array(groups), end_direction, np.stack(starts), blocks, (x0, y0),
                       (rows, cols), config.cell_m)


class TareLocalPlanner(ScanAgent):
    """A map-less local planner after TARE's (see the module docstring):
    ``act(observation, info) -> [v, w, 0]``."""

    control_role = "tare-l"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    label = TARE_LABEL

    def __init__(self, env_config: EnvConfig | None = None, config: TareConfig | None = None,
                 scan_filter: ScanFilterConfig | None = ScanFilterConfig()) -> None:
        super().__init__(env_config, scan_filter)
        self.config = config or TareConfig()
        self.library = build_library(self.config, self.half_length, self.half_width)
        step = self.config.rotation_step_deg
        self.rotations = np.radians(np.arange(-180.0, 180.0, step))  # (R,) rad
        # a path's weight for the turn it needs first: 1 at 90 deg or more, growing to 10 straight ahead
        turn_deg = np.abs(np.degrees(self.rotations))
        self.rotation_weight = np.maximum(1.0, 10.0 - turn_deg / step) ** 4
        corner = math.hypot(self.half_length, self.half_width)
        self._corner_radius = corner + self.config.rotation_margin_m
        self._corner_angle = math.atan2(self.half_width, self.half_length)
        self.path: np.ndarray | None = None  # (n, 2) the path being followed, robot frame when chosen (m)
        self._chosen_at: tuple[float, float, float] | None = None  # odometry pose when it was chosen

    def reset(self, world: World, pair: StartGoal) -> None:
        super().reset(world, pair)
        self.path, self._chosen_at = None, None

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        points, gx, gy = self.sense(observation, info)  # every scan goes into the memory
        pose = odometry(info)  # only the motion since the path was chosen is used
        if self.path is not None and self._chosen_at is not None:
            # a turn in place toward the chosen path is finished before choosing again, so the
            # choice cannot flip between two sides of an obstacle at every step
            action = self.follow(self.path, self._since(pose), math.hypot(gx, gy))
            if action[0] == 0.0 and action[1] != 0.0:
                return action
        self.path, self._chosen_at = self.choose_path(points, gx, gy), pose
        if self.path is None or len(self.path) < 2:
            return self.action(0.0, 0.0)  # trapped: no free path (TARE's planner publishes a 1-point path)
        return self.follow(self.path, (0.0, 0.0, 0.0), math.hypot(gx, gy))

    def _since(self, pose: tuple[float, float, float]) -> tuple[float, float, float]:
        """The motion from where the path was chosen to ``pose``, in the frame of the former."""
        x0, y0, yaw0 = self._chosen_at
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy = pose[0] - x0, pose[1] - y0
        return c * dx + s * dy, -s * dx + c * dy, float(wrap(pose[2] - yaw0))

    def rotation_limits(self, points: np.ndarray) -> tuple[float, float]:
        """How far (rad) the base can turn clockwise (negative) and counter-clockwise before a
        corner meets a static point within its circumscribed circle (CMU's checkRotObstacle)."""
        d = np.hypot(points[:, 0], points[:, 1])
        outside = (np.abs(points[:, 0]) > self.half_length) | (np.abs(points[:, 1]) > self.half_width)
        near = points[(d < self._corner_radius) & outside]
        cw, ccw = -math.pi, math.pi
        for x, y in near:
            a = math.atan2(y, x)
            if a > 0:  # on the left: the front-left corner turns into it, or the rear-left one going clockwise
                ccw = min(ccw, a - self._corner_angle)
                cw = max(cw, a + self._corner_angle - math.pi)
            else:
                cw = max(cw, a + self._corner_angle)
                ccw = min(ccw, math.pi + a - self._corner_angle)
        return min(cw, 0.0), max(ccw, 0.0)

    def choose_path(self, points: np.ndarray, gx: float, gy: float) -> np.ndarray | None:
        """The first segment (``(n, 2)``, robot frame, m) of the best free group toward the goal
        ``(gx, gy)`` (m, robot frame), cropped at the range and the goal; None when none is free."""
        cfg, lib = self.config, self.library
        goal_distance = math.hypot(gx, gy)
        goal_direction = math.atan2(gy, gx)
        off_goal = np.abs(wrap(self.rotations - goal_direction))
        cw, ccw = self.rotation_limits(points)
        tried = (off_goal <= math.radians(cfg.direction_threshold_deg)) & (self.rotations > cw) & (self.rotations < ccw)
        rotations = np.flatnonzero(tried)
        if rotations.size == 0:
            return None
        d = np.hypot(points[:, 0], points[:, 1])
        inside_now = (np.abs(points[:, 0]) <= self.half_length + cfg.margin_m) & \
                     (np.abs(points[:, 1]) <= self.half_width + cfg.margin_m)  # already touching: moving on is the way out
        # how close each path ends to the goal's direction, and how far the robot turns first
        diff = np.degrees(np.abs(wrap(goal_direction - self.rotations[rotations, None] - lib.end_direction[None, :])))
        score = (1.0 - np.sqrt(np.sqrt(cfg.direction_weight * diff))) * self.rotation_weight[rotations, None]
        score = np.maximum(score, cfg.direction_floor * self.rotation_weight[rotations, None])  # (R', P)
        path_range = cfg.path_range_m
        while path_range >= cfg.min_path_range_m - 1e-9:
            used = points[(d < path_range) & (d <= goal_distance + cfg.goal_clear_m) & ~inside_now]
            blocked = np.zeros((rotations.size, lib.paths.shape[0]), dtype=bool)
            if len(used):
                rot = self.rotations[rotations]
                c, s = np.cos(rot)[:, None], np.sin(rot)[:, None]
                local = np.stack([c * used[None, :, 0] + s * used[None, :, 1],
                                  -s * used[None, :, 0] + c * used[None, :, 1]], axis=-1)  # (R', n, 2)
                cells = lib.cells_of(local)
                hit = cells >= 0
                for k in range(rotations.size):
                    if hit[k].any():
                        blocked[k] = lib.blocks[cells[k, hit[k]]].any(axis=0)
            group_score = np.zeros((rotations.size, lib.starts.shape[0]))
            for g in range(lib.starts.shape[0]):
                members = lib.group == g
                group_score[:, g] = np.where(blocked[:, members], 0.0, score[:, members]).sum(axis=1)
            if group_score.max() > 0:
                k, g = np.unravel_index(int(np.argmax(group_score)), group_score.shape)
                rot = self.rotations[rotations[k]]
                start = lib.starts[g]
                keep = np.hypot(start[:, 0], start[:, 1]) <= min(path_range, goal_distance)
                start = start[keep]
                c, s = math.cos(rot), math.sin(rot)
                return np.stack([c * start[:, 0] - s * start[:, 1], s * start[:, 0] + c * start[:, 1]], axis=1)
            path_range -= cfg.path_range_step_m
        return None

    def follow(self, path: np.ndarray, odometry: tuple[float, float, float], goal_distance: float) -> np.ndarray:
        """Pure pursuit of ``path`` (robot frame when it was chosen, m), the robot having moved
        by ``odometry`` (x, y, yaw: m, rad, in that frame) since (CMU's pathFollower)."""
        cfg = self.config
        robot = self.env_config.robot
        ox, oy, oyaw = odometry
        c, s = math.cos(oyaw), math.sin(oyaw)
        rel = np.stack([c * (path[:, 0] - ox) + s * (path[:, 1] - oy),
                        -s * (path[:, 0] - ox) + c * (path[:, 1] - oy)], axis=1)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ahead = np.flatnonzero(dist >= cfg.lookahead_m)
        target = rel[ahead[0]] if ahead.size else rel[-1]
        heading_error = math.atan2(target[1], target[0])
        w = float(np.clip(cfg.yaw_gain * heading_error, -robot.max_angular_speed, robot.max_angular_speed))
        if abs(heading_error) > cfg.turn_in_place_rad:
            return self.action(0.0, w)
        end = float(dist[-1])
        v = robot.max_linear_speed * min(1.0, max(end, min(goal_distance, cfg.slow_down_m)) / cfg.slow_down_m)
        v *= math.cos(heading_error)
        return self.action(v, w)


# -- the dynamic window approach ------------------------------------------------------------------------
@dataclass(frozen=True)
class DwaConfig:
    """``dwa``'s settings (m, s, rad; ROS's dwa_local_planner defaults where they carry over)."""

    acc_lim_x: float = 2.5  # m/s^2
    acc_lim_theta: float = 3.2  # rad/s^2
    v_samples: int = 5
    w_samples: int = 15
    sim_time_s: float = 1.6
    sim_dt_s: float = 0.2
    heading_weight: float = 0.6  # 1 - |goal bearing from the trajectory's end| / pi
    progress_weight: float = 1.0  # how much nearer the goal the trajectory ends / (max speed * sim_time_s): ROS's goal distance
    clearance_weight: float = 0.3  # the trajectory's least distance to a static point / clearance_cap_m
    speed_weight: float = 0.2  # v / max speed
    clearance_cap_m: float = 0.4  # clearance beyond this scores no more
    margin_m: float = 0.1  # a trajectory is dropped when its footprint comes this close to a static point
    ignore_beyond_m: float = 2.6  # static points further than this cannot matter within sim_time_s
    #: also sample backing up (down to the robot's ``max_reverse_speed``; ROS's negative min_vel_x):
    #: off for the baseline, on for the rescue (``curlnav.nav.recovery.rescue``) where its
    #: ``RescueConfig.reverse`` asks (``policies/barn-jackal``'s does), to get a robot out of a spot
    #: where no forward arc keeps the margin
    reverse: bool = False


class DynamicWindowPlanner(ScanAgent):
    """The dynamic window approach on the scan, map-less (see the module docstring):
    ``act(observation, info) -> [v, w, 0]``."""

    control_role = "dwa"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    label = DWA_LABEL

    def __init__(self, env_config: EnvConfig | None = None, config: DwaConfig | None = None,
                 scan_filter: ScanFilterConfig | None = ScanFilterConfig()) -> None:
        super().__init__(env_config, scan_filter)
        self.config = config or DwaConfig()
        self._velocity = (0.0, 0.0)  # last command (m/s, rad/s): the window's centre

    def reset(self, world: World, pair: StartGoal) -> None:
        super().reset(world, pair)
        self._velocity = (0.0, 0.0)

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        points, gx, gy = self.sense(observation, info)
        v, w = self.choose(points, gx, gy)
        self._velocity = (v, w)
        return self.action(v, w)

    def commanded(self, action: np.ndarray) -> None:
        """The command ``[v, w, L]`` (fractions) the robot was sent this step, when another agent
        chose it (``curlnav.nav.recovery.rescue``): the next window is centred on it."""
        robot = self.env_config.robot
        v, w = float(action[0]), float(action[1])
        if math.isfinite(v) and math.isfinite(w):
            self._velocity = (v * robot.max_linear_speed, w * robot.max_angular_speed)

    def window(self) -> tuple[np.ndarray, np.ndarray]:
        """The sampled speeds (m/s) and turn rates (rad/s) reachable within one control period."""
        cfg = self.config
        robot = self.env_config.robot
        dt = self.env_config.control_period
        v0, w0 = self._velocity
        slowest = -robot.max_reverse_speed if cfg.reverse else 0.0
        vs = np.linspace(max(slowest, v0 - cfg.acc_lim_x * dt), min(robot.max_linear_speed, v0 + cfg.acc_lim_x * dt),
                         cfg.v_samples)
        ws = np.linspace(max(-robot.max_angular_speed, w0 - cfg.acc_lim_theta * dt),
                         min(robot.max_angular_speed, w0 + cfg.acc_lim_theta * dt), cfg.w_samples)
        return vs, np.unique(np.concatenate([ws, [0.0]]))

    def choose(self, points: np.ndarray, gx: float, gy: float) -> tuple[float, float]:
        """The best admissible ``(v, w)`` (m/s, rad/s) toward the goal ``(gx, gy)`` (m, robot frame)."""
        cfg = self.config
        vs, ws = self.window()
        v, w = (a.ravel() for a in np.meshgrid(vs, ws))  # (N,)
        t = np.arange(1, int(round(cfg.sim_time_s / cfg.sim_dt_s)) + 1) * cfg.sim_dt_s  # (T,)
        x, y, th = arc_poses(v, w, t)  # (N, T)
        d = np.hypot(points[:, 0], points[:, 1])
        inside_now = (np.abs(points[:, 0]) <= self.half_length) & (np.abs(points[:, 1]) <= self.half_width)
        used = points[(d < cfg.ignore_beyond_m) & ~inside_now]
        clearance = footprint_clearance(used, v, w, t, self.half_length, self.half_width)
        admissible = clearance > cfg.margin_m
        # the goal's bearing from the trajectory's end pose
        ex, ey, eth = x[:, -1], y[:, -1], th[:, -1]
        bearing = wrap(np.arctan2(gy - ey, gx - ex) - eth)
        heading = 1.0 - np.abs(bearing) / math.pi
        progress = (math.hypot(gx, gy) - np.hypot(gx - ex, gy - ey)) / (self.env_config.robot.max_linear_speed * t[-1])
        score = (cfg.heading_weight * heading + cfg.progress_weight * progress
                 + cfg.clearance_weight * np.minimum(clearance, cfg.clearance_cap_m) / cfg.clearance_cap_m
                 + cfg.speed_weight * v / self.env_config.robot.max_linear_speed)
        if not admissible.any():
            return 0.0, 0.0  # no admissible velocity: stop (ROS would try its recovery behaviours)
        best = int(np.argmax(np.where(admissible, score, -np.inf)))
        return float(v[best]), float(w[best])
