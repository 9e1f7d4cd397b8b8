"""A policy artefact (or a map-less planner of ``curlnav.nav``) as a ROS 2 node: ``/scan`` +
``/odom`` + ``/goal_pose`` (+ ``/plan``) in, ``/cmd_vel`` + ``/arm_cmd`` + ``/goal_state`` out, at
the policy's control rate.

``PolicyNode`` is the core (no DDS: messages in, ``Command`` out, testable directly);
``run_node`` is the shell that wires it to DDS topics and a clock.

The scan's ``intensities`` carry the per-beam movable labels (1.0: the beam's first hit is a
movable object, 0.0: static), as a movable-object segmenter writes them; any other beam layout
is resampled to the policy's (241 beams over -120..+120 deg by default; per policy beam the
nearest return of the input beams in its 1-degree bin, the bin's beams uncovered by the input
read as no return). The scanner is taken to sit at ``base_link``'s origin, facing forward.
The labels are handled as in evaluation: a stack built by ``curlnav ros2 run --shield`` (and
``--rescue``, ``--scan-plan``) is the evaluation's own (``curlnav.nav``), built for the robot
profile's arm, so a return labelled movable near the base is an obstacle unless the robot may push
it (``curlnav.nav.safety.push_check``); the node gives it the odometry pose and tells it each command
it publishes (``told``: a stop the node makes is what the robot did).

Safe at the edges (issue 35): every command goes through ``guard`` (finite, within the artefact's
speed limits, else a counted stop); goals beyond ``max_goal_m`` and odometry beyond
``ODOM_BOUND_M`` are refused, so the transform to the robot frame cannot overflow; a scan of more
than ``MAX_SCAN_RANGES`` ranges is refused and the resampler is linear in the ranges; the shell
runs a watchdog thread that sends a stop when no ``/cmd_vel`` went out for ``silence_s``; a goal
ends (``reached``, ``gave_up``, ``cancelled``, ``odometry_reset``, ``refused``) and is never
resumed by itself: only a new ``/goal_pose`` starts one.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from curlnav.layout import beam_angles
from curlnav.layout import goal_frame as layout_goal_frame
from curlnav.nav.global_planners.global_plan import GlobalPlan, WaypointConfig
from curlnav.nav.progress import ProgressChecker

#: A scan of more ranges is refused as malformed (work per message bounded; 2-D scanners give
#: a few thousand: 3,600 at 0.1 degree over 360)
MAX_SCAN_RANGES = 16_384
#: A scan with more NaN ranges than this fraction is refused (a broken sensor); fewer read as no
#: return, as the simulator's dropouts (REP 117: NaN is an erroneous measurement)
MAX_NAN_FRACTION = 0.05
#: A ``/plan`` of more poses is refused
MAX_PLAN_POSES = 20_000
#: Odometry farther than this from its origin (m) is refused (no overflow in the goal transform)
ODOM_BOUND_M = 1e6
#: Odometry that moves more than this (m) plus twice the top speed times the time between the two
#: stamps has jumped: the robot or its odometry restarted
ODOM_JUMP_M = 1.0


@dataclass(frozen=True)
class NodeConfig:
    """How the node runs (topic names live in ``curlnav.ros2.topics``)."""

    rate_hz: float = 5.0  # acts on each scan, at most this often (the policy's control rate)
    silence_s: float = 0.5  # stop when /scan or /odom is older than this (s)
    scan_frame: str = "base_link"  # the frame /scan must come in
    odom_frame: str = "odom"  # the frame /odom (and /goal_pose, /plan) must come in
    goal_tolerance_m: float = 0.8  # the goal is reached within this distance (m)
    max_goal_m: float = 10_000.0  # a goal with |x| or |y| beyond this (m, odom frame) is refused
    max_nan_fraction: float = MAX_NAN_FRACTION  # NaN ranges read as no return up to this fraction of a scan, else refused
    give_up_s: float = 30.0  # give the goal up after this long without progress (s)
    progress_m: float = 0.25  # progress: the distance to go falls this much below its best so far (m)
    # /plan following (--global-plan); the node has no map, so no line-of-sight check against one
    waypoints: WaypointConfig = field(default_factory=lambda: WaypointConfig(line_of_sight=False))

    def __post_init__(self) -> None:
        for name in ("rate_hz", "silence_s", "goal_tolerance_m", "max_goal_m", "give_up_s", "progress_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if self.silence_s < 2.0 / self.rate_hz:
            # commands go out on the first scan after 0.9 period: up to about 1.5 periods apart
            raise ValueError(f"silence_s ({self.silence_s:g} s) must be at least two control periods "
                             f"({2.0 / self.rate_hz:g} s at {self.rate_hz:g} Hz): the watchdog would stop between commands")
        if not (isinstance(self.max_nan_fraction, (int, float)) and 0.0 <= self.max_nan_fraction <= 1.0):
            raise ValueError(f"max_nan_fraction must be a fraction in 0..1, got {self.max_nan_fraction!r}")
        if self.max_goal_m > ODOM_BOUND_M:
            raise ValueError(f"max_goal_m must be at most {ODOM_BOUND_M:g} m, got {self.max_goal_m:g}")


@dataclass(frozen=True)
class ScanLayout:
    """The policy's observation layout (from its ``metadata.json``)."""

    beams: int = 241
    fov_rad: float = math.radians(240.0)
    max_range_m: float = 10.0
    range_frames: int = 4
    label_frames: int = 4
    goal_frames: int = 10
    max_linear_speed: float = 1.0  # m/s at action[0] = 1
    max_angular_speed: float = 1.0  # rad/s at |action[1]| = 1
    arm_reach: float = 0.5  # m at action[2] = 1
    control_period_s: float = 0.2
    arm: bool = True  # False: the robot has no arm (metadata robot.arm), /arm_cmd stays 0
    #: sectors of the network memory's ring (``curlnav.memory``), which the policy's agent adds to
    #: the frames the node builds, from the odometry it is given; 0: no memory
    memory_beams: int = 0

    @classmethod
    def of(cls, metadata: dict) -> ScanLayout:
        obs = metadata.get("observation", {})
        layout = obs.get("layout", {})
        scale = metadata.get("action", {}).get("scale", [1.0, 1.0, 0.5])
        try:
            return cls(beams=int(layout.get("beams", 241)),
                       fov_rad=float(obs.get("lidar_fov_rad", math.radians(240.0))),
                       max_range_m=float(layout.get("max_range", 10.0)),
                       range_frames=int(layout.get("range_frames", 4)), label_frames=int(layout.get("label_frames", 4)),
                       goal_frames=int(layout.get("goal_frames", 10)), max_linear_speed=float(scale[0]),
                       max_angular_speed=float(scale[1]), arm_reach=float(scale[2]),
                       control_period_s=float(obs.get("control_period_s", 0.2)),
                       arm=metadata.get("robot", {}).get("arm", True) is not False,
                       memory_beams=int(layout.get("memory_beams", 0)))
        except (AttributeError, IndexError, KeyError, TypeError, ValueError, OverflowError) as exc:
            raise ValueError(f"metadata: the observation layout or action.scale cannot be read ({exc})") from None

    @classmethod
    def from_env_config(cls, cfg) -> ScanLayout:
        """The layout of an environment (``curlnav.sim.EnvConfig``): what a planner built for it sees
        and commands (the values an artefact exported from it writes in its metadata)."""
        robot = cfg.robot
        return cls(beams=cfg.lidar_beams, fov_rad=cfg.lidar_fov, max_range_m=cfg.lidar_max_range,
                   range_frames=cfg.range_frames, label_frames=cfg.label_frames, goal_frames=cfg.goal_frames,
                   max_linear_speed=robot.max_linear_speed, max_angular_speed=robot.max_angular_speed,
                   arm_reach=robot.arm_reach, control_period_s=cfg.control_period, arm=robot.arm)

    @property
    def limits(self) -> tuple[float, float, float]:
        """(m/s, rad/s, m): the largest forward speed, turn rate and stick extension it may command."""
        return self.max_linear_speed, self.max_angular_speed, self.arm_reach

    def limits_problem(self) -> str | None:
        """Why the limits (``action.scale``) cannot bound a command, or None."""
        if not all(math.isfinite(v) and v > 0 for v in self.limits):
            return f"speed limits not finite and positive (action.scale {list(self.limits)})"
        return None

    @property
    def observation_size(self) -> int:
        """Values the policy reads: the frames the node builds plus the memory's ring."""
        return (self.range_frames + self.label_frames) * self.beams + 3 * self.goal_frames + self.memory_beams

    @property
    def angles(self) -> np.ndarray:
        """(beams,) policy beam angles (rad), beam 0 on the right."""
        return beam_angles(self.fov_rad, self.beams)


@dataclass(frozen=True)
class Command:
    """What the node sends: ``/cmd_vel`` (m/s, rad/s), ``/arm_cmd`` (m) and ``/goal_state``."""

    linear: float
    angular: float
    arm: float
    state: str

    @property
    def is_stop(self) -> bool:
        return self.linear == 0.0 and self.angular == 0.0


def guard(command: Command, layout: ScanLayout) -> tuple[Command, str | None]:
    """The last check on what goes out: ``(command, None)`` when it is finite and within the
    layout's limits (0..max_linear_speed m/s, |angular| <= max_angular_speed rad/s,
    0..arm_reach m), else ``(a stop, why)``. A stop always passes."""
    if command.linear == 0.0 and command.angular == 0.0 and command.arm == 0.0:
        return command, None
    lin, ang, arm = layout.limits
    why = layout.limits_problem()
    slack = 1.0 + 1e-9
    if why is None:
        if not (math.isfinite(command.linear) and 0.0 <= command.linear <= lin * slack):
            why = f"linear {command.linear:g} m/s not in 0..{lin:g}"
        elif not (math.isfinite(command.angular) and abs(command.angular) <= ang * slack):
            why = f"angular {command.angular:g} rad/s not in -{ang:g}..{ang:g}"
        elif not (math.isfinite(command.arm) and 0.0 <= command.arm <= arm * slack):
            why = f"arm {command.arm:g} m not in 0..{arm:g}"
    if why is None:
        return command, None
    return Command(0.0, 0.0, 0.0, f"stopped: unsafe command ({why})"), why


class ScanRefused(ValueError):
    """A scan the node will not act on (too many NaN, wrong length, wrong frame, labels not 0..1)."""


#: an input beam this close to a policy beam's angle is that beam's reading (rad; 0.001 degree)
ALIGNED_RAD = math.radians(0.001)


def resample_scan(scan, layout: ScanLayout, max_nan_fraction: float = MAX_NAN_FRACTION) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges, labels)``, each ``(layout.beams,)`` float32, of a ``sensor_msgs/LaserScan``
    (any object with its fields), or ``ScanRefused`` naming what is wrong. At most
    ``MAX_SCAN_RANGES`` ranges; the work is O(n log n) in the ranges.

    The ranges read as the simulator's LiDAR gives them (REP 117's special values):

    - +Inf (no return within range) and ranges beyond ``range_max`` read ``layout.max_range_m``,
      the simulator's "nothing within max range"; ranges up to that, clipped at it;
    - -Inf (too close to measure) and ranges below ``range_min`` read ``range_min`` (the obstacle
      is at most that far; 0 when the scan gives none): the simulator measures down to 0;
    - NaN (an erroneous measurement) reads as no return with label 0, as the simulator's
      dropouts, while at most ``max_nan_fraction`` of the ranges are NaN; a scan with more is
      refused (the sensor is failing: the robot stops rather than drive on a blind scan).

    The labels (``intensities``) are taken as given on every other beam.

    A scan with a beam at every policy angle it covers (within ``ALIGNED_RAD``: a finer scan of the
    same field, e.g. the UST-10LX's 1081 beams for the Jackal profile's 271) is decimated, as the
    simulator's LiDAR reads exactly at the policy's angles. Otherwise each policy beam takes the
    nearest return among the input beams of its bin (within half a policy step), or, when its bin
    holds none, the nearest input beam within that beam's own increment."""
    n, n_labels = len(scan.ranges), len(scan.intensities)
    if n == 0:
        raise ScanRefused("no ranges")
    if n > MAX_SCAN_RANGES:
        raise ScanRefused(f"too many ranges: {n:,} (at most {MAX_SCAN_RANGES:,})")
    if n_labels != n:
        raise ScanRefused(f"{n_labels} intensities for {n} ranges: one movable label per beam expected")
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    labels = np.asarray(scan.intensities, dtype=np.float64)
    a0, a1, inc = float(scan.angle_min), float(scan.angle_max), float(scan.angle_increment)
    if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(inc)) or inc == 0.0:
        raise ScanRefused(f"bad angles: angle_min {a0}, angle_max {a1}, angle_increment {inc}")
    expected = (a1 - a0) / inc + 1
    if abs(expected - n) > 1.01:
        raise ScanRefused(f"wrong length: {n} ranges, angle_min..angle_max by angle_increment gives {expected:.0f}")
    nan = np.isnan(ranges)
    if nan.any():
        if nan.sum() > max_nan_fraction * n:
            raise ScanRefused(f"too many NaN ranges: {int(nan.sum())} of {n} (at most {max_nan_fraction:.0%}), "
                              f"the first at beam {int(np.flatnonzero(nan)[0])}")
        ranges, labels = np.where(nan, np.inf, ranges), np.where(nan, 0.0, labels)  # no return, no label
    if not np.isfinite(labels).all() or (labels < 0).any() or (labels > 1).any():
        raise ScanRefused("intensities must be movable labels in 0..1 (reflectivity is not a label)")
    max_range = layout.max_range_m
    range_max = float(scan.range_max) if math.isfinite(scan.range_max) and scan.range_max > 0 else max_range
    range_min = float(getattr(scan, "range_min", 0.0))
    range_min = min(range_min, range_max, max_range) if math.isfinite(range_min) and range_min > 0 else 0.0
    r = np.where(ranges > range_max, max_range, ranges)
    r = np.clip(np.nan_to_num(r, posinf=max_range, neginf=range_min), range_min, max_range)
    angles = a0 + inc * np.arange(n)
    angles = (angles + math.pi) % (2 * math.pi) - math.pi
    step = layout.fov_rad / (layout.beams - 1)
    position = (angles + layout.fov_rad / 2) / step
    index = np.rint(position).astype(np.int64)
    inside = (index >= 0) & (index < layout.beams)
    # a scan with a beam at every policy angle it covers (a finer scan of the same field: every k-th
    # beam) is decimated, as the simulator's LiDAR reads exactly at those angles; any other is
    # min-pooled over each policy beam's bin
    at_angle = inside & (np.abs(position - index) * step <= ALIGNED_RAD)
    exact = np.zeros(layout.beams, dtype=bool)
    exact[index[at_angle]] = True
    covered = np.zeros(layout.beams, dtype=bool)
    covered[index[inside]] = True
    use = at_angle if covered.any() and exact[covered].all() else inside
    out = np.full(layout.beams, np.inf)
    np.minimum.at(out, index[use], r[use])
    out_labels = np.zeros(layout.beams)
    hit = use & (r == out[np.clip(index, 0, layout.beams - 1)])
    np.maximum.at(out_labels, index[hit], labels[hit])  # the label of the bin's nearest return
    empty = np.flatnonzero(~np.isfinite(out))
    if len(empty):  # a coarser input: the nearest input beam within its own increment
        nearest, diff = _nearest_beam(angles, layout.angles[empty])
        near = diff <= abs(inc) / 2 + 1e-9
        out[empty[near]] = r[nearest[near]]
        out_labels[empty[near]] = labels[nearest[near]]
        out[~np.isfinite(out)] = max_range
    return out.astype(np.float32), (out_labels >= 0.5).astype(np.float32)


def _nearest_beam(angles: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each target angle (rad), the index of the input beam nearest to it round the circle
    (the lowest index among equals) and the angle between them: ``(k,) int, (k,) rad``. Sorted
    once and searched, O((n + k) log n), never a k x n array."""
    n = len(angles)
    order = np.argsort(angles, kind="stable")
    ordered = angles[order]
    after = np.searchsorted(ordered, targets, side="left")  # the first beam at or after the target
    before = (after - 1) % n  # the last before it, round the circle
    before = np.searchsorted(ordered, ordered[before], side="left")  # the first of equal angles
    candidates = np.stack([order[before], order[after % n]])  # (2, k) input indices
    diff = np.abs((targets[None, :] - angles[candidates] + math.pi) % (2 * math.pi) - math.pi)
    pick = ((diff[1] < diff[0]) | ((diff[1] == diff[0]) & (candidates[1] < candidates[0]))).astype(np.int64)
    k = np.arange(len(targets))
    return candidates[pick, k], diff[pick, k]


def goal_frame(x: float, y: float, yaw: float, gx: float, gy: float) -> np.ndarray:
    """The policy's goal frame ``[sign(dx) log(1+|dx|), sign(dy) log(1+|dy|), atan2(dy, dx)]`` of
    ``(gx, gy)`` seen from the pose ``(x, y, yaw)`` (robot frame, m and rad), as ``NamoEnv``.
    Finite for the coordinates the node takes (goals within ``max_goal_m``, odometry within
    ``ODOM_BOUND_M``); ``ValueError`` rather than a non-finite frame."""
    if not all(math.isfinite(v) and abs(v) <= 2 * ODOM_BOUND_M for v in (x, y, gx, gy)) or not math.isfinite(yaw):
        raise ValueError(f"goal frame of ({gx:g}, {gy:g}) from ({x:g}, {y:g}, {yaw:g}): beyond the bounds")
    return layout_goal_frame(x, y, yaw, gx, gy)


class _GivenPath:
    """A ``GlobalPlan`` planner that hands back a given path: when the robot strays, it joins the
    path again at the path point nearest to it."""

    def __init__(self, path: np.ndarray) -> None:
        self.path = path

    def plan(self, start: tuple[float, float], goal: tuple[float, float]) -> np.ndarray:
        k = int(np.argmin(np.hypot(self.path[:, 0] - start[0], self.path[:, 1] - start[1])))
        return np.vstack([[start], self.path[k:]])


class PolicyNode:
    """The node's core. Feed it ``on_scan``, ``on_odom``, ``on_goal``, ``on_plan``, ``on_cancel``
    (message objects with the ROS 2 fields, times in s of one clock) and call ``act(now)`` at the
    control rate; it returns the ``Command`` to publish (a stop when a safety rule holds).

    Safety: a stop (zero twist) when the last good scan or odometry is older than
    ``silence_s``, at once when a scan is refused (until a good one comes), and whenever the
    policy's command fails ``guard``. ``counts`` tells how many scans, odometry messages and
    goals were taken and refused, by reason, and how many stops were made.

    A goal ends ``reached``, ``gave_up`` (no progress of ``progress_m`` for ``give_up_s``),
    ``cancelled``, ``odometry_reset`` (the odometry jumped, its time went back, or another
    publisher took over: the robot restarted) or ``refused`` (a bad goal in its place); ``state``
    (``/goal_state``) says which and why, the robot gets one stop, and nothing resumes the goal
    but a new ``/goal_pose``."""

    def __init__(self, policy, layout: ScanLayout | None = None, config: NodeConfig | None = None,
                 follow_plan: bool = False) -> None:
        self.policy = policy
        # a planner (``curlnav.nav``: ``reset(world, pair)``, ``act(observation, info)``) gets
        # the odometry pose as ``info["pose"]`` and a reset, without world or pair, on each new goal
        self.agent = policy if callable(getattr(policy, "act", None)) and callable(getattr(policy, "reset", None)) \
            else None
        self.layout = layout or ScanLayout()
        self.config = config or NodeConfig()
        self.follow_plan = follow_plan
        self.counts: Counter[str] = Counter()
        self.goal: tuple[float, float] | None = None
        self.plan: GlobalPlan | None = None
        self.state = "idle"
        self._scan: tuple[np.ndarray, np.ndarray] | None = None
        self._scan_t = -math.inf
        self._scan_refused: str | None = None
        self._pose: tuple[float, float, float] | None = None
        self._odom_t = -math.inf
        self._odom_last: tuple[float, float, float | None, float, object] | None = None  # x, y, stamp, t, source
        self._stacks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # ranges, labels, goals
        self._progress = ProgressChecker(self.config.progress_m, self.config.give_up_s)  # clock: seconds
        self._ended_goal: tuple[float, float] | None = None
        self._stop_pending = False
        self._reset_agent = False  # the planner is reset before its first action for a goal

    # -- inputs -------------------------------------------------------------------------------------
    def on_scan(self, scan, now: float) -> bool:
        """Take a ``sensor_msgs/LaserScan``; False (and counted) when refused."""
        frame = scan.header.frame_id
        try:
            if frame != self.config.scan_frame:
                raise ScanRefused(f"frame {frame!r}, expected {self.config.scan_frame!r}")
            self._scan = resample_scan(scan, self.layout, self.config.max_nan_fraction)
        except ScanRefused as exc:
            self.counts["scans_refused"] += 1
            self.counts[f"scans_refused: {str(exc).split(':')[0]}"] += 1
            self._scan_refused = str(exc)
            return False
        self.counts["scans"] += 1
        self._scan_t, self._scan_refused = now, None
        return True

    def on_odom(self, odom, now: float, source=None) -> bool:
        """Take a ``nav_msgs/Odometry`` (``source``: the publication it came from, when known);
        False (and counted) when not in ``odom_frame``, not finite or beyond ``ODOM_BOUND_M``.
        A jump, time going back or a new source ends the goal (``odometry_reset``)."""
        p = odom.pose.pose
        x, y, yaw = float(p.position.x), float(p.position.y), _yaw(p.orientation)
        if odom.header.frame_id != self.config.odom_frame or not all(map(math.isfinite, (x, y, yaw))) \
                or max(abs(x), abs(y)) > ODOM_BOUND_M:
            self.counts["odom_refused"] += 1
            return False
        self.counts["odom"] += 1
        stamp = _stamp_s(odom.header)
        why = self._odometry_restart(x, y, stamp, now, source)
        self._odom_last = (x, y, stamp, now, source)
        self._pose, self._odom_t = (x, y, yaw), now
        if why is not None:
            self.counts["odometry_resets"] += 1
            if self.goal is not None:
                self._end(f"odometry_reset: {why}")
        return True

    def _odometry_restart(self, x: float, y: float, stamp: float | None, now: float, source) -> str | None:
        """Why this odometry cannot follow the last one (the robot or its odometry restarted), or None."""
        if self._odom_last is None:
            return None
        x0, y0, stamp0, _, source0 = self._odom_last
        if source is not None and source0 is not None and source != source0:
            return "a new /odom publisher"
        if stamp is not None and stamp0 is not None and stamp < stamp0:
            return f"odometry time went back {stamp0 - stamp:.2f} s"
        if stamp is None or stamp0 is None:
            return None  # without stamps the time between them is unknown
        speed = self.layout.max_linear_speed if math.isfinite(self.layout.max_linear_speed) else 1.0
        jump = math.hypot(x - x0, y - y0)
        if jump > ODOM_JUMP_M + 2.0 * speed * (stamp - stamp0):
            return f"odometry jumped {jump:.2f} m in {stamp - stamp0:.2f} s"
        return None

    def on_goal(self, goal) -> bool:
        """Take a ``geometry_msgs/PoseStamped`` in ``odom_frame`` with |x|, |y| within
        ``max_goal_m``: the new goal (a plan ending elsewhere is dropped). A goal refused ends the
        goal held (``refused: why``)."""
        x, y = float(goal.pose.position.x), float(goal.pose.position.y)
        frame, bound = goal.header.frame_id, self.config.max_goal_m
        why = None
        if frame != self.config.odom_frame:
            why = f"goal in frame {frame!r}, expected {self.config.odom_frame!r}"
        elif not (math.isfinite(x) and math.isfinite(y)):
            why = f"goal ({x:g}, {y:g}) not finite"
        elif max(abs(x), abs(y)) > bound:
            why = f"goal ({x:.4g}, {y:.4g}) beyond {bound:g} m of the odometry origin (--max-goal-m)"
        if why is not None:
            self.counts["goals_refused"] += 1
            self._end(f"refused: {why}")
            return False
        self.counts["goals"] += 1
        if self.plan is not None and math.dist(self.plan.goal, (x, y)) > self.config.goal_tolerance_m:
            self.plan = None
        self._start((x, y))
        return True

    def on_plan(self, path) -> bool:
        """Take a ``nav_msgs/Path`` in ``odom_frame`` (with ``follow_plan``): followed waypoint
        by waypoint; its last pose is the goal. A plan for the goal that just ended does not
        start it again (a planner re-sends its plan): that takes a new ``/goal_pose``."""
        if not self.follow_plan:
            return False
        if len(path.poses) > MAX_PLAN_POSES:
            self.counts["plans_refused"] += 1
            return False
        points = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses], dtype=np.float64)
        if path.header.frame_id != self.config.odom_frame or len(points) == 0 or not np.isfinite(points).all() \
                or np.abs(points).max() > self.config.max_goal_m:
            self.counts["plans_refused"] += 1
            return False
        end = (float(points[-1, 0]), float(points[-1, 1]))
        if self.goal is None and self._ended_goal is not None \
                and math.dist(end, self._ended_goal) <= self.config.goal_tolerance_m:
            self.counts["plans_for_an_ended_goal"] += 1
            return False
        self.counts["plans"] += 1
        start = self._pose[:2] if self._pose is not None else tuple(points[0])
        self.plan = GlobalPlan(_GivenPath(points), start, end, self.config.waypoints)
        self._plan_along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
        self._plan_points = points
        if self.goal != end:
            self._start(end)
        return True

    def on_cancel(self, message=None) -> bool:
        """Cancel the goal held (``/goal_cancel``); False when there is none."""
        if self.goal is None:
            return False
        self.counts["goals_cancelled"] += 1
        self._end("cancelled")
        return True

    def _start(self, goal: tuple[float, float]) -> None:
        # a stop still pending for a goal that ended in the same pass is superseded by the new
        # goal's commands: left set, it would make the loop act on every pass, not at rate_hz
        self.goal, self._stacks, self._ended_goal, self._stop_pending = goal, None, None, False
        self._progress.reset()
        self._reset_agent = self.agent is not None

    def _end(self, state: str) -> None:
        """The goal held (if any) ends as ``state``: one stop goes out, nothing resumes it."""
        if self.goal is not None:
            self._ended_goal, self._stop_pending = self.goal, True
        self.goal = self.plan = None
        self._progress.reset()
        self.state = state

    @property
    def stop_pending(self) -> bool:
        """A goal ended since the last ``act``: its stop has yet to go out."""
        return self._stop_pending

    # -- the control step ---------------------------------------------------------------------------
    def stop_reason(self, now: float) -> str | None:
        """Why the robot must stand still now (a safety rule), or None."""
        cfg = self.config
        if self._scan_refused is not None:
            return f"stopped: refused /scan ({self._scan_refused})"
        if now - self._scan_t > cfg.silence_s:
            return "stopped: /scan silent" if self._scan is not None else "stopped: no /scan yet"
        if now - self._odom_t > cfg.silence_s:
            return "stopped: /odom silent" if self._pose is not None else "stopped: no /odom yet"
        return None

    def to_go(self) -> float:
        """The distance still to go (m): along the plan when following one, else straight."""
        x, y, _ = self._pose
        if self.plan is None:
            return math.dist((x, y), self.goal)
        d = np.hypot(self._plan_points[:, 0] - x, self._plan_points[:, 1] - y)
        k = int(np.argmin(d))
        return float(d[k] + self._plan_along[-1] - self._plan_along[k])

    def act(self, now: float) -> Command | None:
        """The command for ``now`` (call it once per control step, after a new scan): None when
        there is no goal (nothing to send), a stop on a safety rule and once when the goal ends,
        else the policy's action scaled to m/s, rad/s and m and passed by ``guard``."""
        if self.goal is None:
            if self._stop_pending:
                self._stop_pending = False
                return Command(0.0, 0.0, 0.0, self.state)
            return None
        if self._pose is not None:  # progress, measured whether the robot may move or not
            to_go = self.to_go()
            if not self._progress.update(to_go, now) and self._progress.stalled(now):
                self.counts["goals_given_up"] += 1
                self._end(f"gave_up: no progress for {self.config.give_up_s:g} s "
                          f"({self._progress.best:.1f} m to go)")
                return self.act(now)
        reason = self.stop_reason(now)
        if reason is not None:
            return self._stop(reason)
        x, y, _ = self._pose
        if math.dist((x, y), self.goal) <= self.config.goal_tolerance_m:
            self.counts["goals_reached"] += 1
            self._end("reached")
            return self.act(now)
        lay = self.layout
        try:
            observation = self.observation()
            if self.agent is None:
                action = self.policy(observation)
            else:
                if self._reset_agent:  # a new goal: the planner starts afresh (no map, no pair)
                    self._reset_agent = False
                    self.agent.reset(None, None)
                action = self.agent.act(observation, {"pose": self._pose})
            action = np.asarray(action, dtype=np.float64).reshape(-1)
            if len(action) != 3:
                raise ValueError(f"{len(action)} values, expected 3")
        except Exception as exc:  # a broken artefact must not end the node while the robot moves
            self.counts["policy_errors"] += 1
            return self._stop(f"stopped: policy failed ({type(exc).__name__}: {str(exc)[:120]})")
        if not np.isfinite(action).all():
            command, why = Command(0.0, 0.0, 0.0, f"stopped: unsafe command (policy action {action.tolist()})"), "nan"
        else:
            v, w, arm = float(np.clip(action[0], 0, 1)), float(np.clip(action[1], -1, 1)), float(np.clip(action[2], 0, 1))
            command, why = guard(Command(v * lay.max_linear_speed, w * lay.max_angular_speed,
                                         arm * lay.arm_reach if lay.arm else 0.0, "active"), lay)
        if why is not None:
            self.counts["unsafe_commands"] += 1
            told(self.agent, np.zeros(3))
            return self._stop(command.state)
        told(self.agent, np.array([v, w, arm if lay.arm else 0.0]))
        self.state = "active"
        return command

    def observation(self) -> np.ndarray:
        """The policy's observation now: the frames pushed one per control step, oldest first,
        all filled with the current reading after a (re)start (as ``NamoEnv.reset``)."""
        lay = self.layout
        ranges, labels = self._scan
        x, y, yaw = self._pose
        target = self.plan.waypoint(x, y) if self.plan is not None else self.goal
        frame = goal_frame(x, y, yaw, *target)
        if self._stacks is None or self.state != "active":
            self._stacks = (np.repeat(ranges[None], lay.range_frames, 0), np.repeat(labels[None], lay.label_frames, 0),
                            np.repeat(frame[None], lay.goal_frames, 0))
            # the agent starts afresh with its frames: a label vote, scan memory or rescue kept from
            # before a stop would stand beside frames of now
            self._reset_agent = self.agent is not None
        else:
            for stack, new in zip(self._stacks, (ranges, labels, frame)):
                stack[:-1] = stack[1:]
                stack[-1] = new
        return np.concatenate([s.ravel() for s in self._stacks]).astype(np.float32)

    def _stop(self, state: str) -> Command:
        if state != self.state:
            self.counts["stops"] += state.startswith("stopped")
        self.state = state
        return Command(0.0, 0.0, 0.0, state)


def told(agent, action: np.ndarray) -> None:
    """Tell ``agent``'s stack the command the robot was sent, ``[v, w, L]`` (fractions): the first
    of the agent and the agents it wraps (``.policy``, front stages first) with a ``commanded``
    hook (the shield's: its push check follows the arm the robot has out). None: nothing to tell."""
    for _ in range(16):  # a stack is a handful of wrappers deep
        if agent is None:
            return
        hook = getattr(agent, "commanded", None)
        if callable(hook):
            hook(action)
            return
        agent = getattr(agent, "policy", None)


def _stamp_s(header) -> float | None:
    """The header's stamp (s), None when it has none (zero or missing)."""
    stamp = getattr(header, "stamp", None)
    if stamp is None or (stamp.sec == 0 and stamp.nanosec == 0):
        return None
    return stamp.sec + stamp.nanosec * 1e-9


def _yaw(q) -> float:
    from .messages import yaw_of

    return yaw_of(q)


# -- the DDS shell -----------------------------------------------------------------------------------------
class LatencyLog:
    """Scan in to ``/cmd_vel`` out, per acted scan (s): in this process (taken from the reader
    to written) and end to end (the scan's DDS source timestamp to written; one host's clock)."""

    def __init__(self) -> None:
        self.in_process: list[float] = []
        self.end_to_end: list[float] = []

    def add(self, taken: float, source_ns: int | None, written: float, written_ns: int) -> None:
        self.in_process.append(written - taken)
        if source_ns:
            self.end_to_end.append((written_ns - source_ns) * 1e-9)

    def summary(self) -> str:
        def part(name: str, values: list[float]) -> str:
            if not values:
                return f"{name}: none"
            ms = np.asarray(values) * 1e3
            return f"{name} median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms"
        return (f"loop latency over {len(self.in_process)} scans: {part('in process', self.in_process)}; "
                f"{part('source stamp to cmd_vel', self.end_to_end)}")


def run_node(node: PolicyNode, bus, topics: dict, stop=lambda: False, stats_every_s: float = 10.0,
             log=lambda line: print(line, file=sys.stderr, flush=True)) -> LatencyLog:
    """Run ``node`` on ``bus`` (a ``curlnav.ros2.topics.Bus``) until ``stop()``: act on each good
    scan at most ``rate_hz`` times a second, check the silence rule 20 times a second, publish
    ``/goal_state`` when it changes. Everything published passes ``guard``. A watchdog thread
    sends a stop whenever no ``/cmd_vel`` went out for ``silence_s`` while the node holds a goal
    or its last command moved the robot (a control loop blocked by a slow policy or a hostile
    message cannot leave the robot driving). Returns the latency log."""
    from .messages import build

    readers = {key: bus.reader(topics[key]) for key in ("scan", "odom", "goal_pose", "goal_cancel", "plan")
               if key in topics and (key != "plan" or node.follow_plan)}
    writers = {key: bus.writer(topics[key]) for key in ("cmd_vel", "arm_cmd", "goal_state")}
    period, silence = 1.0 / node.config.rate_hz, node.config.silence_s
    latency = LatencyLog()
    lock = threading.Lock()  # one publisher at a time: the control loop or the watchdog
    # what went out last; "idle" is not published (the first /goal_state says what became of a goal)
    sent = {"t": time.monotonic(), "moving": False, "state": node.state, "logged": node.state, "late": False}

    lines: list[str] = []  # log lines written under the lock, printed outside it (a full stderr pipe
    # must never hold the lock, so that the watchdog's stop always goes out)

    def flush_log() -> None:  # not under lock
        with lock:
            out = lines[:]
            lines.clear()
        for line in out:
            log(line)

    def write_state(state: str) -> None:  # under lock
        if state != sent["state"]:
            writers["goal_state"].write(build(topics["goal_state"].type, {"data": state}))
            sent["state"] = state
        if state != sent["logged"]:
            lines.append(f"curlnav ros2 run: {state}")
            sent["logged"] = state

    def write_command(command: Command) -> None:  # under lock
        writers["cmd_vel"].write(build(topics["cmd_vel"].type, {"linear": {"x": command.linear},
                                                                 "angular": {"z": command.angular}}))
        writers["arm_cmd"].write(build(topics["arm_cmd"].type, {"data": command.arm}))
        sent["t"], sent["moving"] = time.monotonic(), not command.is_stop or command.arm != 0.0

    def publish(command: Command, scan_taken: float | None = None, source_ns: int | None = None) -> None:
        checked, why = guard(command, node.layout)
        with lock:
            if why is not None:
                node.counts["unsafe_commands"] += 1
                node.state = checked.state
            write_command(checked)
            if scan_taken is not None and why is None:
                latency.add(scan_taken, source_ns, time.monotonic(), time.time_ns())
            sent["late"] = False
            write_state(node.state)
        flush_log()

    def watchdog(halt: threading.Event) -> None:
        while not halt.wait(0.05):
            with lock:
                quiet = time.monotonic() - sent["t"]
                if quiet > silence and (node.goal is not None or sent["moving"]):
                    write_command(Command(0.0, 0.0, 0.0, "stopped"))
                    node.counts["watchdog_stops"] += 1
                    if not sent["late"]:
                        sent["late"] = True
                        lines.append(f"curlnav ros2 run: watchdog: no /cmd_vel for {quiet:.2f} s (control loop late), "
                                     "stop sent")
                        write_state(f"stopped: control loop late (no /cmd_vel for {silence:g} s)")
            flush_log()

    halt = threading.Event()
    guard_thread = threading.Thread(target=watchdog, args=(halt,), name="curlnav-watchdog", daemon=True)
    guard_thread.start()
    last_act, last_stats = -math.inf, time.monotonic()
    try:
        while not stop():
            bus.wait(0.05)
            now = time.monotonic()
            fresh_scan, goal_before = None, node.goal
            # odometry first: a restarted robot ends the goal of before, not a goal sent to the new one;
            # cancels before goals: "cancel, then a new goal" in one pass keeps the new goal
            for odom in bus.take(readers["odom"], 64):
                node.on_odom(odom, now, source=odom.sample_info.publication_handle)
            if "goal_cancel" in readers:
                for _ in bus.take(readers["goal_cancel"], 16):
                    node.on_cancel()
            for goal in bus.take(readers["goal_pose"], 16):
                if node.on_goal(goal):
                    log(f"curlnav ros2 run: goal ({goal.pose.position.x:.2f}, {goal.pose.position.y:.2f})")
                else:
                    with lock:
                        sent["logged"] = None  # each refused goal is logged, one line each
                        write_state(node.state)
            if "plan" in readers:
                for path in bus.take(readers["plan"], 4):
                    node.on_plan(path)
            if node.goal is not None and node.goal != goal_before:
                with lock:  # the watchdog counts a new goal's silence from its start, not from the idle time before
                    sent["t"] = max(sent["t"], time.monotonic())
            for scan in bus.take(readers["scan"], 16):
                fresh_scan = scan if node.on_scan(scan, now) else None
            now = time.monotonic()
            if node.stop_pending:  # a goal ended: its stop at once
                publish(node.act(now))
            elif fresh_scan is not None and now - last_act >= 0.9 * period:
                last_act = now
                command = node.act(now)
                if command is not None:
                    publish(command, now, fresh_scan.sample_info.source_timestamp)
            elif node.goal is not None and node.stop_reason(now) is not None and (
                    now - last_act >= period or node.state == "active"):
                last_act = now  # a stop at once, then held at the control rate
                command = node.act(now)
                if command is not None:
                    publish(command)
            with lock:
                write_state(node.state)
            flush_log()
            if now - last_stats >= stats_every_s:
                last_stats = now
                log(f"curlnav ros2 run: {dict(node.counts)}; {latency.summary()}")
    finally:
        halt.set()
        guard_thread.join(1.0)
    return latency
