"""``slam-office``: a large office floor as a SLAM stack would map it, at 0.05 m per cell.

Real maps from ROS SLAM (gmapping, Cartographer, slam_toolbox) are fine-grained and ragged:
thin walls with bumps where the laser grazed them, furniture, and isolated specks of noise.
Such a map merges into thousands of rectangles, where a clean generated world has a few
hundred. This family is the stress case for the static geometry and the LiDAR (about
92 m x 72 m, several thousand rectangles), and a stand-in for a user's own map.

Layout: the floor is split recursively (binary space partition) into rooms of 4-12 m; every
dividing wall gets a doorway of 1.1-1.6 m, so every room is reachable (the partition is a tree);
then desks, round tables and columns, bumps along the walls, and specks of noise.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from curlnav.worlds.world import RandomPairs, World

SLAM_RESOLUTION = 0.05  # m per cell, a common SLAM map resolution


def slam_office(seed: int = 0, width: float = 92.0, height: float = 72.0, resolution: float = SLAM_RESOLUTION,
                min_room: float = 4.0, max_room: float = 12.0, wall: float = 0.15, furniture_per_room: float = 3.0,
                bump_probability: float = 0.25, speck_density: float = 0.0004) -> World:
    """A seeded office floor (see the module docstring); lengths in m, densities per cell."""
    if width <= 2 * max_room or height <= 2 * max_room:
        raise ValueError(f"slam-office needs width and height above 2 x max_room ({2 * max_room} m)")
    if not 0 < min_room < max_room:
        raise ValueError("slam-office needs 0 < min_room < max_room")
    rng = np.random.default_rng(seed)

    def cells(metres: float) -> int:
        return int(round(metres / resolution))

    rows, cols = cells(height), cells(width)
    grid = np.zeros((rows, cols), dtype=bool)
    t = max(cells(wall), 1)
    grid[:t, :] = grid[-t:, :] = grid[:, :t] = grid[:, -t:] = True
    keep_free = np.zeros_like(grid)  # doorways: no furniture or bumps in front of them
    rooms: list[tuple[int, int, int, int]] = []

    def split(r0: int, c0: int, r1: int, c1: int) -> None:
        h, w = r1 - r0, c1 - c0
        can_rows, can_cols = h > 2 * cells(min_room), w > 2 * cells(min_room)
        if (h <= cells(max_room) and w <= cells(max_room)) or not (can_rows or can_cols):
            rooms.append((r0, c0, r1, c1))
            return
        along_rows = can_rows and (not can_cols or h >= w)
        if along_rows:
            cut = int(rng.integers(r0 + cells(min_room), r1 - cells(min_room)))
            grid[cut:cut + t, c0:c1] = True
            door = cells(rng.uniform(1.1, 1.6))
            at = int(rng.integers(c0 + t + 1, max(c1 - door - 1, c0 + t + 2)))
            grid[cut:cut + t, at:at + door] = False
            keep_free[max(cut - cells(1.0), 0):cut + t + cells(1.0), at:at + door] = True
            split(r0, c0, cut, c1)
            split(cut + t, c0, r1, c1)
        else:
            cut = int(rng.integers(c0 + cells(min_room), c1 - cells(min_room)))
            grid[r0:r1, cut:cut + t] = True
            door = cells(rng.uniform(1.1, 1.6))
            at = int(rng.integers(r0 + t + 1, max(r1 - door - 1, r0 + t + 2)))
            grid[at:at + door, cut:cut + t] = False
            keep_free[at:at + door, max(cut - cells(1.0), 0):cut + t + cells(1.0)] = True
            split(r0, c0, r1, cut)
            split(r0, cut + t, r1, c1)

    split(t, t, rows - t, cols - t)
    furniture = np.zeros_like(grid)
    for r0, c0, r1, c1 in rooms:
        for _ in range(int(rng.poisson(furniture_per_room))):
            kind = rng.random()
            if kind < 0.6:  # a desk or shelf along no particular wall
                fh, fw = (cells(rng.uniform(0.5, 0.8)), cells(rng.uniform(1.0, 1.8)))
                if rng.random() < 0.5:
                    fh, fw = fw, fh
                if r1 - r0 <= fh + 2 * t or c1 - c0 <= fw + 2 * t:
                    continue
                fr = int(rng.integers(r0 + t, r1 - fh - t))
                fc = int(rng.integers(c0 + t, c1 - fw - t))
                furniture[fr:fr + fh, fc:fc + fw] = True
            else:  # a round table or a column
                radius = rng.uniform(0.2, 0.6)
                cy = rng.uniform(r0 + cells(1.0), r1 - cells(1.0))
                cx = rng.uniform(c0 + cells(1.0), c1 - cells(1.0))
                rr = cells(radius)
                y0, y1 = int(max(cy - rr - 1, 0)), int(min(cy + rr + 2, rows))
                x0, x1 = int(max(cx - rr - 1, 0)), int(min(cx + rr + 2, cols))
                yy, xx = np.ogrid[y0:y1, x0:x1]
                furniture[y0:y1, x0:x1] |= (yy + 0.5 - cy) ** 2 + (xx + 0.5 - cx) ** 2 <= rr * rr
    grid |= furniture & ~keep_free
    # bumps where the laser grazed a surface: free cells touching an obstacle, at random
    rim = ndimage.binary_dilation(grid) & ~grid & ~keep_free
    grid |= rim & (rng.random(grid.shape) < bump_probability)
    # isolated specks of noise
    grid |= (rng.random(grid.shape) < speck_density) & ~keep_free
    return World(name=f"slam-office-{seed}", occupancy=grid, resolution=resolution,
                 random_pairs=RandomPairs(min_distance=10.0, clearance=0.6),
                 source=f"generated:slam-office seed={seed}")
