"""Geometry every role of the navigation stack shares: poses and frames, the goal decoded from an
observation, constant-velocity arcs and the base's footprint along them, grid cell keys.

Units: metres, radians, seconds; a pose is ``(x, y, yaw)``; points are ``(n, 2)`` arrays; the robot
frame has +x ahead and +y to the left.
"""

from __future__ import annotations

import math

import numpy as np

#: cell keys: ``ix * CELL_KEY_STRIDE + iy`` (``cell_keys``)
CELL_KEY_STRIDE = 1 << 31  # cell keys: ix * CELL_KEY_STRIDE + iy, cells of +-2**30 * cell_m (1e8 m at 0.1 m)
#: what a cell's key plus each of these gives: the cell and its 8 neighbours
NEIGHBOUR_OFFSETS = np.array([dx * CELL_KEY_STRIDE + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)


def goal_in_robot_frame(goal_frame: np.ndarray) -> tuple[float, float]:
    """``(dx, dy)`` (m, robot frame) from one goal frame ``[sign(dx) log(1+|dx|), sign(dy)
    log(1+|dy|), bearing]`` of the observation."""
    g = np.asarray(goal_frame, dtype=np.float64)
    return float(np.sign(g[0]) * np.expm1(abs(g[0]))), float(np.sign(g[1]) * np.expm1(abs(g[1])))


def odometry(info: dict) -> tuple[float, float, float]:
    """The robot's own pose estimate ``(x, y, yaw)`` (m, rad) in ``info``: ``info["odometry"]``
    where the environment gives one (it drifts under sensor noise), else ``info["pose"]`` (the
    ROS 2 node's ``/odom``)."""
    return info.get("odometry", info["pose"])


def wrap(angle: float | np.ndarray) -> float | np.ndarray:
    """Angle (rad) wrapped to [-pi, pi)."""
    return (np.asarray(angle) + math.pi) % (2 * math.pi) - math.pi


def arc_poses(v: np.ndarray, w: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, y, th)``, each ``(N, T)``: where each command ``(v[i], w[i])`` (m/s, rad/s), driven as a
    constant arc from the origin of the robot frame heading +x, has the base at the ``times``
    ``(T,)`` (s): position (m) and heading (rad), in that frame."""
    v = np.asarray(v, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    th = w[:, None] * times[None, :]
    straight = np.abs(w) < 1e-6
    safe_w = np.where(straight, 1.0, w)[:, None]
    x = np.where(straight[:, None], v[:, None] * times[None, :], v[:, None] * np.sin(th) / safe_w)
    y = np.where(straight[:, None], 0.0, v[:, None] * (1.0 - np.cos(th)) / safe_w)
    return x, y, th


def footprint_clearance(points: np.ndarray, v: np.ndarray, w: np.ndarray, times: np.ndarray,
                        half_length: float, half_width: float, signed: bool = False) -> np.ndarray:
    """For each command ``(v[i], w[i])`` (m/s, rad/s) driven from the origin of the robot frame as a
    constant arc: the least distance (m) from the base's rectangle (``half_length`` x
    ``half_width``, m, centred on the base) to any of ``points`` ``(n, 2)`` (m, robot frame) at the
    ``times`` (s) along it; 0 where a point lies inside the rectangle (``signed``: minus its depth
    inside, the distance to the nearest side), ``inf`` without points."""
    v = np.asarray(v, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    if len(points) == 0:
        return np.full(v.shape, np.inf)
    chunk = max(1, 2_000_000 // max(1, v.size * len(times)))  # points at a time: a few tens of MB per array
    if len(points) > chunk:  # a dense map's walls: thousands of points round the base
        return np.min([footprint_clearance(points[i:i + chunk], v, w, times, half_length, half_width, signed)
                       for i in range(0, len(points), chunk)], axis=0)
    x, y, th = arc_poses(v, w, times)  # (N, T)
    c, s = np.cos(th)[..., None], np.sin(th)[..., None]
    px = points[None, None, :, 0] - x[..., None]
    py = points[None, None, :, 1] - y[..., None]
    qx, qy = c * px + s * py, -s * px + c * py  # (N, T, n) in each pose's frame
    gap = np.hypot(np.maximum(np.abs(qx) - half_length, 0.0), np.maximum(np.abs(qy) - half_width, 0.0))
    if signed:
        depth = np.minimum(half_length - np.abs(qx), half_width - np.abs(qy))  # > 0 inside
        gap = np.where(depth > 0.0, -depth, gap)
    return gap.min(axis=(1, 2))


def cell_keys(points: np.ndarray, cell_m: float) -> np.ndarray:
    """The cell of ``cell_m`` (m) a side of each ``(n, 2)`` point (m), as one int64 key
    (``ix * CELL_KEY_STRIDE + iy``; a cell's 8 neighbours are its key plus ``NEIGHBOUR_OFFSETS``)."""
    return np.floor(points[:, 0] / cell_m).astype(np.int64) * CELL_KEY_STRIDE + np.floor(points[:, 1] / cell_m).astype(np.int64)


def to_frame(points: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """``(n, 2)`` points (m) of the frame at ``pose`` (x, y, yaw: m, rad) in the frame ``pose`` is in."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([x + c * points[:, 0] - s * points[:, 1], y + s * points[:, 0] + c * points[:, 1]], axis=1)


def from_frame(points: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
    """The inverse of ``to_frame``: ``(n, 2)`` points (m) seen from ``pose``."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = points[:, 0] - x, points[:, 1] - y
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)
