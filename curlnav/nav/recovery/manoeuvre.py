"""A short manoeuvre onto the global plan's path for a robot that stands stuck beside it.

Behind a global plan the rescue is the plan's path tracker (``curlnav.nav.recovery.rescue.PlanTracker``,
regulated pure pursuit). Pure pursuit knows one way onto the path: turn toward it, the short way
round, then drive. A base that stands with a post or a wall end a few centimetres off its
corner, where the short turn sweeps that corner into it (or a post just before its nose, where
either turn does), never gets there: the shield refuses the turn, its recovery turns the other way for a second,
the tracker asks for the short turn again, and so on for the rest of the minute (seen on the
validation floors: docs/results/archive.md).

``ManoeuvrePlanner`` plans what a driver does there, a multi-point turn: a search (weighted A*,
as a lattice planner such as Nav2's Smac planners) over poses ``(x, y, yaw)``, each step one
control period of one command out of a small set (turns on the spot, slow forward arcs and, on a
robot that can back up, slow backing arcs: the policies drive forward only, the Husky and the
Jackal back up), to a pose on the path ahead, lined up with it, from where driving forward is
clear. Every step is checked against the map's walls round the pose with the shield's own rule
(``curlnav.nav.safety.shield``: the footprint over the shield's horizon keeps ``margin_m``, a turn on
the spot ``turn_margin_m``, and a base already nearer does not come nearer), so the shield lets the
commands through where the map is right (it still checks them against the scan: a ball, a door).
The search is bounded (``ManoeuvreConfig.max_expansions``); none found, the tracker drives as before.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from curlnav.config import positive_numbers
from curlnav.nav.geometry import arc_poses
from curlnav.nav.safety.shield import ArcRule, ShieldConfig, wall_tree, walls_near
from curlnav.sim import EnvConfig, World


@dataclass(frozen=True)
class ManoeuvreConfig:
    """The manoeuvre's search (m, rad, control steps)."""

    #: forward speeds of the search's commands, m/s (0: turns on the spot; capped at the robot's top speed)
    speeds: tuple[float, ...] = (0.0, 0.25, 0.5)
    #: turn rates of the search's commands, fractions of the top turn rate
    turns: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
    #: backing speeds, m/s, each with every turn rate (capped at ``RobotConfig.max_reverse_speed``;
    #: none on a robot that drives forward only) ...
    backing: tuple[float, ...] = (0.25,)
    #: ... and a step backing up costs this many steps forward (the LiDAR does not see behind:
    #: only the map's walls are checked there)
    backing_cost: float = 2.0
    #: the search ends on a path point between these distances ahead of the robot's place on the path
    ahead_min_m: float = 0.3
    ahead_max_m: float = 2.5
    #: ... within this distance of it and this heading of the path's direction there
    goal_tolerance_m: float = 0.15
    goal_heading_rad: float = math.radians(20.0)
    #: the search's cells: poses nearer than this (m, rad) count as one
    cell_m: float = 0.03
    cell_rad: float = math.radians(5.0)
    #: poses expanded at most (each 1-20 ms, by how many wall points are near; the validation
    #: worlds' manoeuvres took at most 1,057)
    max_expansions: int = 1500
    max_steps: int = 60  # a manoeuvre costs at most this many control steps (backing_cost each backing one)
    #: the search's weight on its estimate of the steps left (weighted A*: above 1, quicker, a
    #: little longer manoeuvres)
    estimate_weight: float = 1.5
    #: the robot counts as stuck when it has stayed within ``still_m`` of one place for
    #: ``still_steps`` steps
    still_steps: int = 10
    still_m: float = 0.05
    #: after a search that found nothing (or a manoeuvre given up after two re-plans), none is
    #: started for this many steps
    retry_steps: int = 25
    #: a driven manoeuvre is planned again when the robot is this far off its predicted pose
    deviation_m: float = 0.1
    deviation_rad: float = math.radians(15.0)

    def __post_init__(self) -> None:
        positive_numbers(self, "manoeuvre", ["ahead_min_m", "ahead_max_m", "goal_tolerance_m", "goal_heading_rad",
                                              "cell_m", "cell_rad", "still_m", "deviation_m", "deviation_rad",
                                              "estimate_weight"])
        if self.ahead_max_m <= self.ahead_min_m:
            raise ValueError(f"manoeuvre: ahead_max_m ({self.ahead_max_m}) must exceed ahead_min_m ({self.ahead_min_m})")
        for name in ("max_expansions", "max_steps", "still_steps", "retry_steps"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 1_000_000):
                raise ValueError(f"manoeuvre: {name} must be a whole number 1-1000000, got {value!r}")
        if not (isinstance(self.backing_cost, (int, float)) and not isinstance(self.backing_cost, bool)
                and math.isfinite(self.backing_cost) and self.backing_cost >= 1):
            raise ValueError(f"manoeuvre: backing_cost must be a number of at least 1, got {self.backing_cost!r}")
        for name, low, high in (("speeds", 0.0, 10.0), ("backing", 0.0, 10.0), ("turns", -1.0, 1.0)):
            values = getattr(self, name)
            if not (isinstance(values, tuple) and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      and low <= x <= high for x in values)):
                raise ValueError(f"manoeuvre: {name} must be a tuple of numbers {low:g}..{high:g}, got {values!r}")
        if not any(v > 0 for v in self.speeds) or 0.0 not in self.turns or 0.0 in self.backing:
            raise ValueError("manoeuvre: speeds needs a forward speed and turns a 0 (the search ends lined up with "
                             f"room to drive straight on), backing no 0; got speeds {self.speeds!r}, turns "
                             f"{self.turns!r}, backing {self.backing!r}")


@dataclass(frozen=True)
class Manoeuvre:
    """A planned manoeuvre: ``commands[k]`` (``[v, w]`` fractions) is sent at ``poses[k]`` (map frame,
    m and rad) and brings the base to ``poses[k + 1]``; the last pose is on the path, lined up."""

    commands: np.ndarray  # (k, 2)
    poses: np.ndarray  # (k + 1, 3)
    expansions: int


class ManoeuvrePlanner:
    """Plans a ``Manoeuvre`` on one world's map (module docstring): ``plan(pose, path, index)``."""

    def __init__(self, env_config: EnvConfig | None = None, config: ManoeuvreConfig | None = None,
                 shield: ShieldConfig | None = None) -> None:
        self.env_config = env_config or EnvConfig()
        self.config = config or ManoeuvreConfig()
        self.shield = shield or ShieldConfig()
        robot = self.env_config.robot
        self.half_length, self.half_width = robot.base_length / 2, robot.base_width / 2
        self._period = self.env_config.control_period
        self._times = self.shield.times()
        speeds = sorted({min(v, robot.max_linear_speed) for v in self.config.speeds}
                        | {-min(b, robot.max_reverse_speed) for b in self.config.backing if robot.max_reverse_speed > 0})
        commands = [(v / robot.max_linear_speed, w) for v in speeds for w in self.config.turns if (v, w) != (0.0, 0.0)]
        self._commands = np.array(commands, dtype=np.float64)  # (m, 2) fractions of the top speeds
        self._cost = np.where(self._commands[:, 0] < 0, self.config.backing_cost, 1.0)  # steps
        self._v = self._commands[:, 0] * robot.max_linear_speed  # m/s
        self._w = self._commands[:, 1] * robot.max_angular_speed  # rad/s
        # m, the furthest a wall point can be from the base's centre and still matter to a command
        self._reach = (math.hypot(self.half_length, self.half_width) + self.shield.margin_m
                       + float(np.max(np.abs(self._v), initial=0.0)) * max(self.shield.horizon_s, self._period))

    def admissible(self, tree: cKDTree, pose: tuple[float, float, float]) -> np.ndarray:
        """``(m,)`` which of the search's commands the shield admits at ``pose`` against the map's
        walls: the footprint over the shield's horizon keeps ``margin_m`` (a turn on the spot
        ``turn_margin_m``) from the points the base does not touch, or no less than it keeps now,
        and presses no deeper into those it touches."""
        points = walls_near(tree, pose, self._reach)
        hl, hw = self.half_length, self.half_width
        on_base = (np.abs(points[:, 0]) <= hl) & (np.abs(points[:, 1]) <= hw)
        rule = ArcRule(points[~on_base], points[on_base], hl, hw, self.shield.margin_m, self.shield.turn_margin_m)
        return rule.admissible(self._v, self._w, self._times)

    def _after(self, pose: tuple[float, float, float]) -> np.ndarray:
        """``(m, 3)`` the pose after one control period of each command (exact arcs)."""
        x, y, yaw = pose
        fx, fy, th = (a[:, 0] for a in arc_poses(self._v, self._w, np.array([self._period])))  # robot frame at pose
        c, s = math.cos(yaw), math.sin(yaw)
        return np.stack([x + c * fx - s * fy, y + s * fx + c * fy, yaw + th], axis=1)

    def plan(self, world: World, pose: tuple[float, float, float], path: np.ndarray, index: int) -> Manoeuvre | None:
        """A manoeuvre from ``pose`` onto ``path`` (``(n, 2)`` m) ahead of its point ``index`` (the
        robot's place on it), or None when the search finds none within its bounds, or when the
        robot stands on the path already, lined up with room to drive on (what holds it is not on
        the map: a ball, a door)."""
        cfg = self.config
        if path is None or len(path) < 2:
            return None
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
        index = min(max(int(index), 0), len(path) - 1)
        here = along[index]
        pick = np.nonzero((along >= here + cfg.ahead_min_m) & (along <= here + cfg.ahead_max_m))[0]
        pick = pick[pick < len(path) - 1]
        if len(pick) == 0:
            return None
        targets = path[pick]
        direction = path[pick + 1] - path[pick]
        headings = np.arctan2(direction[:, 1], direction[:, 0])
        tree = wall_tree(world)
        step_m = max(float(np.max(self._v)) * self._period, 1e-3)  # m, the furthest one step goes
        turn_rad = self.env_config.robot.max_angular_speed * self._period

        def estimate(p: np.ndarray) -> float:
            """Steps to a target, at least: the straight distance and the turn still to make."""
            d = np.hypot(targets[:, 0] - p[0], targets[:, 1] - p[1])
            k = int(np.argmin(d))
            turn = abs(math.remainder(float(p[2] - headings[k]), math.tau))
            return float(d[k] / step_m + max(turn - cfg.goal_heading_rad, 0.0) / turn_rad)

        def arrived(p: np.ndarray, ok: np.ndarray) -> bool:
            d = np.hypot(targets[:, 0] - p[0], targets[:, 1] - p[1])
            lined = np.abs(np.remainder(p[2] - headings + math.pi, math.tau) - math.pi) <= cfg.goal_heading_rad
            forward = ok[(self._commands[:, 0] > 0) & (self._commands[:, 1] == 0.0)]
            return bool(((d <= cfg.goal_tolerance_m) & lined).any() and forward.any())

        def cell(p: np.ndarray) -> tuple[int, int, int]:
            return (round(p[0] / cfg.cell_m), round(p[1] / cfg.cell_m),
                    round(math.remainder(float(p[2]), math.tau) / cfg.cell_rad))
        start = np.asarray(pose, dtype=np.float64)
        nodes = [(start, -1, -1, 0.0)]  # (pose, parent, command, cost in steps)
        frontier = [(estimate(start), 0)]
        seen = {cell(start)}
        expansions = 0
        while frontier and expansions < cfg.max_expansions:
            _, i = heapq.heappop(frontier)
            p, _, _, steps = nodes[i]  # steps: the cost so far
            ok = self.admissible(tree, (float(p[0]), float(p[1]), float(p[2])))
            expansions += 1
            if arrived(p, ok):
                return self._unwind(nodes, i, expansions) if i > 0 else None
            for k, q in zip(np.nonzero(ok)[0], self._after(tuple(p))[ok]):
                cost = steps + float(self._cost[k])
                key = cell(q)
                if key in seen or cost > cfg.max_steps:
                    continue
                seen.add(key)
                nodes.append((q, i, int(k), cost))
                heapq.heappush(frontier, (cost + cfg.estimate_weight * estimate(q), len(nodes) - 1))
        return None

    def _unwind(self, nodes: list, i: int, expansions: int) -> Manoeuvre:
        commands, poses = [], [nodes[i][0]]
        while nodes[i][1] >= 0:
            commands.append(self._commands[nodes[i][2]])
            i = nodes[i][1]
            poses.append(nodes[i][0])
        return Manoeuvre(np.array(commands[::-1]).reshape(-1, 2), np.array(poses[::-1]), expansions)


class ManoeuvreDriver:
    """Watches a tracker drive and, when the robot has stood still (``ManoeuvreConfig.still_steps``
    poses within ``still_m``), plans a ``Manoeuvre`` and drives it: ``command(world, pose, path,
    index)`` gives the manoeuvre's next ``[v, w]`` (fractions), or None (the tracker drives). A
    manoeuvre is planned again from where the robot is when it strays from the predicted pose (a
    ball, the drive's lag, the shield's own recovery; twice at most), and dropped when a command
    other than its own was sent (``sent``); after a search finds nothing, or a manoeuvre is given
    up, none is started for ``retry_steps`` steps."""

    def __init__(self, planner: ManoeuvrePlanner) -> None:
        self.planner = planner
        self.config = planner.config
        self.clear()

    def clear(self) -> None:
        """Forget the episode: the poses seen, any manoeuvre under way, the count."""
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=self.config.still_steps)
        self._active: Manoeuvre | None = None
        self._step = 0  # the next command of the active manoeuvre
        self._given: np.ndarray | None = None  # the command last given
        self._replans = 0
        self._quiet = 0  # steps before a new manoeuvre may be started
        self.manoeuvres = 0  # manoeuvres started in the current episode

    @property
    def driving(self) -> bool:
        """Whether a manoeuvre is under way."""
        return self._active is not None

    def _still(self) -> bool:
        cfg = self.config
        if len(self._poses) < cfg.still_steps or self._quiet > 0:
            return False
        recent = np.array(self._poses)[:, :2]
        return bool(np.max(np.hypot(*(recent - recent[-1]).T)) <= cfg.still_m)

    def _strayed(self, pose: tuple[float, float, float]) -> bool:
        expected = self._active.poses[self._step]
        return (math.hypot(pose[0] - expected[0], pose[1] - expected[1]) > self.config.deviation_m
                or abs(math.remainder(pose[2] - expected[2], math.tau)) > self.config.deviation_rad)

    def _start(self, world: World, pose: tuple[float, float, float], path: np.ndarray, index: int) -> None:
        found = self.planner.plan(world, pose, path, index)
        self._active = found if found is not None and len(found.commands) else None
        self._step = 0
        if self._active is None:
            self._quiet = self.config.retry_steps

    def _end(self) -> None:
        """The manoeuvre is over (done, dropped or given up): stillness is counted afresh."""
        self._active = None
        self._poses.clear()

    def command(self, world: World, pose: tuple[float, float, float], path: np.ndarray | None,
                index: int, may_plan: bool = True) -> np.ndarray | None:
        """The manoeuvre's command at ``pose`` (map frame; ``path`` and ``index`` as ``plan``'s), or
        None; ``may_plan``: whether a new manoeuvre may be started this step."""
        pose = tuple(float(x) for x in pose)
        self._poses.append(pose)
        self._quiet = max(self._quiet - 1, 0)
        self._given = None
        if self._active is not None and self._strayed(pose):
            self._end()
            if self._replans < 2:
                self._replans += 1
                self._start(world, pose, path, index)
            else:
                self._quiet = self.config.retry_steps
        elif self._active is None:
            if path is None or not may_plan or not self._still():
                return None
            self._replans = 0
            self._start(world, pose, path, index)
            if self._active is None:
                return None
            self.manoeuvres += 1
        if self._active is None:
            return None
        self._given = self._active.commands[self._step]
        self._step += 1
        if self._step >= len(self._active.commands):  # the last command: the tracker drives on
            self._end()
        return self._given

    def sent(self, action: np.ndarray) -> None:
        """The command the robot's stack chose this step (behind a rescue: the rescue's, before the
        shield, whose replacements show as a stray from the predicted pose): a manoeuvre whose
        command it was not is dropped."""
        if self._given is not None and not np.allclose(np.asarray(action, dtype=np.float64)[:2], self._given,
                                                       atol=1e-6):
            self._end()
