"""A safety shield: a policy's command checked against the scan before the base executes it.

A learned policy drives well and, now and then, grazes an obstacle: on the BARN Challenge's worlds
most of ``policies/barn-jackal``'s failures are contacts of the rectangular base with a cylinder
while it turns in a tight gap, and the challenge ends a trial at the first one. Real stacks put a
last check between the planner and the wheels (Nav2's collision monitor, move_base's footprint
check of each command); ``ShieldedPolicy`` is that check for any ``obs -> action`` policy:

- each control step the policy proposes ``[v, w, L]`` (fractions of the robot's limits);
- the static obstacle points it is checked against are the scan's, through the same short memory
  of marked and cleared cells as the map-less planners' (``curlnav.nav.perception.scan_filter``), so
  the space behind the robot, outside the LiDAR's field of view, is remembered for a second;
- the command is simulated as an arc of constant ``(v, w)`` for ``horizon_s`` (the command is
  held one control period; the rest is the room needed to stop or turn away next step) and the
  footprint (the base's rectangle) is checked at every ``step_s`` along it;
- a command whose footprint keeps at least ``margin_m`` from every point (or, already nearer
  than that, does not come nearer) passes unchanged. Otherwise the admissible command nearest to
  the policy's (``v`` and ``w`` fractions, ``w`` weighted by ``turn_weight``) out of a grid of
  ``v_samples`` x ``w_samples`` replaces it, and when none is admissible the one that keeps the
  most clearance does. The arm value is passed through;
- behind a global plan (``static_map``) a turn on the spot (``v = 0``) needs only
  ``turn_margin_m`` (1.5 cm): a base wedged at an angle, a post a few centimetres ahead of its
  corner, gets out only by turning past it (the plan's trackers turn on the spot), and the sweep
  of a turn on the spot is known to the centimetre, with no speed to stop from. Map-less, turns
  keep ``margin_m``: there the scan memory alone says where the walls are, and on the validation
  floors the smaller margin bought nothing and added contacts under ``harsh`` senses
  (docs/results/archive.md);
- a policy that keeps asking for a blocked command is stuck behind it (it cannot back out: its
  speed is 0..1 of the top speed, forward). After ``stuck_steps`` replacements in a row that
  barely move the base, the shield drives ``recovery_steps`` steps itself, each the admissible
  command that ends with the most room round the base, as ``move_base`` runs its recovery
  behaviours, and hands back. With ``reverse_recovery``, on a robot that can reverse
  (``RobotConfig.max_reverse_speed``, the Husky's and the Jackal's 0.5 m/s), the recovery may back up, as Nav2's
  BackUp behaviour: a base that drove into a spot too tight to turn in gets out of it. A backing
  command from the policy's stack (the rescue's DWA) is checked like any other.

The shield uses what the policy's own robot has: the observation (scan, labels, goal) and
odometry (``info["odometry"]``, else ``info["pose"]``, over the memory's 5 scans only). It does not
trust the segmenter (``curlnav.nav.safety.push_check``): a return labelled movable near the base is an
obstacle like any other unless it is pushable: the robot has an arm, and the object lies on the arm's
side (ahead of the bumper, within the arm's reach) and pushes have not shown it staying put, or a
push showed it moving. A pushable return is no obstacle to a command at pushing speed
(``PushConfig.push_speed_mps``); a faster one keeps its margin from it, so a push goes on at pushing
speed. A wall called movable is held static after the arm's pushes leave it in place (the shield
checks the base's rectangle: the arm may touch it, the base stops short). Behind a global plan
(``static_map``), where the stack has the map and a localised pose (``info["pose"]``, as the plan
has: in the simulator the true pose, whatever the senses' noise), the walls of the map round the
base are checked too (``wall_outline``): the LiDAR does not see the 120 degrees behind the base,
where a turn on the spot swings its rear corners, nor a post thinner than the gap between two
beams.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from curlnav.nav.geometry import footprint_clearance, from_frame, odometry, to_frame
from curlnav.nav.perception.scan_agent import ScanAgent
from curlnav.nav.perception.scan_filter import ScanFilterConfig, ScanMemory
from curlnav.nav.registry import SHIELD_SUFFIX
from curlnav.nav.safety.push_check import PushCheck, PushConfig
from curlnav.sim import EnvConfig, StartGoal, World
from curlnav.sim.geometry import wall_faces


@dataclass(frozen=True)
class ShieldConfig:
    """The shield's settings (s, m, counts)."""

    horizon_s: float = 0.6  # how far ahead each command's arc is checked
    step_s: float = 0.05  # footprint checks along it, this far apart in time
    margin_m: float = 0.05  # a command is admissible when its footprint keeps this far from every point
    #: behind a global plan (``ShieldedPolicy(static_map=True)``), a turn on the spot (``v = 0``) is
    #: admissible when the footprint keeps this far: the rotation is what frees a base wedged at an
    #: angle, and its sweep is known to the centimetre (map-less: ``margin_m``)
    turn_margin_m: float = 0.015
    v_samples: int = 9  # linear speed fractions 0..1 of the replacement grid
    w_samples: int = 17  # turn rate fractions -1..1 of the replacement grid
    turn_weight: float = 0.5  # how much a change of turn rate counts against a change of speed
    ignore_beyond_m: float = 3.0  # points further than this cannot be reached within horizon_s
    stuck_steps: int = 5  # this many replaced commands in a row that barely move the base ...
    recovery_steps: int = 5  # ... and the shield drives this many steps itself, to the most room
    stuck_speed: float = 0.1  # "barely moves": a replacement's speed below this fraction
    #: the recovery may back up, on a robot that can (``RobotConfig.max_reverse_speed``). Off by
    #: default: the LiDAR does not see behind the base, and on the BARN validation courses a
    #: backing recovery once met a post it had passed more than a second before
    reverse_recovery: bool = False

    def times(self) -> np.ndarray:
        """``(T,)`` s, the checks along each command's arc: every ``step_s`` up to ``horizon_s``."""
        return np.arange(1, int(math.ceil(self.horizon_s / self.step_s - 1e-9)) + 1) * self.step_s

    def __post_init__(self) -> None:
        for name in ("horizon_s", "step_s", "margin_m", "turn_margin_m", "turn_weight", "ignore_beyond_m"):
            value = getattr(self, name)
            zero_ok = name in ("margin_m", "turn_margin_m", "turn_weight")
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value >= 0 and (value > 0 or zero_ok)):
                kind = "non-negative" if zero_ok else "positive"
                raise ValueError(f"shield: {name} must be a {kind} number, got {value!r}")
        for name in ("v_samples", "w_samples"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 2 <= value <= 101):
                raise ValueError(f"shield: {name} must be a whole number 2-101, got {value!r}")
        for name in ("stuck_steps", "recovery_steps"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 1000):
                raise ValueError(f"shield: {name} must be a whole number 0-1000 (0: no recovery), got {value!r}")
        if not isinstance(self.reverse_recovery, bool):
            raise ValueError(f"shield: reverse_recovery must be true or false, got {self.reverse_recovery!r}")
        if not (isinstance(self.stuck_speed, (int, float)) and 0 <= self.stuck_speed <= 1):
            raise ValueError(f"shield: stuck_speed must be a fraction 0-1, got {self.stuck_speed!r}")
        if self.step_s > self.horizon_s:
            raise ValueError(f"shield: step_s ({self.step_s}) must not exceed horizon_s ({self.horizon_s})")

    @classmethod
    def from_dict(cls, values: dict) -> ShieldConfig:
        """From a JSON/YAML mapping; unknown keys are refused by name."""
        if not isinstance(values, dict):
            raise ValueError(f"shield settings must be a mapping, got {type(values).__name__}")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"shield: unknown setting(s) {', '.join(map(str, unknown))}; known: {', '.join(sorted(known))}")
        return cls(**values)


#: the largest gap (m) between two points of ``wall_outline`` along a wall's face: a footprint's
#: distance to the points overstates its distance to the face by at most half of it
WALL_POINT_SPACING_M = 0.02


def wall_outline(world: World) -> np.ndarray:
    """``(n, 2)`` map-frame points (m) along every face between an occupied cell and a free one
    (``curlnav.sim.geometry.wall_faces``: beyond the grid counts as wall, the simulator's boundary
    walls, so a free cell on the grid's edge has its outer face too), at most
    ``WALL_POINT_SPACING_M`` apart, ends included."""
    horizontal, vertical = wall_faces(world.occupancy)
    res = world.resolution
    t = np.linspace(0.0, 1.0, max(1, math.ceil(res / WALL_POINT_SPACING_M - 1e-9)) + 1)
    rows, cols = np.nonzero(horizontal)  # along row boundary ``rows``, columns ``cols`` to ``cols + 1``
    along_rows = np.stack([((cols[:, None] + t) * res).ravel(), np.repeat(rows * res, len(t))], axis=1)
    rows, cols = np.nonzero(vertical)  # along column boundary ``cols``, rows ``rows`` to ``rows + 1``
    along_cols = np.stack([np.repeat(cols * res, len(t)), ((rows[:, None] + t) * res).ravel()], axis=1)
    u, v = np.concatenate([along_rows, along_cols]).T
    x, y = world.map_from_grid(u, v)
    return np.unique(np.round(np.stack([x, y], axis=1), 6), axis=0).reshape(-1, 2)


_WALL_TREE: tuple[World, cKDTree] | None = None  # the last world's, shared by the shield and the manoeuvre


def wall_tree(world: World) -> cKDTree:
    """``wall_outline(world)`` as a tree, built once for the world last asked for (a stack's
    shield and its rescue's manoeuvre both check the same map's walls)."""
    global _WALL_TREE
    if _WALL_TREE is None or _WALL_TREE[0] is not world:
        _WALL_TREE = (world, cKDTree(wall_outline(world)))
    return _WALL_TREE[1]


def walls_near(tree: cKDTree, pose: tuple[float, float, float], reach_m: float) -> np.ndarray:
    """``(n, 2)`` robot-frame points (m) of ``tree``'s (map frame) within ``reach_m`` of ``pose``
    (map frame: x, y m, yaw rad)."""
    x, y, yaw = pose
    near = tree.data[tree.query_ball_point([x, y], reach_m)]
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = near[:, 0] - x, near[:, 1] - y
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1).reshape(-1, 2)


class ArcRule:
    """The shield's rule for the arcs a base may drive from where it stands (module docstring):
    ``near`` ``(n, 2)`` are the points (m, robot frame) the base does not touch, ``touched`` the walls
    on or inside its outline, ``pushable`` the returns of an object the robot may push
    (``curlnav.nav.safety.push_check``). An arc is admissible when its footprint keeps ``margin_m``
    from ``near`` (a turn on the spot ``turn_margin_m``), or no less than it keeps now, presses no
    deeper into ``touched`` (signed clearance) and, faster than ``push_speed`` (m/s), keeps
    ``margin_m`` from ``pushable`` (a push goes at pushing speed). ``v``, ``w``: m/s, rad/s
    (``need``: any speed whose zero is a turn on the spot); ``times``: s along each arc."""

    def __init__(self, near: np.ndarray, touched: np.ndarray, half_length: float, half_width: float,
                 margin_m: float, turn_margin_m: float, pushable: np.ndarray | None = None,
                 push_speed: float = math.inf) -> None:
        self.near, self.touched = near, touched
        self.pushable = np.zeros((0, 2)) if pushable is None else pushable
        self.push_speed = push_speed
        self.half_length, self.half_width = half_length, half_width
        self.margin_m, self.turn_margin_m = margin_m, turn_margin_m
        zero = np.zeros(1)
        self.now = float(self.clearance(zero, zero, zero)[0])  # m, from ``near`` where the base stands
        self.pressed_now = float(self.pressed(zero, zero, zero)[0])  # m, signed, from ``touched`` (inf: none)

    def clearance(self, v: np.ndarray, w: np.ndarray, times: np.ndarray) -> np.ndarray:
        """m, each arc's least clearance from the points the base does not touch."""
        return footprint_clearance(self.near, v, w, times, self.half_length, self.half_width)

    def at_push_speed(self, v: np.ndarray, w: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Whether each arc is at pushing speed, or keeps ``margin_m`` from ``pushable``."""
        v = np.asarray(v, dtype=np.float64)
        out = (v <= self.push_speed + 1e-9) | (len(self.pushable) == 0)
        fast = ~out
        if fast.any():
            out[fast] = footprint_clearance(self.pushable, v[fast], np.asarray(w, dtype=np.float64)[fast], times,
                                            self.half_length, self.half_width) >= self.margin_m
        return out

    def pressed(self, v: np.ndarray, w: np.ndarray, times: np.ndarray) -> np.ndarray:
        """m, each arc's least signed clearance from the walls the base touches (inf: none)."""
        return footprint_clearance(self.touched, v, w, times, self.half_length, self.half_width, signed=True)

    def need(self, v) -> np.ndarray:
        """m, the clearance each arc of speed ``v`` must keep: its margin, or what the base keeps now."""
        return np.minimum(np.where(np.asarray(v) == 0.0, self.turn_margin_m, self.margin_m), self.now)

    def no_deeper(self, v: np.ndarray, w: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Whether each arc presses no deeper into a wall the base touches."""
        return self.pressed(v, w, times) >= self.pressed_now - 1e-9

    def admissible(self, v: np.ndarray, w: np.ndarray, times: np.ndarray,
                   clearance: np.ndarray | None = None) -> np.ndarray:
        """Whether each arc is admissible (``clearance``: ``self.clearance`` of the arcs, if known)."""
        clearance = self.clearance(v, w, times) if clearance is None else clearance
        return (clearance >= self.need(v)) & self.no_deeper(v, w, times) & self.at_push_speed(v, w, times)


class ShieldedPolicy(ScanAgent):
    """``policy`` (``obs -> [v, w, L]``, or an ``EpisodeAgent`` such as a policy behind a global
    plan) behind the safety shield (module docstring):
    ``act(observation, info) -> [v, w, L]``. ``interventions`` counts the commands replaced in
    the current episode, ``steps`` the commands checked; ``push`` is its push check; ``replaced``:
    whether the last command was replaced (``curlnav.nav.roles.chooser``)."""

    control_role = "shield"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    replaced = False

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], env_config: EnvConfig | None = None,
                 config: ShieldConfig | None = None, label: str | None = None,
                 scan_filter: ScanFilterConfig | None = ScanFilterConfig(), static_map: bool = False,
                 push: PushConfig | None = None) -> None:
        """``static_map``: also check the walls of the world's map round ``info["pose"]`` (module
        docstring; only a stack that has the map and a localised pose: behind a global plan);
        ``push``: when a movable label near the base is believed (default ``PushConfig()``)."""
        super().__init__(env_config, scan_filter)
        # one push check for the shield and its memory; the speed condition is the shield's, command by command
        self.push = PushCheck(self.env_config, push)
        if self.memory is not None:
            self.memory = ScanMemory(self.beam_angles, self.env_config.lidar_max_range, scan_filter, push=self.push)
        self.policy = policy
        self.static_map = static_map
        self._walls: tuple[World, cKDTree] | None = None  # the map's wall outline, for static_map
        self.config = config or ShieldConfig()
        self.label = label or f"{getattr(policy, 'label', 'policy')}{SHIELD_SUFFIX}"
        cfg = self.config
        robot = self.env_config.robot
        # m, the furthest a point can be from the base's centre and still be met within the horizon
        self._reach_m = min(cfg.ignore_beyond_m, robot.max_linear_speed * cfg.horizon_s
                            + math.hypot(self.half_length, self.half_width) + cfg.margin_m)
        self._times = cfg.times()
        vs = np.linspace(0.0, 1.0, cfg.v_samples)
        ws = np.linspace(-1.0, 1.0, cfg.w_samples)
        v, w = np.meshgrid(vs, ws)
        self._grid = np.stack([v.ravel(), w.ravel()], axis=1)  # (N, 2) fractions
        v, w = np.meshgrid([-1.0, -0.5], np.linspace(-1.0, 1.0, 5))
        self._reverse = np.stack([v.ravel(), w.ravel()], axis=1)  # backing up: fractions of the reverse limit, of w
        self.interventions = 0
        self.recoveries = 0
        self.steps = 0
        self._stuck = 0  # replaced commands in a row that barely moved the base
        self._recovering = 0  # steps of recovery left

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        super().reset(world, pair)
        if self.static_map and world is None:
            self._walls = None  # map_points refuses until a world is given
        elif self.static_map and (self._walls is None or self._walls[0] is not world):
            self._walls = (world, wall_tree(world))
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)
        self.interventions = 0
        self.recoveries = 0
        self.steps = 0
        self._stuck = 0
        self._recovering = 0
        self.push.reset()

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        points, _, _ = self.sense(observation, info)
        pose = odometry(info)
        if self.memory is None:  # the raw scan: its doubted movable returns are obstacles too
            points = np.concatenate([points, self._doubted(observation, pose)])
        pushable = self.push.pushable_in(pose)
        walls = self.map_points(info["pose"]) if self.static_map else None
        inner = getattr(self.policy, "act", None)
        proposed = self.policy(observation) if inner is None else inner(observation, info)
        proposed = np.asarray(proposed, dtype=np.float32).reshape(-1)
        self.steps += 1
        out = self.check(proposed, points, walls, pushable)
        self.replaced = out is not proposed  # check returns the proposal itself where it lets it pass
        self.push.commanded(out)
        return out

    def commanded(self, action: np.ndarray) -> None:
        """The command the robot was sent this step, where something after the shield changed it
        (the ROS 2 node's stops): the push check reckons with the arm the robot has out."""
        self.push.commanded(action)

    def _doubted(self, observation: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``(n, 2)`` robot-frame points (m) at ``pose`` of the newest scan's returns labelled movable
        that the push check does not believe (without a scan memory, which judges them itself)."""
        ranges, labels, _ = self.layout.newest_frame(np.asarray(observation))
        seen_from = self._poses[0]  # the pose the (possibly late) scan was taken from
        ranges = ranges.astype(np.float64)
        doubted = (ranges < self.env_config.lidar_max_range - 1e-3) & (labels >= 0.5) \
            & ~self.push.update(ranges, labels, seen_from)
        local = np.stack([ranges * np.cos(self.beam_angles), ranges * np.sin(self.beam_angles)], axis=1)[doubted]
        return from_frame(to_frame(local, seen_from), pose)

    def map_points(self, pose: tuple[float, float, float]) -> np.ndarray:
        """``(n, 2)`` robot-frame points (m) of the map's wall outline that a command can reach
        from ``pose`` (map frame: x, y m, yaw rad) within the horizon."""
        if self._walls is None:
            raise RuntimeError("ShieldedPolicy(static_map=True) needs reset(world, pair) first")
        return walls_near(self._walls[1], pose, self._reach_m)

    def check(self, proposed: np.ndarray, points: np.ndarray, walls: np.ndarray | None = None,
              pushable: np.ndarray | None = None) -> np.ndarray:
        """``proposed`` ``[v, w, L]`` (fractions) if its arc is admissible against ``points``
        ``(n, 2)`` (m, robot frame: the scan's), ``walls`` (the map's, behind a global plan) and,
        faster than pushing speed, ``pushable`` (the returns of what the robot is pushing), else its
        replacement (module docstring). A scan return inside the base is no obstacle (as dwa's:
        noise); a wall point on or inside its outline is a wall the base touches: a command may not
        press deeper into those (signed clearance, minus the depth inside), and keeps the margins
        from every other point."""
        cfg = self.config
        robot = self.env_config.robot
        hl, hw = self.half_length, self.half_width

        def reachable(p: np.ndarray) -> np.ndarray:
            """Those of scan points ``p`` ``(n, 2)`` within reach and not inside the base."""
            if len(p) == 0:
                return np.zeros((0, 2))
            inside = (np.abs(p[:, 0]) <= hl) & (np.abs(p[:, 1]) <= hw)
            return p[(np.hypot(p[:, 0], p[:, 1]) < self._reach_m) & ~inside]

        near = reachable(points)
        touched = np.zeros((0, 2))
        if walls is not None and len(walls):
            on_base = (np.abs(walls[:, 0]) <= hl) & (np.abs(walls[:, 1]) <= hw)
            near, touched = np.concatenate([near, walls[~on_base]]), walls[on_base]
        rule = ArcRule(near, touched, hl, hw, cfg.margin_m, cfg.turn_margin_m if self.static_map else cfg.margin_m,
                       pushable=None if pushable is None else reachable(pushable),
                       push_speed=self.push.config.push_speed_mps)
        if not np.isfinite(proposed[:2]).all():
            self.interventions += 1
            out = proposed.copy()
            out[:] = 0.0
            return out  # a broken command: stop (counted as an intervention)
        back = robot.reverse_fraction  # 0: forward only
        v0, w0 = float(np.clip(proposed[0], -back, 1.0)), float(np.clip(proposed[1], -1.0, 1.0))
        arc = np.array([v0 * robot.max_linear_speed]), np.array([w0 * robot.max_angular_speed])
        if rule.admissible(*arc, self._times)[0] and not self._recovering:
            self._stuck = 0
            return proposed
        self.interventions += 1
        grid = self._grid
        vs, ws = grid[:, 0] * robot.max_linear_speed, grid[:, 1] * robot.max_angular_speed
        clearance = rule.clearance(vs, ws, self._times)
        admissible = rule.admissible(vs, ws, self._times, clearance)
        if self._recovering or not admissible.any():
            # recovery (or nothing admissible, which the grid's (0, 0) makes rare: it keeps the
            # clearance of now): the command that ends with the most room round the base, backing
            # up too where the robot can (forward preferred by a little)
            if back > 0 and cfg.reverse_recovery:
                grid = np.vstack([grid, self._reverse * [back, 1.0]])
                rv, rw = grid[len(vs):, 0] * robot.max_linear_speed, grid[len(vs):, 1] * robot.max_angular_speed
                clearance = np.concatenate([clearance, rule.clearance(rv, rw, self._times)])
                vs, ws = np.concatenate([vs, rv]), np.concatenate([ws, rw])
                admissible = rule.admissible(vs, ws, self._times, clearance)
            room = rule.clearance(vs, ws, self._times[-1:])
            best = int(np.argmax(np.where(admissible, room + 0.05 * grid[:, 0], -np.inf))) if admissible.any() \
                else int(np.argmax(clearance))
            self._recovering = max(self._recovering - 1, 0)
        else:
            cost = (grid[:, 0] - v0) ** 2 + cfg.turn_weight * (grid[:, 1] - w0) ** 2
            best = int(np.argmin(np.where(admissible, cost, np.inf)))
            self._stuck = self._stuck + 1 if grid[best, 0] < cfg.stuck_speed else 0
            if cfg.stuck_steps and cfg.recovery_steps and self._stuck >= cfg.stuck_steps:
                self._stuck = 0
                self._recovering = cfg.recovery_steps
                self.recoveries += 1
        out = proposed.copy()
        out[0], out[1] = grid[best]
        return out

