"""Laser odometry: the robot's pose from matching each scan to the one before, in front of an agent.

Wheel odometry drifts with the distance driven (a wheel radius a little off, a track width that
slips), and an agent that reads its goal from odometry stops where its odometry puts the goal:
under the ``harsh`` preset, about half the goals lie more than the 0.8 m tolerance away by the time
the shortest route reaches them (docs/results/2026-11-27-namo-robust/README.md). Robots match
scans for it: ``rf2o_laser_odometry`` or ``laser_scan_matcher`` feed ``robot_localization``'s EKF
beside the wheels. ``ScanMatchedPolicy`` (the suffix ``+scan-match``) does the same, map-less:

- each control step, the static returns of the newest scan (label 0, within ``range_m``) are
  matched to those of the scan before by point-to-line ICP (Gauss-Newton over ``iterations``,
  pairs further than ``pair_m`` apart dropped, each previous point's line fitted to the points of
  the beams around it: ``lines``), started from the wheels' motion between the two scans; the
  points on no line (a corner, a door jamb, a furniture leg, seen by at least ``line_points``
  beams) take part point to point (``corner_points``), as PL-ICP matchers keep them: along a
  corridor the walls' lines say nothing, and without them the wheels' drift went uncorrected
  there (the oracle's routes on the seed-90 validation floors under ``harsh`` senses:
  97 % of the scans matched against 67 %, and 7 of 30 estimates ended more than 0.8 m off
  against 13);
- scans are matched to a reference scan, not each to the one before (which adds up the noise of
  every match, even standing still); the reference is replaced once the robot is ``keyframe_m``
  from it or has turned ``keyframe_rad``;
- a match needs ``min_pairs`` pairs agreeing to ``max_rms_m``; it is then fused with the wheels'
  motion since the reference, each weighed by its information (the fit's Gauss-Newton matrix over
  its residual variance; the wheels' a ``wheel_fraction`` of their motion plus floors), as
  ``robot_localization`` fuses the two: in a straight corridor, where a scan says nothing along
  it, the wheels carry that direction. A match too far from the wheels' motion (``gate_chi2``, a
  squared Mahalanobis distance) is dropped: it laid the scan on the wrong walls. Without a match
  the wheels' motion stands; the reference is renewed only after an accepted match (or
  ``renew_after`` failures in a row), so that one dropped match is not laid down as the next
  reference;
- the estimate chains the reference poses from the episode's start (the odometry's start: the
  goal's frame), and moves on from the newest scan's pose by the wheels' motion since it was
  measured (the observation may be ``latency_steps`` late).

The observation's goal frames are recomputed from this estimate (the goal's place in the odometry
frame read from each observation and the wheel pose it was computed from, so a plan's moving
waypoint is followed too), and the agent behind is given it as ``info["odometry"]`` (the rescue's
scan map and the shield's memory are kept in it). Movable returns (balls being pushed, doors
swinging) take no part in the match.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from curlnav.layout import goal_frame
from curlnav.nav.geometry import goal_in_robot_frame, odometry
from curlnav.nav.perception.stage import FrontStage
from curlnav.nav.registry import SCAN_MATCH_SUFFIX
from curlnav.sim import EnvConfig

Pose = tuple[float, float, float]  # x, y (m), yaw (rad)


@dataclass(frozen=True)
class ScanMatchConfig:
    """The matcher's settings (m, counts, fractions)."""

    range_m: float = 8.0  # static returns nearer than this take part
    pair_m: float = 0.3  # a point and its nearest previous point further apart than this are no pair
    iterations: int = 12  # Gauss-Newton steps per match
    min_pairs: int = 40  # a match needs at least this many pairs ...
    max_rms_m: float = 0.1  # ... whose point-to-line distances have at most this RMS ...
    keyframe_m: float = 0.5  # scans are matched to a reference scan, replaced once the robot is this far from it ...
    keyframe_rad: float = 0.3  # ... or has turned this much (matching each scan to the one before adds up noise)
    #: the wheels' motion since the reference: 1-sigma error of this fraction of the distance (and
    #: of the angle turned), plus the floors below, weighed against the match's own fit
    wheel_fraction: float = 0.05
    wheel_floor_m: float = 0.01
    wheel_floor_rad: float = 0.005
    #: a match whose squared Mahalanobis distance from the wheels' motion exceeds this is dropped
    #: (14.2: the 99.7 % quantile of chi-squared with 3 degrees of freedom, "3 sigma" in 3-D)
    gate_chi2: float = 14.2
    renew_after: int = 5  # the reference is renewed after an accepted match, or after this many failures in a row
    robust_m: float = 0.05  # Cauchy weight scale of a pair's point-to-line distance
    line_beams: int = 8  # a point's line is fitted to the beams this many on either side ...
    line_m: float = 0.8  # ... whose points lie this near it ...
    line_points: int = 5  # ... at least this many of them ...
    line_flatness: float = 0.25  # ... and flat: the lesser axis at most this fraction of the greater
    #: points on no line (corners, door jambs, legs) seen by at least ``line_points`` beams take part
    #: too, point to point: along a corridor, the walls' lines say nothing and only they do
    corner_points: bool = True

    def __post_init__(self) -> None:
        for name in ("range_m", "pair_m", "max_rms_m", "keyframe_m", "keyframe_rad", "wheel_fraction", "wheel_floor_m",
                     "wheel_floor_rad", "gate_chi2", "robust_m", "line_m", "line_flatness"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"scan match: {name} must be a positive number, got {value!r}")
        if not isinstance(self.corner_points, bool):
            raise ValueError(f"scan match: corner_points must be true or false, got {self.corner_points!r}")
        for name in ("iterations", "min_pairs", "renew_after", "line_beams", "line_points"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 10_000):
                raise ValueError(f"scan match: {name} must be a whole number 1-10000, got {value!r}")


def compose(a: Pose, b: Pose) -> Pose:
    """Pose ``b`` (given in the frame of ``a``) in the frame ``a`` is given in."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
            math.atan2(math.sin(a[2] + b[2]), math.cos(a[2] + b[2])))


def relative(a: Pose, b: Pose) -> Pose:
    """Pose ``b`` seen from pose ``a`` (both in one frame): ``compose(a, relative(a, b)) == b``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2])))


def lines(points: np.ndarray, config: ScanMatchConfig) -> tuple[np.ndarray, np.ndarray]:
    """The points of ``points`` (``(n, 2)``, m, in beam order) that lie on a line, moved onto it,
    and the line's unit normal at each: a principal-axis fit to the points of the beams within
    ``line_beams`` on either side that lie within ``line_m``, kept where at least ``line_points``
    of them do and they are flat (the lesser axis at most ``line_flatness`` of the greater), so
    that a few centimetres of range noise on points a few centimetres apart do not turn a wall.
    With ``corner_points``, the points whose window holds ``line_points`` but is not flat are kept
    as they are, with a zero normal: ``match`` pairs them point to point."""
    n = len(points)
    k = config.line_beams
    index = np.arange(n)[:, None] + np.arange(-k, k + 1)[None, :]
    valid = (index >= 0) & (index < n)
    near = points[np.clip(index, 0, n - 1)]  # (n, 2k+1, 2)
    valid &= np.hypot(*(near - points[:, None, :]).transpose(2, 0, 1)) < config.line_m
    count = valid.sum(axis=1)
    w = valid[..., None]
    mean = (near * w).sum(axis=1) / np.maximum(count, 1)[:, None]
    d = (near - mean[:, None, :]) * w
    a, b, c = (d[..., 0] ** 2).sum(1), (d[..., 0] * d[..., 1]).sum(1), (d[..., 1] ** 2).sum(1)
    half, root = (a + c) / 2, np.sqrt(((a - c) / 2) ** 2 + b ** 2)
    major, minor = half + root, half - root
    angle = 0.5 * np.arctan2(2 * b, a - c)  # of the greater axis: the line's direction
    keep = (count >= config.line_points) & (minor <= config.line_flatness ** 2 * np.maximum(major, 1e-12))
    normals = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
    # each point moved onto its fitted line (the line's centroid plus the point's offset along it):
    # the fit averages the range noise of the window, the point alone does not
    along = np.einsum("ij,ij->i", points - mean, np.stack([np.cos(angle), np.sin(angle)], axis=1))
    on_line = mean + along[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    if not config.corner_points:
        return on_line[keep], normals[keep]
    corner = ~keep & (count >= config.line_points)  # no line, but no lone return either
    normals[corner] = 0.0  # a point feature: matched point to point (``match``)
    on_line[corner] = points[corner]
    both = keep | corner
    return on_line[both], normals[both]


def match(reference: tuple[np.ndarray, np.ndarray], current: np.ndarray, guess: Pose,
          config: ScanMatchConfig) -> tuple[Pose, np.ndarray] | None:
    """The pose of the current scan's frame in the reference scan's frame that lays ``current``
    (``(n, 2)`` robot-frame points, m) onto the reference's lines (``lines`` of its points),
    started from ``guess``, and the fit's information matrix ``(3, 3)`` (1/m², 1/rad²); None
    when too few pairs agree (module docstring)."""
    points, normals = reference
    if len(points) < config.min_pairs or len(current) < config.min_pairs:
        return None
    tree = cKDTree(points)
    x, y, yaw = guess
    last = config.iterations  # the pass that only scores the pose it ends at
    for iteration in range(config.iterations + 1):
        c, s = math.cos(yaw), math.sin(yaw)
        moved = np.stack([x + c * current[:, 0] - s * current[:, 1], y + s * current[:, 0] + c * current[:, 1]], axis=1)
        distance, index = tree.query(moved, distance_upper_bound=config.pair_m)
        paired = np.isfinite(distance)
        if paired.sum() < config.min_pairs:
            return None
        n, p, q = normals[index[paired]], points[index[paired]], moved[paired]
        point = ~n.any(axis=1)  # a point feature: two residuals, along x and along y
        if point.any():
            p, q = np.concatenate([p, p[point]]), np.concatenate([q, q[point]])
            n[point] = (1.0, 0.0)  # n is the paired rows' own copy (fancy indexing)
            n = np.concatenate([n, np.tile([0.0, 1.0], (int(point.sum()), 1))])
        residual = np.einsum("ij,ij->i", n, q - p)
        arm = q - np.array([x, y])
        jacobian = np.stack([n[:, 0], n[:, 1], n[:, 1] * arm[:, 0] - n[:, 0] * arm[:, 1]], axis=1)
        weight = 1.0 / (1.0 + (residual / config.robust_m) ** 2)  # Cauchy: a pair on the wrong wall counts little
        hessian = jacobian.T @ (jacobian * weight[:, None])
        if iteration == last:
            break
        try:
            step = np.linalg.solve(hessian + 1e-9 * np.eye(3), -jacobian.T @ (weight * residual))
        except np.linalg.LinAlgError:
            return None
        x, y, yaw = x + step[0], y + step[1], yaw + step[2]
        if abs(step[0]) + abs(step[1]) < 1e-5 and abs(step[2]) < 1e-5:
            last = iteration + 1  # converged: score this pose next
    rms = float(np.sqrt(np.sum(weight * residual ** 2) / np.sum(weight)))
    if rms > config.max_rms_m:
        return None
    # the fit's information (inverse covariance) in (x, y, yaw): weak along a corridor, where the
    # fusion with the wheels lets the wheels speak
    information = hessian / max(rms, config.robust_m / 5) ** 2
    return (float(x), float(y), math.atan2(math.sin(yaw), math.cos(yaw))), information


def fuse(fitted: tuple[Pose, np.ndarray], predicted: Pose, wheels_moved: Pose, config: ScanMatchConfig) -> Pose | None:
    """The motion since the reference: the match's and the prediction's, each weighed by its
    information (the wheels': ``wheel_fraction`` of ``wheels_moved`` plus the floors); None when
    the two disagree by more than ``gate_chi2`` (their squared Mahalanobis distance, as
    ``robot_localization``'s rejection thresholds): a match that laid the scan on the wrong walls."""
    (pose, information) = fitted
    sigma_xy = config.wheel_fraction * math.hypot(wheels_moved[0], wheels_moved[1]) + config.wheel_floor_m
    sigma_yaw = config.wheel_fraction * abs(wheels_moved[2]) + config.wheel_floor_rad
    wheels = np.diag([sigma_xy ** -2, sigma_xy ** -2, sigma_yaw ** -2])
    a, b = np.array(pose), np.array(predicted)
    a[2] = b[2] + math.atan2(math.sin(a[2] - b[2]), math.cos(a[2] - b[2]))  # the same turn, unwrapped
    difference = a - b
    covariance = np.linalg.inv(wheels) + np.linalg.inv(information + 1e-9 * np.eye(3))
    if float(difference @ np.linalg.solve(covariance, difference)) > config.gate_chi2:
        return None
    fused = np.linalg.solve(information + wheels, information @ a + wheels @ b)
    return (float(fused[0]), float(fused[1]), math.atan2(math.sin(fused[2]), math.cos(fused[2])))


class ScanMatchedPolicy(FrontStage):
    """``policy`` (``obs -> action`` or an ``EpisodeAgent``) fed goal frames and odometry from
    laser odometry (module docstring): ``act(observation, info) -> action``. ``pose`` is the
    estimate of now; ``matched`` and ``unmatched`` count the steps the scans and the wheels gave."""

    control_role = "laser-odometry"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    suffix = SCAN_MATCH_SUFFIX

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], env_config: EnvConfig | None = None,
                 config: ScanMatchConfig | None = None, label: str | None = None) -> None:
        self.config = config or ScanMatchConfig()
        super().__init__(policy, env_config, label)

    def _clear(self) -> None:
        # the reference scan: its lines, the estimate and the wheel pose when it was measured
        self._reference: tuple[tuple[np.ndarray, np.ndarray], Pose, Pose] | None = None
        self._wheels_seen: Pose | None = None  # the wheel pose of the last scan
        self._failures = 0  # matches dropped in a row
        self._seen: Pose | None = None  # the estimate at the last scan
        self._frames: np.ndarray | None = None  # (goal_frames, 3)
        self.pose: Pose | None = None
        self.matched = self.unmatched = 0
        super()._clear()

    def static_points(self, ranges: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """``(n, 2)`` robot-frame points (m), in beam order, of the static returns within ``range_m``."""
        keep = (labels < 0.5) & (ranges < min(self.config.range_m, self.max_range - 1e-3))
        r = ranges[keep].astype(np.float64)
        return np.stack([r * self.beam_cos[keep], r * self.beam_sin[keep]], axis=1)

    def update(self, ranges: np.ndarray, labels: np.ndarray, wheels_now: Pose) -> Pose:
        """Take the newest scan and the wheel odometry now; return the estimate at the scan's time."""
        cfg = self.config
        self.poses.append(wheels_now)
        wheels_seen = self.poses[0]  # the wheel pose the newest scan was measured at
        points = self.static_points(ranges, labels)
        if self._reference is None:
            self._seen = wheels_seen  # the start: odometry and estimate agree
        else:
            lines_ref, estimate_ref, wheels_ref = self._reference
            wheels_moved = relative(wheels_ref, wheels_seen)  # since the reference, by the wheels
            predicted = relative(estimate_ref, compose(self._seen, relative(self._wheels_seen, wheels_seen)))
            fitted = match(lines_ref, points, predicted, cfg)
            moved = None if fitted is None else fuse(fitted, predicted, wheels_moved, cfg)
            self.matched += moved is not None
            self.unmatched += moved is None
            self._failures = 0 if moved is not None else self._failures + 1
            self._seen = compose(estimate_ref, predicted if moved is None else moved)
        self._wheels_seen = wheels_seen
        away = None if self._reference is None else relative(self._reference[1], self._seen)
        if away is None or self._failures >= cfg.renew_after or (self._failures == 0 and (
                math.hypot(away[0], away[1]) > cfg.keyframe_m or abs(away[2]) > cfg.keyframe_rad)):
            self._reference = (lines(points, cfg), self._seen, wheels_seen)
            self._failures = 0
        self.pose = compose(self._seen, relative(wheels_seen, wheels_now))
        return self._seen

    def observation(self, observation: np.ndarray, info: dict) -> np.ndarray:
        """``observation`` with its goal frames seen from the estimate (``update`` called)."""
        obs = np.asarray(observation, dtype=np.float32)
        ranges, labels, goal_shown = self.layout.newest_frame(obs)
        wheels_now = odometry(info)
        seen = self.update(ranges, labels, wheels_now)
        # the goal (or a plan's waypoint) in the odometry frame: where the observation puts it,
        # from the wheel pose the scan was measured at, as the environment and the node compute it
        goal = compose(self.poses[0], (*goal_in_robot_frame(goal_shown), 0.0))
        frame = goal_frame(*seen, goal[0], goal[1])
        count = self.layout.goal_frames
        self._frames = (np.repeat(frame[None], count, 0) if self._frames is None
                        else np.vstack([self._frames[1:], frame[None]]))
        out = obs.copy()
        out[-3 * count:] = self._frames.ravel()
        return out

    def inner_info(self, info: dict) -> dict:
        return {**info, "odometry": self.pose}  # the helpers behind keep their maps in the estimate's frame
