"""Top-down pictures of a world, the robot, its LiDAR and its trajectory (matplotlib, headless)."""

from __future__ import annotations

import math
import os
from typing import Any, Protocol

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from curlnav.worlds.core.picture import draw_world, rotated_rect  # noqa: E402
from curlnav.worlds.core.world import StartGoal, World  # noqa: E402


class DrawableEnv(Protocol):
    """What a picture of a running environment reads (``NamoEnv`` has it all). A protocol, so this
    module does not import the environment that imports it for ``render()``."""

    scene: Any  # robot_pose(), ball_positions(), door_angles(), box_poses()
    world: World
    config: Any  # .robot (footprint), .goal_tolerance (m)
    last_hits: Any  # (241, 2) LiDAR hit points in the map frame (m), or None before the first scan
    last_labels: Any  # (241,) movable labels of those beams
    trajectory: list  # [(x, y)] robot positions so far (m)
    pair: StartGoal | None


def draw_env(ax, env: DrawableEnv, title: str | None = None) -> None:
    """Draw the environment's current state: world, robot, LiDAR hits, trajectory, goal."""
    scene = env.scene
    draw_world(ax, env.world, ball_positions=scene.ball_positions(), door_angles=scene.door_angles(),
               box_poses=scene.box_poses())
    x, y, yaw, arm = scene.robot_pose()
    robot = env.config.robot
    if env.last_hits is not None:
        hits, labels = env.last_hits, env.last_labels
        ax.scatter(hits[labels == 0, 0], hits[labels == 0, 1], s=2, color="tab:purple", label="LiDAR hit (static)")
        ax.scatter(hits[labels == 1, 0], hits[labels == 1, 1], s=4, color="tab:cyan", label="LiDAR hit (movable)")
    if env.trajectory:
        traj = np.asarray(env.trajectory)
        ax.plot(traj[:, 0], traj[:, 1], "-", color="tab:green", lw=1.5, label="trajectory")
    ax.add_patch(rotated_rect(x, y, robot.base_length, robot.base_width, yaw, color="tab:olive", alpha=0.9))
    tip = robot.base_length / 2 + arm
    ax.plot([x, x + tip * math.cos(yaw)], [y, y + tip * math.sin(yaw)], color="black", lw=2)
    if env.pair is not None:
        ax.plot([env.pair.x], [env.pair.y], "o", color="tab:green", ms=6, label="start")
        ax.add_patch(Circle((env.pair.gx, env.pair.gy), env.config.goal_tolerance, fill=False, color="tab:red"))
        ax.plot([env.pair.gx], [env.pair.gy], "*", color="tab:red", ms=12, label="goal")
    ax.legend(loc="upper right", fontsize=6, framealpha=0.7)
    if title:
        ax.set_title(title, fontsize=9)


def save_env_picture(env: DrawableEnv, path: str | os.PathLike, title: str | None = None) -> str:
    """Write a PNG of the environment's current state; returns the path."""
    x0, y0, x1, y1 = env.world.bounds
    fig, ax = plt.subplots(figsize=(7, 7 * (y1 - y0) / max(x1 - x0, 1e-9) + 0.5), dpi=110)
    draw_env(ax, env, title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return os.fspath(path)


def render_topdown_array(env: DrawableEnv) -> np.ndarray:
    """The environment's current state as an RGB array (H, W, 3), uint8."""
    fig, ax = plt.subplots(figsize=(5, 5), dpi=80)
    draw_env(ax, env)
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb
