"""The PyBullet NAMO simulator: worlds, scene, environment, pictures."""

from .builtin import BUILTIN_WORLDS, get_world
from .config import ConfigError, EnvConfig, RewardConfig, RobotConfig
from .env import NamoEnv
from .world import Ball, Box, Door, RandomPairs, Region, StartGoal, World, WorldError, load_world, save_world

__all__ = ["Ball", "Box", "BUILTIN_WORLDS", "ConfigError", "Door", "EnvConfig", "NamoEnv", "RandomPairs",
           "Region", "RewardConfig", "RobotConfig", "StartGoal", "World", "WorldError", "get_world",
           "load_world", "save_world"]
