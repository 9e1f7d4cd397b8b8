"""The push check: when a return labelled movable near the base may be believed.

The NAMO policies push balls, boxes and doors, so the safety layer round a policy used to take
every return a segmenter labels movable (label 1) for something to push, not an obstacle. A
segmenter errs by object: the same pillar, the same stretch of wall called movable in every
frame, and a shield that believes it lets the base drive into it (issue 51: ``policies/barn-jackal``
under ``--sensor-noise realistic`` collided with cylinders labelled movable). Real stacks keep
their collision monitor on the raw returns and let a deliberate push through only under explicit
conditions (Nav2's collision monitor). ``PushCheck`` holds those conditions in one place for the
shield (``curlnav.nav.safety.shield``), its scan memory (``curlnav.nav.perception.scan_filter``) and the
scan map (``curlnav.nav.global_planners.scan_map``).

Each scan, the movable returns within ``near_m`` of the base are cut into objects (runs of
neighbouring beams without a range jump of ``jump_m``). An object is **pushable**, its returns no
obstacle to a command at pushing speed, when

(a) **the robot has an arm** (``RobotConfig.arm``): a robot without one pushes nothing, and every
    return labelled movable near it is an obstacle;
(b) **it lies on the arm's side**: the arm points straight ahead, so some of its returns lie in
    the corridor ahead of the bumper no wider than the base's half-width plus ``sector_margin_m``
    each side, the nearest within the arm's reach plus ``contact_m``;
(c) **at pushing speed**: the shield holds a command faster than ``push_speed_mps`` to its margin
    from a pushable object, so a push goes on at pushing speed;
(d) **and pushes have not shown it staying put**. An object the arm presses on (where the scan
    before saw it, the arm now reaches: within ``contact_m`` of its tip at the extension sent last,
    or of the returns beside the beams the arm hides; the bumper with the arm retracted) is
    compared, in the odometry frame, with the movable returns of the last scan before which the
    base advanced ``advance_m``. A pushed object moved with the base: its returns lie nearer (in
    the median, by ``moved_m``) to that scan's moved by the base's advance than to where they were;
    a wall stayed put: the other way round. ``still_steps`` pushes in a row that leave it in place
    hold its cells (``cell_m`` and their 8 neighbours, odometry frame) static for the episode. An
    object shown to **move** is a movable object: it stays pushable wherever it lies near the base
    while it is followed from scan to scan (``track_m``), and is never held (a door at its stop or
    a ball against a wall is no wall; a door swings beside the base as it opens).

So an object on the arm's side is pushable for its first pushes, until they show it staying put:
balls and doors go on being pushed, by the arm or the bumper, and a pillar or a wall called
movable is held after ``still_steps`` pushes of the arm. The arm may touch it, the base need not:
with the Husky's arm out (0.5 m) at pushing speed, three pushes end 0.3 m short of the wall (0.15 m
with ``realistic`` senses' latency), and the shield stops the base there; under ``harsh`` senses
(two steps late, the wall's returns broken up) the base still reaches it. With the arm retracted
the bumper is what pushes: a base pushing a wall called movable touches it before it can tell
(what ``policies/namo-robust`` does with doors and balls, and it needs to), and the bumper's push
of something that does not give is no evidence (it is a contact already, or a glancing touch). A
movable label further than ``near_m`` is believed: a plan may route through a ball it will push,
and nothing there can be reached before the next scans. Odometry is used over a few scans only.

Defaults, and why: ``push_speed_mps`` 0.5 m/s (half the Husky's top speed: ``policies/namo-robust``
pushes with the arm at a median 0.76 m/s and with the bumper at 0.92 m/s; held to 0.5 m/s a push
still moves a ball 0.1 m a control step, what (d) needs to tell it from a wall, and three pushes of
a wall end nearer it by less than the arm reaches); ``sector_margin_m`` 0.1 m (a ball pushed
off-centre rolls along the bumper); ``contact_m`` 0.05 m (range noise; an object this far ahead of
the tip is touched by the next push); ``advance_m`` 0.05 m and ``moved_m`` 0.02 m (the median
distance of a wall's returns to the scan before's, under ``realistic`` range noise (3 cm 1-sigma),
is about 0.02 m: a comparison over 5 cm of advance tells a ball from a wall); ``still_steps`` 3 (as
the arm reaches a ball, its first comparison may show it still); ``near_m`` 2.0 m (the scan
memory's ``range_m``: further than the shield checks at any of the robots' speeds).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from curlnav.layout import beam_angles
from curlnav.nav.geometry import NEIGHBOUR_OFFSETS, cell_keys, from_frame, to_frame
from curlnav.sim import EnvConfig


@dataclass(frozen=True)
class PushConfig:
    """When a movable label near the base is believed (module docstring; m, m/s, scans)."""

    push_speed_mps: float = 0.5  # m/s, the fastest forward command a deliberate push is made at
    sector_margin_m: float = 0.1  # m, the arm's sector reaches this far sideways beyond the base's half-width
    contact_m: float = 0.05  # m, an object this near the arm's tip (ahead of it) is touched by it
    near_m: float = 2.0  # m from the base's centre: a movable label further away is believed as given
    jump_m: float = 0.15  # m, a range jump between neighbouring beams that separates two objects
    advance_m: float = 0.05  # m, a push: compared with the last scan before which the base advanced this far
    moved_m: float = 0.02  # m, one way (moved with the base, or stayed put) fits better by this, in the median
    still_steps: int = 3  # pushes in a row that leave an object in place hold its cells static for the episode
    cell_m: float = 0.1  # m, the cells (odometry frame) held static, with their 8 neighbours
    track_m: float = 0.15  # m, an object shown to move is followed from scan to scan within this
    history: int = 5  # scans kept to compare with (a push at a crawl advances advance_m in several)
    #: whether a robot with an arm doubts its movable labels too (the whole check); False: it believes
    #: them as given, as before the check existed. Off by default: on the NAMO validation floors (seeds
    #: 90 and 91, exact senses) the check cost policies/namo-robust 12 of 120 trials (106 -> 94 of
    #: 120), pushing slowly at door jambs, while it cut base contact events under ``realistic`` from
    #: 0.68 to 0.40 per trial. A robot without an arm always doubts (it pushes nothing).
    with_arm: bool = False

    def __post_init__(self) -> None:
        for name in ("push_speed_mps", "sector_margin_m", "contact_m", "near_m", "jump_m", "advance_m", "moved_m",
                     "cell_m", "track_m"):
            value = getattr(self, name)
            zero_ok = name in ("push_speed_mps", "sector_margin_m", "contact_m", "moved_m")
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value >= 0 and (value > 0 or zero_ok)):
                kind = "non-negative" if zero_ok else "positive"
                raise ValueError(f"push check: {name} must be a {kind} number, got {value!r}")
        if not isinstance(self.with_arm, bool):
            raise ValueError(f"push check: with_arm must be true or false, got {self.with_arm!r}")
        for name, top in (("still_steps", 1000), ("history", 100)):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= top):
                raise ValueError(f"push check: {name} must be a whole number 1-{top}, got {value!r}")

    @classmethod
    def from_dict(cls, values: dict) -> PushConfig:
        """From a JSON/YAML mapping; unknown keys are refused by name."""
        if not isinstance(values, dict):
            raise ValueError(f"push check settings must be a mapping, got {type(values).__name__}")
        unknown = sorted(set(values) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(f"push check: unknown setting(s) {', '.join(map(str, unknown))}; "
                             f"known: {', '.join(sorted(cls.__dataclass_fields__))}")
        return cls(**values)


_NONE = np.zeros((0, 2))


class PushCheck:
    """The push check of the module docstring for one consumer (each keeps its own: it follows
    the scans that consumer is shown). Once per scan, ``update(ranges, labels, pose)`` says which
    movable labels to believe; ``commanded(action)`` is told each command sent (the arm's
    extension). ``pushable`` holds the newest scan's pushable returns (odometry frame), to which the
    shield applies the speed condition (c) command by command; ``pushes`` counts the comparisons of
    the episode (d), ``held`` the cells they held static."""

    def __init__(self, env_config: EnvConfig | None = None, config: PushConfig | None = None) -> None:
        env_config = env_config or EnvConfig()
        self.config = config or PushConfig()
        robot = env_config.robot
        self.arm = bool(robot.arm)
        #: a robot with an arm and ``with_arm`` off believes every movable label as given
        self.believes_labels = self.arm and not self.config.with_arm
        self.half_length, self.half_width = robot.base_length / 2, robot.base_width / 2  # m
        self.arm_reach = float(robot.arm_reach) if self.arm else 0.0  # m
        self.arm_width = float(robot.arm_width) if self.arm else 0.0  # m
        angles = beam_angles(env_config.lidar_fov, env_config.lidar_beams)
        self._cos, self._sin = np.cos(angles), np.sin(angles)  # beam 0 on the right
        self.max_range = float(env_config.lidar_max_range)
        self.reset()

    def reset(self) -> None:
        """Forget every scan, command and held cell (a new episode or goal: the odometry may have
        restarted)."""
        self.extension = 0.0  # m, the arm's extension sent last
        # the last scans: odometry pose, movable returns within near_m (odometry frame), newest last
        self._scans: deque[tuple[tuple[float, float, float], np.ndarray]] = deque(maxlen=self.config.history)
        self._counts: dict[int, int] = {}  # cell key: pushes in a row that left it in place
        self._held = np.zeros(0, dtype=np.int64)  # sorted keys of the cells held static
        self._moving = _NONE  # (n, 2) odometry frame: the last scan's returns of objects a push moved
        self.pushable = _NONE  # (n, 2) odometry frame: the newest scan's pushable returns
        self.pushes = 0

    @property
    def held(self) -> int:
        """How many cells pushes held static in this episode."""
        return len(self._held)

    def commanded(self, action) -> None:
        """The command sent this step, ``[v, w, L]`` (fractions of the robot's limits)."""
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        arm = float(a[2]) if len(a) > 2 and math.isfinite(a[2]) else 0.0
        self.extension = min(max(arm, 0.0), 1.0) * self.arm_reach

    def held_at(self, points: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: odometry-frame points ``(n, 2)`` (m) in a cell held static."""
        if len(points) == 0 or len(self._held) == 0:
            return np.zeros(len(points), dtype=bool)
        return np.isin(cell_keys(points, self.config.cell_m), self._held)

    def update(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``(beams,)`` bool: which returns of the newest scan (``ranges`` m, ``labels`` 1.0
        movable, beam 0 on the right), seen from the odometry ``pose`` (x, y, yaw; m, rad), are
        believed movable: labelled movable and beyond ``near_m``, or pushable (module docstring).
        The others labelled movable are obstacles. Call once per scan."""
        cfg = self.config
        ranges = np.asarray(ranges, dtype=np.float64)
        movable = (ranges < self.max_range - 1e-3) & (np.asarray(labels) >= 0.5)
        if self.believes_labels:
            return movable
        near = movable & (ranges <= cfg.near_m)
        local = np.stack([ranges * self._cos, ranges * self._sin], axis=1)
        odom = to_frame(local, pose)
        pushable = np.zeros(len(ranges), dtype=bool)
        moving = np.zeros(len(ranges), dtype=bool)
        if self.arm:
            ahead = near & (local[:, 0] >= self.half_length - cfg.contact_m) \
                & (np.abs(local[:, 1]) <= self.half_width + cfg.sector_margin_m)
            followed = _near(odom, self._moving, cfg.track_m)
            for beams in self._objects(ranges, near):
                moved = bool(followed[beams].any())  # a push moved it before: a movable object
                in_front = ahead[beams]
                front = float(local[beams[in_front], 0].min()) - self.half_length if in_front.any() else math.inf
                if front <= self.extension + cfg.contact_m:  # m ahead of the bumper: the arm's tip reaches it
                    moved = self._judge(odom[beams], pose, moved) or moved
                moving[beams] = moved
                if moved:
                    pushable[beams] = True  # shown to move: believed wherever it lies near the base
                elif front <= self.arm_reach + cfg.contact_m:  # on the arm's side: pushable until held
                    pushable[beams] = ~self.held_at(odom[beams])
        self._scans.append((pose, odom[near]))
        self._moving = odom[moving]
        self.pushable = odom[pushable]
        return (movable & ~near) | pushable

    def static(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``(beams,)`` bool: the returns of a scan (as ``update``'s) labelled movable within
        ``near_m`` that the push check knows cannot be pushed: every one on a robot without an arm,
        else those in cells pushes held static (what the scan map lays down as static)."""
        ranges = np.asarray(ranges, dtype=np.float64)
        near = (ranges < self.max_range - 1e-3) & (np.asarray(labels) >= 0.5) & (ranges <= self.config.near_m)
        if self.believes_labels:
            return np.zeros(len(ranges), dtype=bool)
        if not self.arm:
            return near
        return near & self.held_at(to_frame(np.stack([ranges * self._cos, ranges * self._sin], axis=1), pose))

    def follows(self, points: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: odometry-frame points ``(n, 2)`` (m) within ``track_m`` of the newest scan's
        pushable returns: what a memory kept of an object from before it was pushable lies there."""
        return _near(points, self.pushable, self.config.track_m)

    def pushable_in(self, pose: tuple[float, float, float]) -> np.ndarray:
        """``(n, 2)`` robot-frame points (m) of the ``pushable`` returns at the odometry ``pose``:
        where they were, and, from a scan that came late, also where they lie from the base if they
        moved with it since (a pushed object does): the nearer counts, whichever it is."""
        if len(self.pushable) == 0:
            return _NONE
        now = from_frame(self.pushable, pose)
        seen = from_frame(self.pushable, self._scans[-1][0])  # in the frame the scan was taken in
        return now if np.allclose(now, seen) else np.concatenate([now, seen])

    def _objects(self, ranges: np.ndarray, chosen: np.ndarray) -> list[np.ndarray]:
        """The ``chosen`` returns cut into objects: runs of neighbouring beams (one missing beam
        allowed) without a range jump of ``jump_m``; each a sorted array of beam indices."""
        beams = np.flatnonzero(chosen)
        if len(beams) == 0:
            return []
        breaks = (np.diff(beams) > 2) | (np.abs(np.diff(ranges[beams])) > self.config.jump_m)
        return np.split(beams, np.flatnonzero(breaks) + 1)

    def _judge(self, odom: np.ndarray, pose: tuple[float, float, float], moved: bool) -> bool:
        """Compare one object the arm's tip reaches (its returns, odometry frame) with the last scan
        before which the base advanced ``advance_m`` (condition (d)); True when a push moved it
        with the base. Its cells count one more push that left it in place (``still_steps`` hold
        them static), but for an object a push ``moved`` before (a door at its stop is no wall), or
        start again when it moved."""
        cfg = self.config
        compared = next((scan for scan in reversed(self._scans) if self._advance(scan[0], pose) >= cfg.advance_m), None)
        if compared is None or len(compared[1]) == 0:
            return False  # no push: nothing learnt
        (bx, by, _), before = compared
        shift = np.array([pose[0] - bx, pose[1] - by])  # m, the base's move since (odometry frame)
        # pushed at all: where that scan saw it, the arm or the bumper now is (had it stayed put,
        # they would have driven into it); else the base passed it by
        was = from_frame(before[_near(before, odom, cfg.track_m + float(np.hypot(*shift)))], pose)
        by_arm, by_bumper = self._under_arm(was).any(), self._under_bumper(was).any()
        if not (by_arm or by_bumper):
            return False
        tree = cKDTree(before)
        stayed = float(np.median(tree.query(odom)[0]))  # m, to that scan's returns where they were
        pushed = float(np.median(tree.query(odom - shift)[0]))  # m, to them moved with the base
        if min(stayed, pushed) > cfg.track_m:
            return False  # not in that scan, where it was nor moved with the base: nothing to compare
        self.pushes += 1
        keys = np.unique((cell_keys(odom, cfg.cell_m)[:, None] + NEIGHBOUR_OFFSETS[None, :]).ravel())
        if pushed + cfg.moved_m <= stayed:  # it moved with the push: start again
            for k in keys.tolist():
                self._counts.pop(k, None)
            self._held = np.setdiff1d(self._held, keys, assume_unique=True)
            return True
        # it stayed put where the arm pushed (the arm gives; the bumper stays put only against a
        # wall it already touches, or glancing past what it does not push: no evidence)
        if stayed + cfg.moved_m <= pushed and by_arm and not moved:
            held = []
            for k in keys.tolist():
                self._counts[k] = self._counts.get(k, 0) + 1
                if self._counts[k] >= cfg.still_steps:
                    held.append(k)
            if held:
                self._held = np.union1d(self._held, np.array(held, dtype=np.int64))
        return False

    @staticmethod
    def _advance(then: tuple[float, float, float], now: tuple[float, float, float]) -> float:
        """m the base advanced from odometry pose ``then`` to ``now``, along its heading of then."""
        return (now[0] - then[0]) * math.cos(then[2]) + (now[1] - then[1]) * math.sin(then[2])

    def _under_arm(self, points: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: robot-frame points ``(n, 2)`` (m) within ``contact_m`` of the arm at the
        extension sent last, or of the returns beside it: the arm hides the beams behind it, so a
        wall it presses on is seen only beside its shadow (which widens with the range)."""
        x, y = points[:, 0], np.abs(points[:, 1])
        cfg = self.config
        shadow = self.arm_width / 2 * np.maximum(1.0, x / self.half_length)
        return (x >= 0) & (x <= self.half_length + self.extension + cfg.contact_m) & (y <= shadow + cfg.contact_m)

    def _under_bumper(self, points: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: robot-frame points ``(n, 2)`` (m) within ``contact_m`` of the bumper's face,
        or inside the base."""
        x, y = points[:, 0], np.abs(points[:, 1])
        return (x >= 0) & (x <= self.half_length + self.config.contact_m) & (y <= self.half_width)


def _near(points: np.ndarray, to: np.ndarray, reach: float) -> np.ndarray:
    """``(n,)`` bool: which of ``points`` ``(n, 2)`` lie within ``reach`` of one of ``to`` (m)."""
    if len(points) == 0 or len(to) == 0:
        return np.zeros(len(points), dtype=bool)
    return cKDTree(to).query(points)[0] <= reach
