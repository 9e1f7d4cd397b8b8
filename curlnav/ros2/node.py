"""A policy artefact as a ROS 2 node: ``/scan`` + ``/odom`` + ``/goal_pose`` (+ ``/plan``) in,
``/cmd_vel`` + ``/arm_cmd`` + ``/goal_state`` out, at the policy's control rate.

``PolicyNode`` is the core (no DDS: messages in, ``Command`` out, testable directly);
``run_node`` is the shell that wires it to DDS topics and a clock.

The scan's ``intensities`` carry the per-beam movable labels (1.0: the beam's first hit is a
movable object, 0.0: static), as a movable-object segmenter writes them; any other beam layout
is resampled to the policy's (241 beams over -120..+120 deg by default; per policy beam the
nearest return of the input beams in its 1-degree bin, the bin's beams uncovered by the input
read as no return). The scanner is taken to sit at ``base_link``'s origin, facing forward.
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from curlnav.evaluation.baseline import GlobalPlan, WaypointConfig


@dataclass(frozen=True)
class NodeConfig:
    """How the node runs (topic names live in ``curlnav.ros2.topics``)."""

    rate_hz: float = 5.0  # acts on each scan, at most this often (the policy's control rate)
    silence_s: float = 0.5  # stop when /scan or /odom is older than this (s)
    scan_frame: str = "base_link"  # the frame /scan must come in
    odom_frame: str = "odom"  # the frame /odom (and /goal_pose, /plan) must come in
    goal_tolerance_m: float = 0.8  # the goal is reached within this distance (m)
    # /plan following (--global-plan); the node has no map, so no line-of-sight check against one
    waypoints: WaypointConfig = field(default_factory=lambda: WaypointConfig(line_of_sight=False))

    def __post_init__(self) -> None:
        for name in ("rate_hz", "silence_s", "goal_tolerance_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")


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

    @classmethod
    def of(cls, metadata: dict) -> ScanLayout:
        obs = metadata.get("observation", {})
        layout = obs.get("layout", {})
        scale = metadata.get("action", {}).get("scale", [1.0, 1.0, 0.5])
        return cls(beams=int(layout.get("beams", 241)), fov_rad=float(obs.get("lidar_fov_rad", math.radians(240.0))),
                   max_range_m=float(layout.get("max_range", 10.0)), range_frames=int(layout.get("range_frames", 4)),
                   label_frames=int(layout.get("label_frames", 4)), goal_frames=int(layout.get("goal_frames", 10)),
                   max_linear_speed=float(scale[0]), max_angular_speed=float(scale[1]), arm_reach=float(scale[2]),
                   control_period_s=float(obs.get("control_period_s", 0.2)))

    @property
    def observation_size(self) -> int:
        return (self.range_frames + self.label_frames) * self.beams + 3 * self.goal_frames

    @property
    def angles(self) -> np.ndarray:
        """(beams,) policy beam angles (rad), beam 0 on the right."""
        return np.linspace(-self.fov_rad / 2, self.fov_rad / 2, self.beams)


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


class ScanRefused(ValueError):
    """A scan the node will not act on (NaN, wrong length, wrong frame, labels not 0..1)."""


def resample_scan(scan, layout: ScanLayout) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges, labels)``, each ``(layout.beams,)`` float32, of a ``sensor_msgs/LaserScan``
    (any object with its fields), or ``ScanRefused`` naming what is wrong. +Inf and ranges
    beyond ``range_max`` read ``layout.max_range_m`` (no return), -Inf reads 0 (too close)."""
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    labels = np.asarray(scan.intensities, dtype=np.float64)
    n = len(ranges)
    if n == 0:
        raise ScanRefused("no ranges")
    if len(labels) != n:
        raise ScanRefused(f"{len(labels)} intensities for {n} ranges: one movable label per beam expected")
    a0, a1, inc = float(scan.angle_min), float(scan.angle_max), float(scan.angle_increment)
    if not (math.isfinite(a0) and math.isfinite(a1) and math.isfinite(inc)) or inc == 0.0:
        raise ScanRefused(f"bad angles: angle_min {a0}, angle_max {a1}, angle_increment {inc}")
    expected = (a1 - a0) / inc + 1
    if abs(expected - n) > 1.01:
        raise ScanRefused(f"wrong length: {n} ranges, angle_min..angle_max by angle_increment gives {expected:.0f}")
    if np.isnan(ranges).any():
        raise ScanRefused(f"NaN range at beam {int(np.flatnonzero(np.isnan(ranges))[0])}")
    if not np.isfinite(labels).all() or (labels < 0).any() or (labels > 1).any():
        raise ScanRefused("intensities must be movable labels in 0..1 (reflectivity is not a label)")
    max_range = layout.max_range_m
    range_max = float(scan.range_max) if math.isfinite(scan.range_max) and scan.range_max > 0 else max_range
    r = np.where(ranges > range_max, max_range, ranges)
    r = np.clip(np.nan_to_num(r, posinf=max_range, neginf=0.0), 0.0, max_range)
    angles = a0 + inc * np.arange(n)
    angles = (angles + math.pi) % (2 * math.pi) - math.pi
    step = layout.fov_rad / (layout.beams - 1)
    index = np.rint((angles + layout.fov_rad / 2) / step).astype(np.int64)
    inside = (index >= 0) & (index < layout.beams)
    out = np.full(layout.beams, np.inf)
    np.minimum.at(out, index[inside], r[inside])
    out_labels = np.zeros(layout.beams)
    hit = inside & (r == out[np.clip(index, 0, layout.beams - 1)])
    np.maximum.at(out_labels, index[hit], labels[hit])  # the label of the bin's nearest return
    empty = ~np.isfinite(out)
    if empty.any():  # a coarser input: the nearest input beam within its own increment
        policy_angles = layout.angles[empty]
        diff = np.abs((policy_angles[:, None] - angles[None, :] + math.pi) % (2 * math.pi) - math.pi)
        nearest = np.argmin(diff, axis=1)
        near = diff[np.arange(len(nearest)), nearest] <= abs(inc) / 2 + 1e-9
        out[np.flatnonzero(empty)[near]] = r[nearest[near]]
        out_labels[np.flatnonzero(empty)[near]] = labels[nearest[near]]
        out[~np.isfinite(out)] = max_range
    return out.astype(np.float32), (out_labels >= 0.5).astype(np.float32)


def goal_frame(x: float, y: float, yaw: float, gx: float, gy: float) -> np.ndarray:
    """The policy's goal frame ``[sign(dx) log(1+|dx|), sign(dy) log(1+|dy|), atan2(dy, dx)]`` of
    ``(gx, gy)`` seen from the pose ``(x, y, yaw)`` (robot frame, m and rad), as ``NamoEnv``."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = c * (gx - x) + s * (gy - y), -s * (gx - x) + c * (gy - y)
    return np.array([math.copysign(math.log1p(abs(dx)), dx), math.copysign(math.log1p(abs(dy)), dy),
                     math.atan2(dy, dx)], dtype=np.float32)


class _GivenPath:
    """A ``GlobalPlan`` planner that hands back a given path: when the robot strays, it joins the
    path again at the path point nearest to it."""

    def __init__(self, path: np.ndarray) -> None:
        self.path = path

    def plan(self, start: tuple[float, float], goal: tuple[float, float]) -> np.ndarray:
        k = int(np.argmin(np.hypot(self.path[:, 0] - start[0], self.path[:, 1] - start[1])))
        return np.vstack([[start], self.path[k:]])


class PolicyNode:
    """The node's core. Feed it ``on_scan``, ``on_odom``, ``on_goal``, ``on_plan`` (message
    objects with the ROS 2 fields, times in s of one clock) and call ``act(now)`` at the control
    rate; it returns the ``Command`` to publish (a stop when a safety rule holds).

    Safety: a stop (zero twist) when the last good scan or odometry is older than
    ``silence_s``, and at once when a scan is refused (until a good one comes). ``counts`` tells
    how many scans, odometry messages and goals were taken and refused, by reason."""

    def __init__(self, policy, layout: ScanLayout | None = None, config: NodeConfig | None = None,
                 follow_plan: bool = False) -> None:
        self.policy = policy
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
        self._stacks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # ranges, labels, goals

    # -- inputs -------------------------------------------------------------------------------------
    def on_scan(self, scan, now: float) -> bool:
        """Take a ``sensor_msgs/LaserScan``; False (and counted) when refused."""
        frame = scan.header.frame_id
        try:
            if frame != self.config.scan_frame:
                raise ScanRefused(f"frame {frame!r}, expected {self.config.scan_frame!r}")
            self._scan = resample_scan(scan, self.layout)
        except ScanRefused as exc:
            self.counts["scans_refused"] += 1
            self.counts[f"scans_refused: {str(exc).split(':')[0]}"] += 1
            self._scan_refused = str(exc)
            return False
        self.counts["scans"] += 1
        self._scan_t, self._scan_refused = now, None
        return True

    def on_odom(self, odom, now: float) -> bool:
        """Take a ``nav_msgs/Odometry``; False (and counted) when not in ``odom_frame`` or not finite."""
        p = odom.pose.pose
        x, y, yaw = float(p.position.x), float(p.position.y), _yaw(p.orientation)
        if odom.header.frame_id != self.config.odom_frame or not all(map(math.isfinite, (x, y, yaw))):
            self.counts["odom_refused"] += 1
            return False
        self.counts["odom"] += 1
        self._pose, self._odom_t = (x, y, yaw), now
        return True

    def on_goal(self, goal) -> bool:
        """Take a ``geometry_msgs/PoseStamped`` in ``odom_frame``: the new goal (a plan ending
        elsewhere is dropped)."""
        x, y = float(goal.pose.position.x), float(goal.pose.position.y)
        if goal.header.frame_id != self.config.odom_frame or not (math.isfinite(x) and math.isfinite(y)):
            self.counts["goals_refused"] += 1
            return False
        self.counts["goals"] += 1
        if self.plan is not None and math.dist(self.plan.goal, (x, y)) > self.config.goal_tolerance_m:
            self.plan = None
        self.goal, self._stacks = (x, y), None
        return True

    def on_plan(self, path) -> bool:
        """Take a ``nav_msgs/Path`` in ``odom_frame`` (with ``follow_plan``): followed waypoint
        by waypoint; its last pose is the goal."""
        if not self.follow_plan:
            return False
        points = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses], dtype=np.float64)
        if path.header.frame_id != self.config.odom_frame or len(points) == 0 or not np.isfinite(points).all():
            self.counts["plans_refused"] += 1
            return False
        self.counts["plans"] += 1
        start = self._pose[:2] if self._pose is not None else tuple(points[0])
        self.plan = GlobalPlan(_GivenPath(points), start, tuple(points[-1]), self.config.waypoints)
        if self.goal != tuple(points[-1]):
            self.goal, self._stacks = tuple(points[-1]), None
        return True

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

    def act(self, now: float) -> Command | None:
        """The command for ``now`` (call it once per control step, after a new scan): None when
        there is no goal (nothing to send), a stop on a safety rule and once at the goal (which
        then clears), else the policy's action scaled to m/s, rad/s and m."""
        if self.goal is None:
            return None
        reason = self.stop_reason(now)
        if reason is not None:
            return self._stop(reason)
        x, y, _ = self._pose
        if math.dist((x, y), self.goal) <= self.config.goal_tolerance_m:
            self.goal = self.plan = None
            return self._stop("reached")
        action = np.asarray(self.policy(self.observation()), dtype=np.float64)
        v, w, arm = float(np.clip(action[0], 0, 1)), float(np.clip(action[1], -1, 1)), float(np.clip(action[2], 0, 1))
        lay = self.layout
        self.state = "active"
        return Command(v * lay.max_linear_speed, w * lay.max_angular_speed, arm * lay.arm_reach, self.state)

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
    ``/goal_state`` when it changes. Returns the latency log."""
    from .messages import build

    readers = {key: bus.reader(topics[key]) for key in ("scan", "odom", "goal_pose", "plan")
               if key != "plan" or node.follow_plan}
    writers = {key: bus.writer(topics[key]) for key in ("cmd_vel", "arm_cmd", "goal_state")}
    period = 1.0 / node.config.rate_hz
    latency = LatencyLog()
    last_act, last_stats, published_state = -math.inf, time.monotonic(), None

    def publish(command: Command, scan_taken: float | None = None, source_ns: int | None = None) -> None:
        nonlocal published_state
        writers["cmd_vel"].write(build(topics["cmd_vel"].type, {"linear": {"x": command.linear},
                                                                 "angular": {"z": command.angular}}))
        if scan_taken is not None:
            latency.add(scan_taken, source_ns, time.monotonic(), time.time_ns())
        writers["arm_cmd"].write(build(topics["arm_cmd"].type, {"data": command.arm}))
        if command.state != published_state:
            writers["goal_state"].write(build(topics["goal_state"].type, {"data": command.state}))
            published_state = command.state
            log(f"curlnav ros2 run: {command.state}")

    while not stop():
        bus.wait(0.05)
        now = time.monotonic()
        fresh_scan = None
        for goal in bus.take(readers["goal_pose"], 16):
            if node.on_goal(goal):
                log(f"curlnav ros2 run: goal ({goal.pose.position.x:.2f}, {goal.pose.position.y:.2f})")
        if "plan" in readers:
            for path in bus.take(readers["plan"], 4):
                node.on_plan(path)
        for odom in bus.take(readers["odom"], 64):
            node.on_odom(odom, now)
        for scan in bus.take(readers["scan"], 16):
            fresh_scan = scan if node.on_scan(scan, now) else None
        now = time.monotonic()
        if fresh_scan is not None and now - last_act >= 0.9 * period:
            last_act = now
            command = node.act(now)
            if command is not None:
                publish(command, now, fresh_scan.sample_info.source_timestamp)
        elif node.goal is not None and node.stop_reason(now) is not None and (
                now - last_act >= period or node.state == "active"):
            last_act = now  # a stop at once, then held at the control rate
            publish(node.act(now))
        if now - last_stats >= stats_every_s:
            last_stats = now
            log(f"curlnav ros2 run: {dict(node.counts)}; {latency.summary()}")
    return latency
