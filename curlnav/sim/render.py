"""Top-down pictures of a world, the robot, its LiDAR and its trajectory (matplotlib, headless)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any, Protocol

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Polygon  # noqa: E402
from matplotlib.transforms import Affine2D  # noqa: E402

from curlnav.worlds.world import StartGoal, World  # noqa: E402


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


def draw_world(ax, world: World, pairs: Sequence[StartGoal] | None = None,
               ball_positions: Sequence[tuple[float, float]] | None = None,
               door_angles: Sequence[float] | None = None,
               box_poses: Sequence[tuple[float, float, float]] | None = None) -> None:
    """Draw the static map, movable objects (at given or file positions) and start/goal pairs,
    all in the map frame; a rotated grid (``world.origin_yaw``) is drawn rotated."""
    x0, y0, x1, y1 = world.bounds
    width, height = world.size
    image = ax.imshow(world.occupancy, origin="lower", extent=(0.0, width, 0.0, height), cmap="Greys", vmin=0,
                      vmax=1.4, interpolation="nearest")
    # grid frame -> map frame: rotate by origin_yaw about cell (0, 0)'s corner, then move it to origin
    image.set_transform(Affine2D().rotate(world.origin_yaw).translate(*world.origin) + ax.transData)
    positions = ball_positions if ball_positions is not None else [(b.x, b.y) for b in world.balls]
    for ball, (bx, by) in zip(world.balls, positions):
        ax.add_patch(Circle((bx, by), ball.radius, color="tab:blue", alpha=0.8))
    poses = box_poses if box_poses is not None else [(b.x, b.y, b.yaw) for b in world.boxes]
    for box, (bx, by, yaw) in zip(world.boxes, poses):
        ax.add_patch(_rotated_rect(bx, by, box.size_x, box.size_y, yaw, color="tab:cyan", alpha=0.8))
    angles = door_angles if door_angles is not None else [0.0] * len(world.doors)
    for door, opening in zip(world.doors, angles):
        a = door.closed_angle + opening
        ax.plot([door.hinge_x, door.hinge_x + door.width * math.cos(a)],
                [door.hinge_y, door.hinge_y + door.width * math.sin(a)], color="tab:orange", lw=3)
        ax.plot([door.hinge_x], [door.hinge_y], "o", color="tab:orange", ms=4)
    for pair in pairs or ():
        ax.plot([pair.x], [pair.y], "o", color="tab:green", ms=6)
        ax.plot([pair.gx], [pair.gy], "*", color="tab:red", ms=12)
        ax.annotate(pair.name, (pair.gx, pair.gy), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def _rotated_rect(cx: float, cy: float, length: float, width: float, yaw: float, **kw) -> Polygon:
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(dx, dy) for dx, dy in ((length / 2, width / 2), (-length / 2, width / 2),
                                       (-length / 2, -width / 2), (length / 2, -width / 2))]
    return Polygon([(cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in corners], closed=True, **kw)


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
    ax.add_patch(_rotated_rect(x, y, robot.base_length, robot.base_width, yaw, color="tab:olive", alpha=0.9))
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
