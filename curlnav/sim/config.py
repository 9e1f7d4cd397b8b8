"""Typed, validated configuration of the robot and the NAMO environment.

Every value the paper leaves open is a field here, with the choice we made and why.
Units: metres, seconds, radians, kilograms, newtons.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any

from curlnav.files import decimal_float, decimal_int, shown


class ConfigError(ValueError):
    """A configuration value is out of range or of the wrong type."""


#: the most a robot's field may be (the unit of the field): a mobile robot that a 2-D LiDAR and a
#: pushing arm serve, with room to spare (the Husky is 0.99 m and 50 kg); beyond these the simulator
#: overflows or its time step cannot hold the robot
ROBOT_LIMITS = {"base_length": 5.0, "base_width": 5.0, "base_height": 3.0,  # m
                "base_mass": 2000.0,  # kg
                "max_linear_speed": 10.0, "max_reverse_speed": 10.0,  # m/s
                "max_angular_speed": 10.0,  # rad/s
                "drive_force": 1e6, "arm_force": 1e5,  # N
                "arm_reach": 3.0, "arm_length": 3.0, "arm_width": 1.0, "arm_thickness": 1.0,  # m
                "arm_speed": 10.0}  # m/s
#: the LiDAR's bounds: range and scan-plane height at most (m), field of view at least (rad, 1 degree)
LIDAR_MAX_RANGE_LIMIT, LIDAR_HEIGHT_LIMIT, LIDAR_FOV_MIN = 100.0, 5.0, math.radians(1.0)


@dataclass(frozen=True)
class RobotConfig:
    """A differential-drive base with a one-DOF pushing arm (the end effector).

    Presets: ``husky()`` (the paper's robot, the default) and ``jackal()`` (the BARN benchmark's);
    whole profiles, with their LiDARs, are ``curlnav.sim.robots.PROFILES``.
    """

    #: the profile's name (``husky``, ``jackal`` or a file's own): what a policy artefact records
    #: and checks against the robot it is asked to drive
    name: str = field(default="husky", metadata={"hash": "omit-default"})
    #: False: no pushing arm (the stick has no collision shape and action[2] is ignored)
    arm: bool = field(default=True, metadata={"hash": "omit-default"})
    base_length: float = 0.99  # m, along the heading
    base_width: float = 0.67  # m
    base_height: float = 0.31  # m
    base_mass: float = 50.0  # kg
    max_linear_speed: float = 1.0  # m/s at action[0] = 1 (authors' code 1.5; curriculum tasks 0.33)
    max_angular_speed: float = 1.0  # rad/s at |action[1]| = 1 (authors' code 0.8)
    drive_force: float = 3000.0  # N (and N m for the yaw drive): how hard the base motors push
    arm_reach: float = 0.5  # m, end-effector forward displacement at action[2] = 1 (UR5 limit)
    arm_length: float = 0.5  # m, the stick
    arm_width: float = 0.09  # m
    arm_thickness: float = 0.03  # m
    arm_force: float = 200.0  # N, prismatic actuator limit
    arm_speed: float = 1.0  # m/s, prismatic actuator speed limit
    #: m/s the base may back up at: the Husky's 0.5 (its datasheet's top speed is 1.0 m/s both ways;
    #: backing up is kept slow, the LiDAR does not see behind). The policies drive forward only
    #: (action[0] in 0..1, as in the paper); a negative action[0], down to -max_reverse_speed /
    #: max_linear_speed, comes only from a stack's helpers (the rescue's DWA with
    #: ``RescueConfig.reverse``, the shield's recovery with ``reverse_recovery``, the manoeuvre behind a
    #: global plan: ``curlnav.nav.recovery.manoeuvre``).
    #: 0: the base drives forward only (a robot profile file's default).
    max_reverse_speed: float = field(default=0.5, metadata={"hash": "omit-default"})

    @staticmethod
    def husky() -> RobotConfig:
        return RobotConfig()

    @staticmethod
    def jackal() -> RobotConfig:
        """Clearpath's Jackal (its published 0.508 x 0.430 x 0.250 m, 17 kg, 2.0 m/s), no arm; turn
        rate 1.57 rad/s, the BARN Challenge's own move_base limit; it drives both ways (backing up
        kept to 0.5 m/s: the LiDAR does not see behind it)."""
        return RobotConfig(name="jackal", arm=False, base_length=0.508, base_width=0.430, base_height=0.25,
                           base_mass=17.0, max_linear_speed=2.0, max_angular_speed=1.57, arm_reach=0.3,
                           arm_length=0.3, drive_force=1000.0, max_reverse_speed=0.5)

    @property
    def reverse_fraction(self) -> float:
        """The lowest ``action[0]`` the base takes: ``-reverse_fraction`` backs up at
        ``max_reverse_speed`` (0: forward only, the policies' range)."""
        return self.max_reverse_speed / self.max_linear_speed

    @property
    def radius(self) -> float:
        """Circumscribed radius of the base footprint (m)."""
        return 0.5 * math.hypot(self.base_length, self.base_width)

    def validate(self) -> None:
        if not isinstance(self.name, str) or not re.fullmatch(r"[a-z0-9][a-z0-9_-]{0,39}", self.name):
            raise ConfigError(f"robot.name must be 1-40 characters of a-z, 0-9, - and _, got {self.name!r}")
        if not isinstance(self.arm, bool):
            raise ConfigError(f"robot.arm must be true or false, got {self.arm!r}")
        _positive(self, [f.name for f in dataclasses.fields(self) if f.name not in ("name", "arm", "max_reverse_speed")])
        if not (isinstance(self.max_reverse_speed, (int, float)) and not isinstance(self.max_reverse_speed, bool)
                and math.isfinite(self.max_reverse_speed) and self.max_reverse_speed >= 0):
            raise ConfigError(f"robot.max_reverse_speed must be a number of m/s of at least 0 (0: forward only), "
                              f"got {self.max_reverse_speed!r}")
        _at_most(self, ROBOT_LIMITS)


@dataclass(frozen=True)
class RewardConfig:
    """Equation (1) of the paper. ``R = r_hg + r_rg + r_mv + r_bc + r_ec`` (plus ``progress``, ours,
    0 by default).

    "Heading toward the goal" is not defined in the paper. ``heading_rule``:
    ``"progress"`` (default): the distance to the goal shrank by more than ``progress_epsilon``
    this step; ``"bearing"``: the goal lies within ``heading_cone`` of the robot's heading.
    """

    heading_toward: float = 0.2
    heading_away: float = -0.2
    reach_goal: float = 200.0
    moving: float = 0.1
    not_moving: float = -0.1
    moving_threshold: float = 0.03  # m of position change per step
    base_collision: float = -10.0
    end_effector_collision: float = -0.5
    heading_rule: str = "progress"
    progress_epsilon: float = 1e-3  # m
    heading_cone: float = math.radians(30.0)
    #: not in the paper: reward per metre the distance to the goal shrank this step (negative when
    #: it grew), so a circle or a back-and-forth earns nothing net, unlike ``heading_toward`` /
    #: ``heading_away`` (which pay the steps toward and charge the steps away alike, whatever their
    #: length). 0 (the default) leaves the paper's reward; left out of the config hash while 0
    progress: float = field(default=0.0, metadata={"hash": "omit-default"})

    def validate(self) -> None:
        if isinstance(self.progress, bool) or not isinstance(self.progress, (int, float)) or not math.isfinite(
                self.progress) or self.progress < 0:
            raise ConfigError(f"reward.progress must be a number >= 0 (reward per metre), got {self.progress!r}")
        if self.heading_rule not in ("progress", "bearing"):
            raise ConfigError(f"reward.heading_rule must be 'progress' or 'bearing', got {self.heading_rule!r}")
        _positive(self, ["moving_threshold", "heading_cone"])


#: The magnitudes of ``SensorNoiseConfig`` (every field but ``preset``, ``randomise`` and ``heading``), in order.
SENSOR_NOISE_FIELDS = ("range_sigma", "range_sigma_fraction", "dropout", "spurious", "label_error", "label_run",
                       "latency_steps", "odometry_drift", "odometry_rotation_drift", "gyro_bias", "gyro_scale",
                       "gyro_noise", "max_linear_accel", "max_angular_accel", "actuation_lag", "wheel_slip",
                       "block_label_error", "object_label_error", "dark_blocks", "glass_blocks", "phantom_blocks",
                       "mount_yaw", "mount_height", "arm_occlusion")

_ADDED_WITH_IMU = ("gyro_bias", "gyro_scale", "gyro_noise")
#: the errors that persist for an episode (``curlnav.sim.lidar_faults``): counted in a config's hash
#: only where set, so every config from before they existed keeps its hash
PERSISTENT_FIELDS = ("block_label_error", "object_label_error", "dark_blocks", "glass_blocks", "phantom_blocks",
                     "mount_yaw", "mount_height", "arm_occlusion")
_NO_PERSISTENT = dict.fromkeys(PERSISTENT_FIELDS, 0.0)

#: Where the odometry's heading comes from in each preset (``SensorNoiseConfig.heading``):
#: ``wheels`` (the wheels' differential, ``odometry_rotation_drift``) or ``imu`` (a gyro fused
#: with the wheels' translation, as the Husky's and the Jackal's robot_localization EKFs do:
#: ``gyro_bias``, ``gyro_scale``, ``gyro_noise``).
SENSOR_NOISE_HEADINGS: dict[str, str] = {"none": "wheels", "realistic": "imu", "harsh": "imu",
                                         "realistic-frame": "imu", "harsh-frame": "imu"}

#: Named presets of ``SensorNoiseConfig``: ``none`` (exact senses, the default), ``realistic`` (a
#: robot with a datasheet LiDAR, a segmenter, wheel odometry and an IMU's heading, its LiDAR's and
#: segmenter's errors drawn afresh in every frame *and* persisting for the episode: mislabelled wall
#: blocks and objects, dark and glass surfaces, phantoms, a LiDAR mounted a little off, the arm in the
#: way) and ``harsh`` (about double). ``realistic-frame`` and ``harsh-frame``: the same without the
#: errors that persist (every error lasts one frame), the presets that figures before them measured.
#: Sources of the values: docs/guide/environment.md, "Sensor, odometry and actuation models" and
#: "Errors that persist".
_FRAME_PRESETS: dict[str, dict[str, float | int]] = {
    "none": dict(range_sigma=0.0, range_sigma_fraction=0.0, dropout=0.0, spurious=0.0, label_error=0.0,
                 label_run=1.0, latency_steps=0, odometry_drift=0.0, odometry_rotation_drift=0.0,
                 gyro_bias=0.0, gyro_scale=0.0, gyro_noise=0.0,
                 max_linear_accel=0.0, max_angular_accel=0.0, actuation_lag=0.0, wheel_slip=0.0),
    "realistic": dict(range_sigma=0.03, range_sigma_fraction=0.0, dropout=0.02, spurious=0.005, label_error=0.05,
                      label_run=6.0, latency_steps=1, odometry_drift=0.02, odometry_rotation_drift=0.05,
                      gyro_bias=math.radians(0.02), gyro_scale=0.01, gyro_noise=math.radians(0.01),
                      max_linear_accel=3.0, max_angular_accel=6.0, actuation_lag=0.05, wheel_slip=0.02),
    "harsh": dict(range_sigma=0.05, range_sigma_fraction=0.01, dropout=0.05, spurious=0.01, label_error=0.10,
                  label_run=10.0, latency_steps=2, odometry_drift=0.05, odometry_rotation_drift=0.10,
                  gyro_bias=math.radians(0.04), gyro_scale=0.02, gyro_noise=math.radians(0.02),
                  max_linear_accel=1.5, max_angular_accel=3.0, actuation_lag=0.1, wheel_slip=0.05),
}
_PERSISTENT_PRESETS: dict[str, dict[str, float]] = {
    "realistic": dict(block_label_error=0.05, object_label_error=0.05, dark_blocks=0.02, glass_blocks=0.03,
                      phantom_blocks=0.01, mount_yaw=math.radians(0.5), mount_height=0.01, arm_occlusion=1.0),
    "harsh": dict(block_label_error=0.10, object_label_error=0.10, dark_blocks=0.04, glass_blocks=0.06,
                  phantom_blocks=0.02, mount_yaw=math.radians(1.0), mount_height=0.02, arm_occlusion=1.0),
}
SENSOR_NOISE_PRESETS: dict[str, dict[str, float | int]] = {
    "none": {**_FRAME_PRESETS["none"], **_NO_PERSISTENT},
    "realistic": {**_FRAME_PRESETS["realistic"], **_PERSISTENT_PRESETS["realistic"]},
    "harsh": {**_FRAME_PRESETS["harsh"], **_PERSISTENT_PRESETS["harsh"]},
    "realistic-frame": {**_FRAME_PRESETS["realistic"], **_NO_PERSISTENT},
    "harsh-frame": {**_FRAME_PRESETS["harsh"], **_NO_PERSISTENT},
}


def _field_words(exc: ConfigError) -> str:
    """A sensor-noise refusal's text without the ``sensor_noise.`` of its field names (for a command
    line's ``--sensor-set FIELD=VALUE``, which names the fields bare)."""
    return str(exc).replace("sensor_noise.", "")


@dataclass(frozen=True)
class SensorNoiseConfig:
    """How imperfect the robot's senses, odometry and drive are (``curlnav.sim.sensors``).

    Every magnitude left ``None`` takes the value of ``preset`` (``SENSOR_NOISE_PRESETS``), so a
    config names a preset and overrides only what it changes: ``SensorNoiseConfig("realistic",
    dropout=0.05)``. After construction every magnitude holds its value. The draws come from the
    environment's episode RNG (``NamoEnv.np_random``): the same reset seed gives the same noisy
    episode. The preset ``none`` (every magnitude 0) leaves the simulator exact: observations are
    bit for bit those of an environment without this config.

    Units: metres, seconds, radians; fractions in [0, 1]; a limit of 0 means "no limit".
    """

    preset: str = "none"  # the preset that magnitudes left None take their values from
    #: draw a scale s uniform in [0, 1] at each reset and use the preset's magnitudes times s
    #: (latency rounded, acceleration limits divided by s): training over a range of senses
    randomise: bool = False
    range_sigma: float | None = None  # m, Gaussian range noise (1-sigma) of every beam with a return
    range_sigma_fraction: float | None = None  # and a further 1-sigma of this fraction of the range
    dropout: float | None = None  # fraction of beams that return nothing (read lidar_max_range, label 0)
    spurious: float | None = None  # fraction of beams with a spurious short return (uniform in [0, range], label 0)
    #: movable objects missed whole (each run of movable beams, with this probability) and
    #: the fraction of other beams labelled movable, in runs of ``label_run`` beams on average
    label_error: float | None = None
    label_run: float | None = None  # beams, mean length of a false movable run (1: isolated beams)
    latency_steps: int | None = None  # control periods by which the whole observation lags
    odometry_drift: float | None = None  # 1-sigma translation error per metre travelled (fraction of distance)
    #: where the odometry's heading comes from: ``"wheels"`` or ``"imu"`` (``SENSOR_NOISE_HEADINGS``)
    heading: str | None = None
    odometry_rotation_drift: float | None = None  # heading "wheels": 1-sigma heading error per radian turned
    gyro_bias: float | None = None  # heading "imu": rad/s, 1-sigma per-episode gyro bias left after calibration
    gyro_scale: float | None = None  # heading "imu": 1-sigma per-episode gyro scale-factor error (fraction)
    gyro_noise: float | None = None  # heading "imu": rad/s/sqrt(Hz), the gyro's angle random walk
    max_linear_accel: float | None = None  # m/s^2 of the base (0: none)
    max_angular_accel: float | None = None  # rad/s^2 of the base (0: none)
    actuation_lag: float | None = None  # s, first-order time constant from command to velocity (0: none)
    wheel_slip: float | None = None  # 1-sigma fraction of the commanded motion lost to slip each step
    # -- errors that persist for the episode (curlnav.sim.lidar_faults; the map in blocks of 0.5 m)
    block_label_error: float | None = None  # fraction of wall blocks whose returns are all labelled movable
    object_label_error: float | None = None  # fraction of movable objects labelled static (missed) throughout
    dark_blocks: float | None = None  # fraction of wall blocks that return nothing at any angle (black, absorbing)
    glass_blocks: float | None = None  # fraction of wall blocks that return only near their normal (glass)
    phantom_blocks: float | None = None  # fraction of wall blocks whose returns read short by a fixed distance (a phantom)
    mount_yaw: float | None = None  # rad, 1-sigma per-episode yaw error of the LiDAR's mount
    mount_height: float | None = None  # m, 1-sigma per-episode height error of the scan plane
    #: the fraction of the extended arm's width that hides the beams behind it (self-filtered: no return); 0: none
    arm_occlusion: float | None = None

    def __post_init__(self) -> None:
        if self.preset not in SENSOR_NOISE_PRESETS:
            raise ConfigError(f"sensor_noise.preset must be one of {', '.join(SENSOR_NOISE_PRESETS)}, "
                              f"got {self.preset!r}")
        if not isinstance(self.randomise, bool):
            raise ConfigError(f"sensor_noise.randomise must be true or false, got {self.randomise!r}")
        base = SENSOR_NOISE_PRESETS[self.preset]
        for name in SENSOR_NOISE_FIELDS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, base[name])
        if self.heading is None:
            object.__setattr__(self, "heading", SENSOR_NOISE_HEADINGS[self.preset])
        self.validate()

    def validate(self) -> None:
        """Refuse values out of range, naming the field (``ConfigError``)."""
        for name in SENSOR_NOISE_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"sensor_noise.{name} must be a finite number, got {value!r}")
        if self.heading not in ("wheels", "imu"):
            raise ConfigError(f"sensor_noise.heading must be 'wheels' or 'imu', got {self.heading!r}")
        bounded = {"range_sigma": 1.0, "range_sigma_fraction": 0.5, "dropout": 1.0, "spurious": 1.0,
                   "label_error": 1.0, "odometry_drift": 1.0, "odometry_rotation_drift": 1.0,
                   "gyro_bias": 1.0, "gyro_scale": 0.5, "gyro_noise": 1.0,
                   "max_linear_accel": 1e3, "max_angular_accel": 1e3, "actuation_lag": 10.0, "wheel_slip": 0.5,
                   "block_label_error": 1.0, "object_label_error": 1.0, "dark_blocks": 1.0, "glass_blocks": 1.0,
                   "phantom_blocks": 1.0, "mount_yaw": 0.2, "mount_height": 0.2, "arm_occlusion": 1.0}
        for name, high in bounded.items():
            value = getattr(self, name)
            if not 0 <= value <= high:
                raise ConfigError(f"sensor_noise.{name} must be in [0, {high:g}], got {value!r}")
        if self.dark_blocks + self.glass_blocks + self.phantom_blocks > 1:
            raise ConfigError("sensor_noise.dark_blocks + glass_blocks + phantom_blocks must be at most 1 (a block is "
                              f"one surface), got {self.dark_blocks} + {self.glass_blocks} + {self.phantom_blocks}")
        if self.dropout + self.spurious > 1:
            raise ConfigError(f"sensor_noise.dropout + sensor_noise.spurious must be at most 1, "
                              f"got {self.dropout} + {self.spurious}")
        if not 1 <= self.label_run <= 1000:
            raise ConfigError(f"sensor_noise.label_run must be in [1, 1000] beams, got {self.label_run!r}")
        if isinstance(self.latency_steps, float) or not 0 <= self.latency_steps <= 50:
            raise ConfigError(f"sensor_noise.latency_steps must be a whole number in [0, 50], "
                              f"got {self.latency_steps!r}")

    @staticmethod
    def from_preset(name: str, **overrides: Any) -> SensorNoiseConfig:
        """Preset ``name`` with some magnitudes overridden (unknown names raise ``ConfigError``)."""
        unknown = set(overrides) - set(SENSOR_NOISE_FIELDS) - {"randomise", "heading"}
        if unknown:
            raise ConfigError(f"unknown sensor-noise field {sorted(unknown)[0]}; known: "
                              f"{', '.join(SENSOR_NOISE_FIELDS + ('heading', 'randomise'))}")
        return SensorNoiseConfig(preset=name, **overrides)

    @staticmethod
    def from_strings(preset: str, items: list[str] | tuple[str, ...] = ()) -> SensorNoiseConfig:
        """Preset ``preset`` with ``field=value`` overrides, as a command line gives them
        (``--sensor-noise PRESET``, ``--sensor-set FIELD=VALUE`` repeated; every caller is one). A
        refusal is a one-line ``ConfigError`` naming the option and what was given
        (``--sensor-noise: unknown preset 'loud'; presets: none, realistic, ...``,
        ``--sensor-set 'dropout=2': dropout must be in [0, 1], got 2.0``); ``from_preset`` and the
        constructor, for values in hand, name the field (``sensor_noise.dropout ...``)."""
        if not isinstance(preset, str) or preset not in SENSOR_NOISE_PRESETS:
            raise ConfigError(f"--sensor-noise: unknown preset {shown(preset)}; presets: "
                              f"{', '.join(SENSOR_NOISE_PRESETS)}")
        known = SENSOR_NOISE_FIELDS + ("heading", "randomise")
        overrides: dict[str, Any] = {}
        given: list[tuple[str, str, Any]] = []  # (item, field, value)
        for item in items:
            name, sep, raw = item.partition("=")
            name, raw = name.strip(), raw.strip()
            if not sep or not name or not raw:
                raise ConfigError(f"--sensor-set takes FIELD=VALUE (e.g. dropout=0.05), got {shown(item)}")
            if name not in known:
                raise ConfigError(f"--sensor-set: unknown field {shown(name)}; fields: {', '.join(known)}")
            if name == "heading":
                value: Any = raw  # checked by the config: 'wheels' or 'imu'
            elif name == "randomise":
                if raw.lower() not in ("true", "false", "yes", "no", "1", "0", "on", "off"):
                    raise ConfigError(f"--sensor-set {shown(item)}: randomise must be true or false, "
                                      f"got {shown(raw)}")
                value = raw.lower() in ("true", "yes", "1", "on")
            else:
                try:
                    value = decimal_int(raw) if name == "latency_steps" else decimal_float(raw)
                except ValueError:
                    kind = "a whole number" if name == "latency_steps" else "a number"
                    raise ConfigError(f"--sensor-set {shown(item)}: {name} must be {kind}, "
                                      f"got {shown(raw)}") from None
            overrides[name] = value
            given.append((item, name, value))
        for item, name, value in given:  # each alone on the preset, so the refusal names its item
            try:
                SensorNoiseConfig.from_preset(preset, **{name: value})
            except ConfigError as exc:
                raise ConfigError(f"--sensor-set {shown(item)}: {_field_words(exc)}") from None
        try:
            return SensorNoiseConfig.from_preset(preset, **overrides)
        except ConfigError as exc:  # the items together (dropout + spurious above 1)
            raise ConfigError(f"--sensor-set {' '.join(shown(i) for i in items)}: {_field_words(exc)}") from None

    def describe(self) -> str:
        """One line: the preset and the magnitudes that differ from it."""
        base = SENSOR_NOISE_PRESETS[self.preset]
        changed = [f"{name}={getattr(self, name):g}" for name in SENSOR_NOISE_FIELDS if getattr(self, name) != base[name]]
        if self.heading != SENSOR_NOISE_HEADINGS[self.preset]:
            changed.insert(0, f"heading={self.heading}")
        return " ".join([self.preset, *changed, *(["randomised per episode"] if self.randomise else [])])

    @property
    def senses(self) -> str:
        """What a result line says of these senses: ``exact``, or ``describe()``."""
        return "exact" if self.is_exact else self.describe()

    @property
    def is_exact(self) -> bool:
        """No noise, no lag, no limits: the simulator's exact senses (``none``, however reached)."""
        return all(getattr(self, name) == 0 for name in SENSOR_NOISE_FIELDS if name != "label_run")

    def scaled(self, scale: float) -> SensorNoiseConfig:
        """These magnitudes times ``scale`` in [0, 1]: noise and drift multiplied, latency rounded,
        acceleration limits divided (0 stays "no limit"; ``scale`` 0 removes them), ``label_run``
        kept. ``randomise`` is off in the result."""
        if not 0 <= scale <= 1:
            raise ConfigError(f"a sensor-noise scale must be in [0, 1], got {scale!r}")
        values: dict[str, Any] = {}
        for name in SENSOR_NOISE_FIELDS:
            value = getattr(self, name)
            if name == "label_run":
                values[name] = value
            elif name == "latency_steps":
                values[name] = int(round(value * scale))
            elif name in ("max_linear_accel", "max_angular_accel"):
                values[name] = value / scale if value > 0 and scale > 0 else 0.0
            else:
                values[name] = value * scale
        values["max_linear_accel"] = min(values["max_linear_accel"], 1e3)
        values["max_angular_accel"] = min(values["max_angular_accel"], 1e3)
        return SensorNoiseConfig(preset=self.preset, randomise=False, heading=self.heading, **values)

    def config_dict(self, for_hash: bool = False) -> dict[str, Any]:
        """The config-file form: ``preset``, ``randomise``, ``heading`` and each magnitude, ``None``
        where it is the preset's (so that a later change of preset carries the magnitudes with it).
        ``for_hash``: the heading and the gyro's magnitudes count only with ``heading: imu``, by
        value: a config driving by the wheels' heading, as every config did before the IMU existed,
        keeps its hash, and one whose preset now means the IMU gets a new one (the physics differ,
        so services of one run started before and after cannot agree)."""
        base = SENSOR_NOISE_PRESETS[self.preset]
        out: dict[str, Any] = {"preset": self.preset, "randomise": self.randomise}
        imu = self.heading == "imu"
        if for_hash and imu:
            out["heading"] = self.heading
        elif not for_hash:
            out["heading"] = None if self.heading == SENSOR_NOISE_HEADINGS[self.preset] else self.heading
        for name in SENSOR_NOISE_FIELDS:
            if name in _ADDED_WITH_IMU and for_hash:
                if imu:
                    out[name] = getattr(self, name)
                continue
            if name in PERSISTENT_FIELDS and for_hash:
                if getattr(self, name):
                    out[name] = getattr(self, name)
                continue
            out[name] = None if getattr(self, name) == base[name] else getattr(self, name)
        return out


@dataclass(frozen=True)
class EnvConfig:
    """The NAMO environment.

    Observation layout (float32, length ``4*241 + 4*241 + 10*3 = 1958`` by default):
    ``[range frames (oldest..newest), label frames (oldest..newest), goal frames (oldest..newest)]``.
    """

    robot: RobotConfig = field(default_factory=RobotConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    control_period: float = 0.2  # s per environment step (5 Hz, as the authors trained)
    physics_substeps: int = 10  # physics steps per environment step (0.02 s each: no tunnelling of the 5 cm door by the arm)
    solver_iterations: int = 10  # Bullet constraint-solver iterations per physics step
    lidar_beams: int = 241
    lidar_fov: float = math.radians(240.0)  # rad, centred on the heading (-120..120 deg)
    lidar_max_range: float = 10.0  # m; a beam that hits nothing reads this
    lidar_height: float = 0.3  # m, the scan plane; every body of the world crosses it
    range_frames: int = 4
    label_frames: int = 4
    goal_frames: int = 10
    goal_tolerance: float = 0.8  # m, success radius
    max_episode_steps: int = 300  # truncation (60 s at 5 Hz, the authors' evaluation timeout)
    end_on_base_collision: bool = True  # training default; evaluation counts and goes on
    gui: bool = False  # open the PyBullet GUI (needs a display)
    #: range noise, dropouts, spurious returns, label errors, latency, odometry drift, acceleration
    #: limits, lag and wheel slip (``SensorNoiseConfig``; default: none, the exact simulator). Left
    #: out of the config hash while it is the default, so runs from before it keep their hash.
    sensor_noise: SensorNoiseConfig = field(default_factory=SensorNoiseConfig, metadata={"hash": "omit-default"})

    def __post_init__(self) -> None:
        self.validate()

    @property
    def observation_size(self) -> int:
        return (self.range_frames + self.label_frames) * self.lidar_beams + 3 * self.goal_frames

    @property
    def physics_timestep(self) -> float:
        return self.control_period / self.physics_substeps

    def validate(self) -> None:
        if not isinstance(self.robot, RobotConfig) or not isinstance(self.reward, RewardConfig):
            raise ConfigError("robot and reward must be RobotConfig and RewardConfig instances")
        if not isinstance(self.sensor_noise, SensorNoiseConfig):
            raise ConfigError("sensor_noise must be a SensorNoiseConfig instance")
        self.robot.validate()
        self.reward.validate()
        _positive(self, ["control_period", "physics_substeps", "solver_iterations", "lidar_beams",
                         "lidar_fov", "lidar_max_range", "lidar_height", "range_frames",
                         "label_frames", "goal_frames", "goal_tolerance", "max_episode_steps"])
        if self.lidar_fov > 2 * math.pi:
            raise ConfigError("lidar_fov must be at most 2 pi")
        if self.lidar_fov < LIDAR_FOV_MIN:
            raise ConfigError(f"lidar_fov must be at least 1 degree ({LIDAR_FOV_MIN:.4f} rad), got {self.lidar_fov!r}")
        _at_most(self, {"lidar_max_range": LIDAR_MAX_RANGE_LIMIT, "lidar_height": LIDAR_HEIGHT_LIMIT})

    def replace(self, **changes: Any) -> EnvConfig:
        return dataclasses.replace(self, **changes)


def _at_most(obj: Any, limits: dict[str, float]) -> None:
    """Refuse (``ConfigError``, one line) a field above its limit (the fields are numbers already)."""
    for name, limit in limits.items():
        value = getattr(obj, name)
        if value > limit:
            raise ConfigError(f"{type(obj).__name__}.{name} must be at most {limit:g}, got {value:.6g}")


def _positive(obj: Any, names: list[str]) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{type(obj).__name__}.{name} must be a positive number, got {value!r}")
