"""The PyBullet NAMO simulator: worlds, scene, environment, pictures.

``NamoEnv`` (and with it PyBullet) is imported on first use: a learner or a replay host reads the
configs and worlds of this package and needs no simulator installed."""

from curlnav.worlds.builtin import BUILTIN_WORLDS, get_world
from curlnav.worlds.core.world import Ball, Box, Door, RandomPairs, Region, StartGoal, World, WorldError, load_world, save_world

from .config import ConfigError, EnvConfig, RewardConfig, RobotConfig, SensorNoiseConfig

__all__ = ["Ball", "Box", "BUILTIN_WORLDS", "ConfigError", "Door", "EnvConfig", "NamoEnv", "RandomPairs",
           "Region", "RewardConfig", "RobotConfig", "SensorNoiseConfig", "StartGoal", "World", "WorldError", "get_world",
           "load_world", "save_world"]


def __getattr__(name: str):
    if name == "NamoEnv":
        from .env import NamoEnv

        return NamoEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
