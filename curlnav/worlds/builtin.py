"""Built-in worlds for tests, demos and benchmarks, and the lookup of a world by name or file."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from curlnav.worlds.core.world import Ball, Door, RandomPairs, Region, StartGoal, World, WorldError, load_world


def _walled_grid(width_m: float, height_m: float, resolution: float) -> np.ndarray:
    cols = int(round(width_m / resolution))
    rows = int(round(height_m / resolution))
    grid = np.zeros((rows, cols), dtype=bool)
    grid[0, :] = grid[-1, :] = True
    grid[:, 0] = grid[:, -1] = True
    return grid


def _fill(grid: np.ndarray, resolution: float, x0: float, y0: float, x1: float, y1: float) -> None:
    """Mark the cells covering ``[x0, x1] x [y0, y1]`` (m, map frame at origin 0) as obstacles."""
    grid[int(round(y0 / resolution)):int(round(y1 / resolution)),
         int(round(x0 / resolution)):int(round(x1 / resolution))] = True


def open_room() -> World:
    """A 10 m x 10 m walled room with four pillars and two balls re-placed on every reset.

    Start/goal pairs are drawn at random, at least 4 m apart; four named pairs are kept for
    evaluation and demos.
    """
    res = 0.1
    grid = _walled_grid(10.0, 10.0, res)
    for x, y in ((3.0, 3.0), (6.6, 3.2), (3.2, 6.6), (6.4, 6.4)):
        _fill(grid, res, x, y, x + 0.6, y + 0.6)
    pairs = (
        StartGoal("diagonal", 1.2, 1.2, math.pi / 4, 8.8, 8.8),
        StartGoal("across", 1.2, 5.0, 0.0, 8.8, 5.0),
        StartGoal("up", 5.0, 1.2, math.pi / 2, 5.0, 8.8),
        StartGoal("back", 8.8, 1.5, math.pi, 1.5, 8.5),
    )
    return World(
        name="open-room", occupancy=grid, resolution=res, wall_height=1.0,
        balls=(Ball(5.0, 5.0, 0.25, 0.5, region=0), Ball(2.0, 8.0, 0.25, 0.5, region=0)),
        pairs=pairs, ball_regions=(Region(1.0, 1.0, 9.0, 9.0),),
        random_pairs=RandomPairs(min_distance=4.0, clearance=0.8), source="builtin:open-room",
    )


def door_corridor() -> World:
    """A 12 m x 4 m corridor cut by a wall at x = 6 m whose 1.4 m gap holds a hinged door.

    The door hangs at (6.0, 1.3), closed along +y, and swings clockwise (toward +x) when pushed
    from the start side. The only pair starts at x = 2 m and ends at x = 10 m.
    """
    res = 0.1
    grid = _walled_grid(12.0, 4.0, res)
    _fill(grid, res, 5.9, 0.0, 6.1, 1.3)
    _fill(grid, res, 5.9, 2.7, 6.1, 4.0)
    door = Door(hinge_x=6.0, hinge_y=1.3, width=1.38, closed_angle=math.pi / 2, swing="right",
                mass=2.0, hinge_friction=0.5)
    return World(
        name="door-corridor", occupancy=grid, resolution=res, wall_height=1.0, doors=(door,),
        pairs=(StartGoal("through-door", 2.0, 2.0, 0.0, 10.0, 2.0, step=1),),
        source="builtin:door-corridor",
    )


def bench_world(seed: int = 7) -> World:
    """The benchmark world: 36 m x 36 m at 0.6 m cells (the paper's grid), a wall all round,
    scattered obstacle clusters to about 300 obstacle cells, and 8 balls."""
    res = 0.6
    rng = np.random.default_rng(seed)
    grid = _walled_grid(36.0, 36.0, res)
    target = 300
    while grid.sum() < target:
        iy, ix = rng.integers(3, 57, size=2)
        h, w = rng.integers(1, 4, size=2)
        grid[iy:iy + h, ix:ix + w] = True
    grid[27:33, 27:33] = False  # keep the centre free for the start
    free = np.argwhere(~grid)
    balls = []
    while len(balls) < 8:
        iy, ix = free[rng.integers(len(free))]
        x, y = (ix + 0.5) * res, (iy + 0.5) * res
        if math.hypot(x - 18.0, y - 18.0) > 3.0:
            balls.append(Ball(float(x), float(y), 0.25, 0.5))
    return World(name="bench-36m", occupancy=grid, resolution=res, wall_height=1.0, balls=tuple(balls),
                 pairs=(StartGoal("centre", 18.0, 18.0, 0.0, 30.0, 30.0),), source="builtin:bench-36m")


BUILTIN_WORLDS: dict[str, Callable[[], World]] = {
    "open-room": open_room,
    "door-corridor": door_corridor,
    "bench-36m": bench_world,
}

#: the forms every world argument takes (one resolver, ``get_world``): for command-line help
WORLD_FORMS = ("built-in world name, world YAML path, FAMILY:SEED for a generated world (e.g. t-maze:0), or "
               "real:NAME for a real building's SLAM map with the real suite's pairs and balls (e.g. real:willow-garage)")

_CACHE: dict[str, World] = {}
_DISTRIBUTION = re.compile(r"^[a-z0-9][a-z0-9-]*:\d+-\d+(\(.*\))?$")


def get_world(spec: str | os.PathLike | World) -> World:
    """The one resolver of a world argument (every command, service and curriculum file): a
    built-in name, a path to a world YAML, ``FAMILY:SEED`` for a generated world
    (``t-maze:0``, ``barn-3x3:12``: ``curlnav.worlds.families``), a world distribution's key
    (``barn-3x3:0-99(fill_pct=0.1~0.3)``: its first world, ``curlnav.worlds.distribution``),
    ``real:NAME`` for a real building's vendored SLAM map with the ``real`` suite's pairs and balls
    (``curlnav.worlds.real.real_maps``), or a ``World`` (returned as is).

    Raises ``WorldError`` naming the forms and the known built-ins when ``spec`` is none of them.
    """
    if isinstance(spec, World):
        return spec
    key = os.fspath(spec)
    if key in BUILTIN_WORLDS:
        if key not in _CACHE:
            _CACHE[key] = BUILTIN_WORLDS[key]()
        return _CACHE[key]
    path = Path(key)
    if path.suffix in (".yaml", ".yml") or path.exists():
        return load_world(path)
    if _DISTRIBUTION.match(key):  # FAMILY:LO-HI(...): a world distribution names its first world
        from curlnav.worlds.distribution import WorldDistribution

        if key not in _CACHE:
            try:
                distribution = WorldDistribution.parse(key)
            except ValueError as exc:
                raise WorldError(str(exc)) from None
            _CACHE[key] = distribution.world(distribution.lo)
        return _CACHE[key]
    if key.startswith("real:"):  # a vendored real map (its task is cached there)
        from curlnav.worlds.real import real_maps

        return real_maps.task(key.removeprefix("real:"))
    family, sep, seed = key.rpartition(":")
    if sep and seed.isascii() and seed.isdigit():
        from curlnav.worlds.families import FAMILIES, generate

        if family in FAMILIES:
            if key not in _CACHE:
                _CACHE[key] = generate(family, int(seed))
            return _CACHE[key]
        raise WorldError(f"unknown world family {family!r} in {key!r}: FAMILY:SEED takes one of {', '.join(FAMILIES)}")
    raise WorldError(f"unknown world {key!r}: not a built-in ({', '.join(BUILTIN_WORLDS)}), not a world YAML file, "
                     f"not FAMILY:SEED (a generated world, e.g. t-maze:0) and not real:NAME (a real building's map)")
