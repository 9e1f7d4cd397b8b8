"""Make a NAMO task from any map: scatter movable balls on the shortest paths of its pairs.

``scatter_balls(world, count, seed)`` takes the world's pairs (or, for a plain SLAM map,
``pairs`` seeded random ones from ``curlnav.worlds.core.pairs``, which become the world's pairs), finds
each pair's shortest path on the C-space grid of ``curlnav.worlds.difficulty.rank.world_paths`` (0.15 m
cells, the map inflated by 0.3 m; Dijkstra), and puts ``count`` balls on those paths, in turn
over the pairs: each ball's centre is a path cell whose whole disc (plus ``gap``) clears every
obstacle cell of the map, the balls do not overlap (``gap`` apart), and none sits on a start
(robot footprint), a goal or in a door's swing (a ball under a panel would jam it). Same world,
count and seed: same balls.
"""

from __future__ import annotations

import math

import numpy as np

from curlnav.worlds.core.pairs import clearance_map, sample_pairs
from curlnav.worlds.core.world import Ball, World, WorldError
from curlnav.worlds.difficulty.rank import METRIC_RESOLUTION, path_points, world_paths

START_KEEP_OUT = 1.0  # m from a start to a ball's edge (the Husky's half-diagonal is 0.6 m)
GOAL_KEEP_OUT = 1.0  # m from a goal to a ball's edge (the goal tolerance is 0.8 m)


def scatter_balls(world: World, count: int, seed: int = 0, radius: float = 0.25, mass: float = 0.5,
                  pairs: int = 3, gap: float = 0.1) -> World:
    """``world`` with ``count`` more balls on the shortest paths of its pairs (see the module
    docstring). ``WorldError`` (one line) when the paths leave no room for ``count`` balls."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    if not (radius > 0 and mass > 0):
        raise ValueError(f"ball radius and mass must be positive, got {radius} and {mass}")
    chosen = world.pairs or sample_pairs(world, max(1, pairs), seed=seed)
    task = world.with_changes(pairs=chosen)
    _, paths = world_paths(task)
    wall = clearance_map(world)  # centre to wall edge
    rng = np.random.default_rng(seed)
    candidates = []
    for pair, path in zip(chosen, paths):
        xs, ys = path_points(world, path[1:], METRIC_RESOLUTION)
        keep = []
        for x, y in zip(np.asarray(xs, dtype=float), np.asarray(ys, dtype=float)):
            if not world.contains(x, y):
                continue
            iy, ix = world.cell_of(x, y)
            if wall[iy, ix] < radius + gap:
                continue
            if math.hypot(x - pair.x, y - pair.y) < START_KEEP_OUT + radius:
                continue
            if math.hypot(x - pair.gx, y - pair.gy) < GOAL_KEEP_OUT + radius:
                continue
            if any(math.hypot(x - d.hinge_x, y - d.hinge_y) < d.width + radius + gap for d in world.doors):
                continue
            keep.append((x, y))
        candidates.append(keep)
    all_pairs = [(p.x, p.y, p.gx, p.gy) for p in chosen]
    placed: list[tuple[float, float]] = [(b.x, b.y) for b in world.balls]
    radii = [b.radius for b in world.balls]
    new: list[Ball] = []
    order = [i for i in range(len(candidates)) if candidates[i]]
    turn = 0
    while len(new) < count and order:
        k = order[turn % len(order)]
        options = candidates[k]
        while options:
            x, y = options.pop(int(rng.integers(len(options))))
            if any(math.hypot(x - bx, y - by) < radius + br + gap for (bx, by), br in zip(placed, radii)):
                continue
            if any(math.hypot(x - sx, y - sy) < START_KEEP_OUT + radius for sx, sy, _, _ in all_pairs):
                continue
            if any(math.hypot(x - gx, y - gy) < GOAL_KEEP_OUT + radius for _, _, gx, gy in all_pairs):
                continue
            new.append(Ball(round(x, 4), round(y, 4), radius, mass))
            placed.append((x, y))
            radii.append(radius)
            turn += 1
            break
        else:
            order.remove(k)
    if len(new) < count:
        raise WorldError(f"{world.source}: room for only {len(new)} of {count} balls of radius {radius:g} m on the "
                         f"shortest paths of {len(chosen)} pairs of world {world.name!r}")
    return task.with_changes(balls=world.balls + tuple(new))
