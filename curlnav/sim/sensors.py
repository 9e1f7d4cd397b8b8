"""Imperfect senses: the LiDAR, the movable-object segmenter, wheel odometry and the drive.

``SensorModel`` holds one episode's noise state; ``NamoEnv`` makes one at each reset from
``EnvConfig.sensor_noise`` (``SensorNoiseConfig``) and a generator drawn from its episode RNG, and
makes none when the config is exact (the ``none`` preset), so the clean path stays untouched.

Per step, in this order:

- **Drive** (``Actuator``): the commanded ``(v, w)`` loses a slip fraction (half-normal, 1-sigma
  ``wheel_slip``), follows it with a first-order lag (``actuation_lag``, s) and within acceleration
  limits (``max_linear_accel``, ``max_angular_accel``), one value per physics sub-step.
- **Persistent errors** (``curlnav.sim.lidar_faults.LidarFaults``, when the preset sets any):
  mislabelled, dark, glass and phantom surfaces and missed objects for the whole episode, the
  LiDAR's mount off in yaw and height, the arm hiding the beams behind it; applied to the true scan
  first.
- **Scan** (``corrupt_scan``): Gaussian range noise (``range_sigma`` + ``range_sigma_fraction`` x
  range) on beams with a return; movable objects missed whole (each run of movable beams with
  probability ``label_error``) and false movable runs on other beams with a return (a fraction
  ``label_error`` of them, in runs of ``label_run`` beams on average); then each beam, from one
  uniform draw, returns nothing (``dropout``: ``lidar_max_range``, the value the simulator gives
  for nothing within range, as a ROS ``LaserScan``'s +inf) or a spurious short return
  (``spurious``: uniform in [0, range], a mixed pixel). Dropped and spurious beams are labelled 0.
- **Odometry** (``Odometry``): the pose estimate integrates the measured motion, which is the true
  motion with per-episode biases (scale and sideways: 1-sigma ``odometry_drift`` per metre) plus as
  much again in per-step noise, and the wheels' motion before slip. Its heading comes from the
  wheels (``heading="wheels"``: rotation scale 1-sigma ``odometry_rotation_drift`` per radian, plus
  as much per-step noise; slip counts here too) or from a gyro fused in (``heading="imu"``, as the
  Husky's and the Jackal's robot_localization EKFs take it: the true turn with a per-episode scale
  error, 1-sigma ``gyro_scale``, a per-episode bias, 1-sigma ``gyro_bias`` rad/s, integrated over
  the control period, and angle random walk, ``gyro_noise`` rad/s/sqrt(Hz); wheel slip does not
  fool a gyro). The goal frames of the observation are computed from this estimate, so their error
  grows with the distance travelled and the angle turned (or the time, for a gyro's bias).
- **Latency** (``latency_steps`` = k): the observation's newest frame (ranges, labels, goal) is the
  one measured k control periods ago.

Every step draws the same number of values whatever the state, so agents given the same reset
seed see the same noise draws.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from curlnav.layout import beam_angles

from .config import EnvConfig, SensorNoiseConfig
from .lidar_faults import LidarFaults


def corrupt_scan(ranges: np.ndarray, labels: np.ndarray, noise: SensorNoiseConfig, max_range: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Noisy copies of one scan: ``ranges`` (m, float32, shape ``(beams,)``) and ``labels`` (0/1).

    Draws six arrays of ``beams`` values from ``rng``, whatever the magnitudes."""
    n = len(ranges)
    r = ranges.astype(np.float64)
    returned = r < max_range
    z = rng.standard_normal(n)
    miss_u = rng.random(n)
    start_u = rng.random(n)
    run_length = rng.geometric(1.0 / noise.label_run, n)
    beam_u = rng.random(n)
    spurious_u = rng.random(n)

    sigma = noise.range_sigma + noise.range_sigma_fraction * r
    noisy = np.where(returned, np.clip(r + sigma * z, 0.0, max_range), r)

    movable = labels > 0.5
    starts = movable & ~np.concatenate(([False], movable[:-1]))
    run_id = np.cumsum(starts)
    missed_run = np.zeros(n + 1, dtype=bool)
    missed_run[run_id[starts]] = miss_u[starts] < noise.label_error
    missed = movable & missed_run[run_id]
    begins = np.flatnonzero(start_u < noise.label_error / noise.label_run)
    cover = np.zeros(n + 1, dtype=np.int64)
    np.add.at(cover, begins, 1)
    np.add.at(cover, np.minimum(begins + run_length[begins], n), -1)
    false = (np.cumsum(cover[:n]) > 0) & ~movable & returned
    new_labels = (movable & ~missed) | false

    dropped = beam_u < noise.dropout
    spurious = ~dropped & (beam_u < noise.dropout + noise.spurious)
    noisy = np.where(spurious, spurious_u * noisy, noisy)
    noisy[dropped] = max_range
    new_labels &= ~(dropped | spurious)
    return noisy.astype(np.float32), new_labels.astype(np.float32)


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


class Odometry:
    """A pose estimate ``(x, y, yaw)`` (map frame, m and rad) that starts at the true pose and
    drifts by a fraction of the distance travelled and of the angle turned."""

    def __init__(self, pose: tuple[float, float, float], noise: SensorNoiseConfig, rng: np.random.Generator,
                 period: float = 0.2) -> None:
        """``period``: s between updates (the control period), over which a gyro's bias integrates."""
        self.pose = pose
        self._noise = noise
        self._rng = rng
        self._period = period
        # per-episode biases: a wheel radius and a track width a little off (calibration)
        self._scale, self._sideways, self._turn = rng.standard_normal(3) * (
            noise.odometry_drift, noise.odometry_drift, noise.odometry_rotation_drift)
        self._gyro_scale = self._gyro_bias = 0.0
        if noise.heading == "imu":  # two more draws, only for a gyro: the wheels' stream is unchanged
            self._gyro_scale, self._gyro_bias = rng.standard_normal(2) * (noise.gyro_scale, noise.gyro_bias)
        self.travelled = 0.0  # m, true distance since the reset

    def update(self, before: tuple[float, float, float], after: tuple[float, float, float],
               slip: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float, float]:
        """Integrate the motion from true pose ``before`` to ``after``; ``slip``: the fractions of
        the wheels' linear and angular motion the base lost (the wheels, so the odometry, saw more)."""
        x0, y0, yaw0 = before
        x1, y1, yaw1 = after
        c, s = math.cos(yaw0), math.sin(yaw0)
        dx, dy = c * (x1 - x0) + s * (y1 - y0), -s * (x1 - x0) + c * (y1 - y0)
        turn = _wrap(yaw1 - yaw0)
        true_turn = turn
        dx, dy, turn = dx / (1 - slip[0]), dy / (1 - slip[0]), turn / (1 - slip[1])
        d = math.hypot(dx, dy)
        self.travelled += math.hypot(x1 - x0, y1 - y0)
        z = self._rng.standard_normal(3)
        noise = self._noise
        drift, rot = noise.odometry_drift, noise.odometry_rotation_drift
        mx = dx * (1 + self._scale) + drift * d * z[0]
        my = dy + (self._sideways + drift * z[1]) * d
        if noise.heading == "imu":
            mturn = (true_turn * (1 + self._gyro_scale) + self._gyro_bias * self._period
                     + noise.gyro_noise * math.sqrt(self._period) * z[2])
        else:
            mturn = turn * (1 + self._turn) + rot * abs(turn) * z[2]
        ex, ey, eyaw = self.pose
        ce, se = math.cos(eyaw), math.sin(eyaw)
        self.pose = (ex + ce * mx - se * my, ey + se * mx + ce * my, _wrap(eyaw + mturn))
        return self.pose


class Actuator:
    """The base's velocity response: slip, first-order lag and acceleration limits.

    ``profile(v, w)`` gives the velocities (m/s, rad/s) of each physics sub-step of one control
    period, shapes ``(substeps,)``, and keeps the last as the state for the next period."""

    def __init__(self, cfg: EnvConfig, noise: SensorNoiseConfig, rng: np.random.Generator) -> None:
        self._noise = noise
        self._rng = rng
        self._dt = cfg.physics_timestep
        self._substeps = cfg.physics_substeps
        self.velocity = (0.0, 0.0)
        self.slip = (0.0, 0.0)

    def profile(self, linear: float, angular: float) -> tuple[np.ndarray, np.ndarray]:
        noise = self._noise
        z = np.abs(self._rng.standard_normal(2)) * noise.wheel_slip
        self.slip = (min(float(z[0]), 0.9), min(float(z[1]), 0.9))
        out = np.empty((2, self._substeps))
        follow = 1.0 - math.exp(-self._dt / noise.actuation_lag) if noise.actuation_lag > 0 else 1.0
        limits = (noise.max_linear_accel * self._dt, noise.max_angular_accel * self._dt)
        state = list(self.velocity)
        for i, target in enumerate((linear * (1 - self.slip[0]), angular * (1 - self.slip[1]))):
            value = state[i]
            for k in range(self._substeps):
                step = (target - value) * follow
                if limits[i] > 0:
                    step = min(max(step, -limits[i]), limits[i])
                value += step
                out[i, k] = value
            state[i] = value
        self.velocity = (state[0], state[1])
        return out[0], out[1]


class SensorModel:
    """One episode's imperfect senses (see the module docstring). ``noise`` is the episode's
    config (already scaled when the experiment randomises it)."""

    def __init__(self, cfg: EnvConfig, noise: SensorNoiseConfig, rng: np.random.Generator,
                 pose: tuple[float, float, float]) -> None:
        self.noise = noise
        self.rng = rng
        self.max_range = cfg.lidar_max_range
        self.odometry = Odometry(pose, noise, rng, cfg.control_period)
        self.actuator = Actuator(cfg, noise, rng)
        self.moves_differently = noise.wheel_slip > 0 or noise.actuation_lag > 0 or (
            noise.max_linear_accel > 0 or noise.max_angular_accel > 0)
        self._delayed: deque[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]] = deque()
        #: the odometry pose of the frame ``observe`` gave last (``latency_steps`` old, as its scan)
        self.seen_pose: tuple[float, float, float] = tuple(pose)
        #: the errors that persist for the episode; None where the preset sets none (then nothing is
        #: drawn for them, so the frame-by-frame presets' streams are as before they existed)
        self.faults: LidarFaults | None = None
        if LidarFaults.wanted(noise):
            self.faults = LidarFaults(noise, rng, cfg.robot, beam_angles(cfg.lidar_fov, cfg.lidar_beams),
                                      cfg.lidar_max_range)

    @property
    def mount(self) -> tuple[float, float]:
        """The LiDAR mount's error: yaw (rad) and scan-plane height (m), to add where the scan is cast."""
        return (self.faults.mount_yaw, self.faults.mount_height) if self.faults is not None else (0.0, 0.0)

    @staticmethod
    def for_episode(cfg: EnvConfig, episode_rng: np.random.Generator,
                    pose: tuple[float, float, float]) -> SensorModel | None:
        """The model of one episode, or None when ``cfg.sensor_noise`` is exact (nothing drawn
        then, so the episode RNG's stream is that of the exact simulator)."""
        noise = cfg.sensor_noise
        if noise.is_exact:
            return None
        rng = np.random.default_rng(int(episode_rng.integers(2 ** 63)))
        if noise.randomise:
            noise = noise.scaled(float(rng.random()))
        return SensorModel(cfg, noise, rng, pose)

    def observe(self, ranges: np.ndarray, labels: np.ndarray, hits: np.ndarray | None = None,
                bodies: np.ndarray | None = None, origin: tuple[float, float] = (0.0, 0.0),
                arm_displacement: float = 0.0) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
        """The frame the observation shows now: the corrupted scan and the odometry pose, from
        ``latency_steps`` control periods ago (the first frame until then). The persistent errors
        need the beams' end points ``hits`` (m, map frame), the movable body each hit (``bodies``,
        -1: none), the LiDAR's ``origin`` (m) and the arm's displacement (m)."""
        if self.faults is not None:
            if hits is None or bodies is None:
                raise ValueError("persistent sensor errors need the scan's hit points and bodies")
            ranges, labels = self.faults.apply(ranges, labels, hits, bodies, origin, arm_displacement)
        frame = (*corrupt_scan(ranges, labels, self.noise, self.max_range, self.rng), self.odometry.pose)
        if not self._delayed:
            self._delayed.extend([frame] * self.noise.latency_steps)
        self._delayed.append(frame)
        seen = self._delayed.popleft()
        self.seen_pose = seen[2]
        return seen
