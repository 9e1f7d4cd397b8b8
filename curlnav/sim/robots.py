"""Robot profiles: a base, its arm (or none) and its LiDAR, selected by name or file.

``robot: husky | jackal | FILE.yaml`` in an experiment config (``curlnav train --robot``,
``curlnav eval --robot``, ``curlnav ros2 run --robot``) sets ``EnvConfig.robot`` and the LiDAR
fields of ``EnvConfig`` from one profile (``RobotProfile.apply``); later ``env.*`` settings still
win. A policy artefact records its robot (``robot.name`` and footprint in ``metadata.json``) and
``check_robot`` refuses, in one line, to drive another.

Built-in profiles (manufacturers' published figures; ``docs/guide/robots.md``):

- ``husky``: Clearpath Husky class, 0.99 x 0.67 x 0.31 m, 50 kg, 1.0 m/s, 1.0 rad/s, a 0.5 m
  pushing arm; a 241-beam, 240-degree LiDAR to 10 m (the paper's 3-D LiDAR cut to 2-D).
- ``jackal``: Clearpath Jackal, 0.508 x 0.430 x 0.250 m, 17 kg, 2.0 m/s, 1.57 rad/s (the BARN
  Challenge's move_base limit), no arm; the challenge's Hokuyo UST-10LX (270 degrees in 0.25
  degree steps, 10 m) read at every 4th beam: 271 beams, 1 degree apart, the same angles as
  beams 0, 4, ..., 1080 of the full scan (``curlnav ros2 run`` resamples a 1081-beam scan to them).

A profile file (YAML) gives ``name``, any ``RobotConfig`` field (``base_length``, ``base_width``,
``base_height``, ``base_mass``, ``max_linear_speed``, ``max_angular_speed``, ``drive_force``,
``arm`` true/false, ``arm_reach`` ...; m, kg, m/s, rad/s, N) and ``lidar: {beams, fov_deg, range_m,
height_m}``; fields left out keep the Husky's, but for ``max_reverse_speed``: 0 (forward only) unless
the file gives it. See ``docs/guide/robots.md`` for an example.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .config import ConfigError, EnvConfig, RobotConfig

#: an artefact's recorded footprint within this of the robot's drives it (m)
FOOTPRINT_TOLERANCE = 0.02
LIDAR_KEYS = ("beams", "fov_deg", "range_m", "height_m")


@dataclass(frozen=True)
class RobotProfile:
    """A robot and its LiDAR: beams (count), field of view (rad, centred on the heading), range
    and scan-plane height (m)."""

    robot: RobotConfig
    lidar_beams: int
    lidar_fov: float
    lidar_max_range: float
    lidar_height: float

    @property
    def name(self) -> str:
        return self.robot.name

    def apply(self, env: EnvConfig) -> EnvConfig:
        """``env`` with this robot and LiDAR (everything else unchanged)."""
        return env.replace(robot=self.robot, lidar_beams=self.lidar_beams, lidar_fov=self.lidar_fov,
                           lidar_max_range=self.lidar_max_range, lidar_height=self.lidar_height)

    def describe(self) -> str:
        r = self.robot
        arm = f"a {r.arm_reach:g} m arm" if r.arm else "no arm"
        return (f"{r.name}: {r.base_length:g} x {r.base_width:g} m, {r.base_mass:g} kg, {r.max_linear_speed:g} m/s, "
                f"{r.max_angular_speed:g} rad/s, {arm}; LiDAR {self.lidar_beams} beams over "
                f"{math.degrees(self.lidar_fov):g} deg to {self.lidar_max_range:g} m")


PROFILES: dict[str, RobotProfile] = {
    "husky": RobotProfile(RobotConfig.husky(), 241, math.radians(240.0), 10.0, 0.3),
    "jackal": RobotProfile(RobotConfig.jackal(), 271, math.radians(270.0), 10.0, 0.3),
}


def profile_of_env(env: EnvConfig) -> RobotProfile:
    """The profile an environment config holds."""
    return RobotProfile(env.robot, env.lidar_beams, env.lidar_fov, env.lidar_max_range, env.lidar_height)


def load_profile(spec: str) -> RobotProfile:
    """A built-in profile by name, or a profile file; ``ConfigError`` (one line) otherwise."""
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"robot must be {', '.join(PROFILES)} or a profile file (.yaml), got {spec!r}")
    if spec in PROFILES:
        return PROFILES[spec]
    path = Path(spec)
    if path.suffix not in (".yaml", ".yml", ".json"):
        raise ConfigError(f"unknown robot {spec!r}: choose {', '.join(PROFILES)} or give a profile file (.yaml)")
    from curlnav.files import FileRefused, read_yaml

    try:
        data = read_yaml(path, what="robot profile")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the robot profile: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise ConfigError(str(exc)) from None
    try:
        return profile_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def profile_keys() -> list[str]:
    """Every key a profile file may give: ``name``, the ``RobotConfig`` fields and ``lidar`` (with its own keys)."""
    robot = sorted(f.name for f in dataclasses.fields(RobotConfig) if f.name != "name")
    return ["name", *robot, f"lidar ({', '.join(LIDAR_KEYS)})"]


def _robot_from_dict(data: dict) -> RobotConfig:
    """``RobotConfig`` from a profile file's fields; ``ConfigError`` naming an unknown or mistyped one."""
    fields = {f.name: f for f in dataclasses.fields(RobotConfig)}
    values: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            raise ConfigError(f"unknown key {str(key)[:40]} in a robot profile; its keys: {', '.join(profile_keys())}")
        if key == "name":
            values[key] = value
        elif key == "arm":
            if not isinstance(value, bool):
                raise ConfigError(f"robot.arm must be true or false, got {value!r}")
            values[key] = value
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            kind = "a number of at least 0" if key == "max_reverse_speed" else "a positive number"
            raise ConfigError(f"RobotConfig.{key} must be {kind}, got {value!r}")
        else:
            values[key] = float(value)
    values.setdefault("max_reverse_speed", 0.0)  # a robot of one's own backs up only when its file says it can
    return RobotConfig(**values)


def profile_from_dict(data: Any) -> RobotProfile:
    """A profile from a file's mapping (see the module docstring); ``ConfigError`` naming the field."""
    if not isinstance(data, dict):
        raise ConfigError("a robot profile is a mapping of name, robot fields and lidar")
    data = dict(data)
    if "name" not in data:
        raise ConfigError("a robot profile needs a name")
    if not isinstance(data["name"], str):
        raise ConfigError(f"robot.name must be a text of 1-40 of a-z, 0-9, - and _, got {str(data['name'])[:40]!r}")
    if data["name"] in PROFILES:
        raise ConfigError(f"name {data['name']!r} is a built-in profile's; give your robot its own name")
    lidar = data.pop("lidar", None) or {}
    if not isinstance(lidar, dict):
        raise ConfigError("lidar must be a mapping of " + ", ".join(LIDAR_KEYS))
    unknown = sorted(set(map(str, lidar)) - set(LIDAR_KEYS))
    if unknown:
        raise ConfigError(f"unknown lidar key {unknown[0]}; known: {', '.join(LIDAR_KEYS)}")
    robot = _robot_from_dict(data)
    husky = PROFILES["husky"]
    values = {"beams": lidar.get("beams", husky.lidar_beams),
              "fov_deg": lidar.get("fov_deg", math.degrees(husky.lidar_fov)),
              "range_m": lidar.get("range_m", husky.lidar_max_range),
              "height_m": lidar.get("height_m", husky.lidar_height)}
    for key, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"lidar.{key} must be a positive number, got {value!r}")
    if not isinstance(values["beams"], int) or values["beams"] > 16384:
        raise ConfigError(f"lidar.beams must be a whole number 1-16384, got {values['beams']!r}")
    if values["fov_deg"] > 360:
        raise ConfigError(f"lidar.fov_deg must be at most 360, got {values['fov_deg']!r}")
    profile = RobotProfile(robot, values["beams"], math.radians(values["fov_deg"]), float(values["range_m"]),
                           float(values["height_m"]))
    profile.apply(EnvConfig())  # validates the whole environment with it
    return profile


def recorded_robot(meta: dict) -> tuple[str, float, float]:
    """``(name, base_length, base_width)`` an artefact's metadata records; an artefact from before
    profiles has no name: the built-in profile of its footprint (within ``FOOTPRINT_TOLERANCE``)."""
    robot = meta.get("robot")
    if not isinstance(robot, dict):
        raise ValueError("its metadata records no robot")
    try:
        length, width = float(robot["base_length"]), float(robot["base_width"])
    except (KeyError, TypeError, ValueError):
        raise ValueError("its metadata records no robot footprint") from None
    name = robot.get("name")
    if name is None:  # from before profiles: the built-in robot of that footprint, if any
        name = next((p.name for p in PROFILES.values() if abs(p.robot.base_length - length) <= FOOTPRINT_TOLERANCE
                     and abs(p.robot.base_width - width) <= FOOTPRINT_TOLERANCE), "unnamed robot")
    return str(name), length, width


def check_robot(meta: dict, robot: RobotConfig, what: str) -> None:
    """Refuse (``ValueError``, one line) an artefact's metadata ``meta`` that records another robot
    than ``robot``: another name, a footprint more than ``FOOTPRINT_TOLERANCE`` off, an arm it has
    not (or lacks), or a top speed above the robot's. A policy trained at a *lower* top speed drives
    it at that speed (``command_scale``, ``SpeedLimitedPolicy``): a Jackal policy trained to command
    at most 1 m/s drives the 2 m/s Jackal at up to 1 m/s."""
    try:
        name, length, width = recorded_robot(meta)
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}; it cannot drive the {robot.name}") from None
    same_size = (abs(length - robot.base_length) <= FOOTPRINT_TOLERANCE
                 and abs(width - robot.base_width) <= FOOTPRINT_TOLERANCE)
    if name != robot.name or not same_size:
        raise ValueError(f"{what}: trained for the {name} ({length:g} x {width:g} m), not the {robot.name} "
                         f"({robot.base_length:g} x {robot.base_width:g} m); refused")
    recorded = meta["robot"]
    for key, unit in (("max_linear_speed", "m/s"), ("max_angular_speed", "rad/s")):
        value = recorded.get(key)
        if isinstance(value, (int, float)) and value > getattr(robot, key) + 1e-6:
            raise ValueError(f"{what}: trained for a top {key.split('_')[1]} speed of {value:g} {unit}, the "
                             f"{robot.name} here has only {getattr(robot, key):g} {unit}; refused")
    if isinstance(recorded.get("arm"), bool) and recorded["arm"] != robot.arm:
        has = "with" if recorded["arm"] else "without"
        raise ValueError(f"{what}: trained {has} an arm, the {robot.name} here {'has one' if robot.arm else 'has none'}; "
                         f"refused")


def command_scale(meta: dict, robot: RobotConfig) -> tuple[float, float]:
    """``(linear, angular)``: what the policy of metadata ``meta`` commands at action 1, as a
    fraction of ``robot``'s top speeds (1.0 where ``meta`` records no speed). ``check_robot`` first:
    a fraction above 1 is refused there."""
    recorded = meta.get("robot") if isinstance(meta.get("robot"), dict) else {}
    out = []
    for key in ("max_linear_speed", "max_angular_speed"):
        value = recorded.get(key)
        valid = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
        out.append(min(1.0, value / getattr(robot, key)) if valid else 1.0)
    return out[0], out[1]


class SpeedLimitedPolicy:
    """A policy trained at lower top speeds than the robot it drives (``command_scale``): its
    action's linear and angular parts are scaled down so that it commands, in m/s and rad/s, what
    it learned to (``action[2]``, the arm, is left alone). ``metadata`` is the wrapped policy's."""

    def __init__(self, policy: Any, scale: tuple[float, float]) -> None:
        if not all(0 < s <= 1 for s in scale):
            raise ValueError(f"command scales must be in (0, 1], got {scale}")
        self.policy = policy
        self.scale = np.array([scale[0], scale[1], 1.0], dtype=np.float32)
        self.metadata = getattr(policy, "metadata", None)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        action = np.asarray(self.policy(observation), dtype=np.float32)
        return action * self.scale[:action.shape[-1]]  # one action (3,) or a batch (B, 3)

    @property
    def version(self) -> Any:
        return getattr(self.policy, "version", None)

    @property
    def observation_size(self) -> Any:
        return getattr(self.policy, "observation_size", None)


def speed_limited(policy: Any, robot: RobotConfig) -> Any:
    """``policy`` wrapped in ``SpeedLimitedPolicy`` when its ``metadata`` records lower top speeds
    than ``robot``'s; itself otherwise."""
    meta = getattr(policy, "metadata", None)
    scale = command_scale(meta, robot) if isinstance(meta, dict) else (1.0, 1.0)
    return policy if scale == (1.0, 1.0) else SpeedLimitedPolicy(policy, scale)


def sensor_metadata(env: EnvConfig) -> dict:
    """What a training checkpoint records of its robot and LiDAR (an artefact's ``robot`` and
    ``observation.lidar_fov_rad``), so that it is checked as an artefact is."""
    return {"robot": robot_metadata(env), "lidar_fov_rad": env.lidar_fov}


def check_observation(meta: dict, env: EnvConfig, what: str) -> None:
    """Refuse (``ValueError``, one line) a policy whose observation (``meta``'s
    ``observation.layout`` and ``lidar_fov_rad``) is not the one ``env``'s LiDAR gives: another beam
    count, field of view, range or frame count."""
    from curlnav.layout import ObservationLayout

    observation = meta.get("observation") if isinstance(meta.get("observation"), dict) else {}
    layout = observation.get("layout")
    if not isinstance(layout, dict):
        return  # the loader names a missing layout
    mine = ObservationLayout.from_env_config(env).to_dict()
    for key, unit in (("beams", " beams"), ("max_range", " m of range"), ("range_frames", " range frames"),
                      ("label_frames", " label frames"), ("goal_frames", " goal frames")):
        if key in layout and layout[key] != mine[key]:
            raise ValueError(f"{what}: reads {layout[key]}{unit}, the {env.robot.name}'s LiDAR here gives "
                             f"{mine[key]}{unit}; refused")
    fov = observation.get("lidar_fov_rad")
    if isinstance(fov, (int, float)) and abs(fov - env.lidar_fov) > 1e-6:
        raise ValueError(f"{what}: reads a LiDAR of {math.degrees(fov):g} deg, the {env.robot.name}'s here covers "
                         f"{math.degrees(env.lidar_fov):g} deg; refused")


def robot_metadata(env: EnvConfig) -> dict:
    """What an artefact records of its robot (``metadata.json``'s ``robot``)."""
    r = env.robot
    out = {k: getattr(r, k) for k in ("base_length", "base_width", "arm_reach", "max_linear_speed",
                                      "max_angular_speed")}
    out.update(name=r.name, arm=r.arm)
    return out


def replace_robot(env: EnvConfig, **changes: Any) -> EnvConfig:
    """``env`` with robot fields changed (a convenience for tests and studies)."""
    return env.replace(robot=dataclasses.replace(env.robot, **changes))
