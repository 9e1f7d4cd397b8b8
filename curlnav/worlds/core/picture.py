"""A top-down picture of a world: its static map, movable objects and start/goal pairs, in the map
frame (matplotlib). The simulator's pictures of a running environment (``curlnav.sim.render``)
draw on it, and so do ``curlnav worlds show`` and the evaluation's figures."""

from __future__ import annotations

import math
from collections.abc import Sequence

from matplotlib.patches import Circle, Polygon
from matplotlib.transforms import Affine2D

from curlnav.worlds.core.world import StartGoal, World


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
        ax.add_patch(rotated_rect(bx, by, box.size_x, box.size_y, yaw, color="tab:cyan", alpha=0.8))
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


def rotated_rect(cx: float, cy: float, length: float, width: float, yaw: float, **kw) -> Polygon:
    c, s = math.cos(yaw), math.sin(yaw)
    corners = [(dx, dy) for dx, dy in ((length / 2, width / 2), (-length / 2, width / 2),
                                       (-length / 2, -width / 2), (length / 2, -width / 2))]
    return Polygon([(cx + c * dx - s * dy, cy + s * dx + c * dy) for dx, dy in corners], closed=True, **kw)
