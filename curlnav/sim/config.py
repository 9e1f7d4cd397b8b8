"""Typed, validated configuration of the robot and the NAMO environment.

Every value the paper leaves open is a field here, with the choice we made and why.
Units: metres, seconds, radians, kilograms, newtons.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any


class ConfigError(ValueError):
    """A configuration value is out of range or of the wrong type."""


@dataclass(frozen=True)
class RobotConfig:
    """A differential-drive base with a one-DOF pushing arm (the end effector).

    Presets: ``husky()`` (the paper's robot, the default) and ``jackal()`` (the BARN benchmark's).
    """

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

    @staticmethod
    def husky() -> RobotConfig:
        return RobotConfig()

    @staticmethod
    def jackal() -> RobotConfig:
        return RobotConfig(base_length=0.51, base_width=0.43, base_height=0.25, base_mass=17.0,
                           max_linear_speed=0.5, max_angular_speed=1.57, arm_reach=0.3,
                           arm_length=0.3, drive_force=1000.0)

    @property
    def radius(self) -> float:
        """Circumscribed radius of the base footprint (m)."""
        return 0.5 * math.hypot(self.base_length, self.base_width)

    def validate(self) -> None:
        _positive(self, [f.name for f in dataclasses.fields(self)])


@dataclass(frozen=True)
class RewardConfig:
    """Equation (1) of the paper. ``R = r_hg + r_rg + r_mv + r_bc + r_ec``.

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

    def validate(self) -> None:
        if self.heading_rule not in ("progress", "bearing"):
            raise ConfigError(f"reward.heading_rule must be 'progress' or 'bearing', got {self.heading_rule!r}")
        _positive(self, ["moving_threshold", "heading_cone"])


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
        self.robot.validate()
        self.reward.validate()
        _positive(self, ["control_period", "physics_substeps", "solver_iterations", "lidar_beams",
                         "lidar_fov", "lidar_max_range", "lidar_height", "range_frames",
                         "label_frames", "goal_frames", "goal_tolerance", "max_episode_steps"])
        if self.lidar_fov > 2 * math.pi:
            raise ConfigError("lidar_fov must be at most 2 pi")

    def replace(self, **changes: Any) -> EnvConfig:
        return dataclasses.replace(self, **changes)


def _positive(obj: Any, names: list[str]) -> None:
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{type(obj).__name__}.{name} must be a positive number, got {value!r}")
