"""The BARN Challenge's 300 static worlds, vendored (``curlnav/worlds/data/barn``, MIT licence;
``SOURCE.md`` there says from where and when; ``scripts/vendor-barn.py`` made it).

The challenge (github.com/Daffan/the-barn-challenge, ``run.py``): a Clearpath Jackal starts at
``START`` facing +y; the goal is 10 m ahead; success within ``GOAL_RADIUS`` of it; ``TIME_LIMIT``;
any collision ends the trial. Score per trial ``success * OT / clip(T, 2 OT, 8 OT)``, with
``OT`` the world's reference path length (its path file, as ``run.py`` measures it) over
``REFERENCE_SPEED``; 0.5 is the best a trial can score.

Each world is 0.075 m cylinders on a 0.15 m lattice: ``lattice(n)[j, k]`` is a cylinder at
``x = -(k + 0.5) * 0.15``, ``y = (j + 0.5) * 0.15`` (m). Rows 0..33 are the start area (walled
behind and on both sides); rows 34..63 are the 30 x 30 BARN grid (``grid(n)``, oriented as the
path files: grid row ``r`` at ``k = 29 - r``, column ``c`` at ``j = c + 34``). Beyond y = 9.6 m the
field is open up to the goal.
"""

from __future__ import annotations

import lzma
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from curlnav.worlds.core.world import StartGoal, World
from curlnav.worlds.real.sdf import DEFAULT_RESOLUTION, Shape, rasterise

DATA = Path(__file__).resolve().parent.parent / "data" / "barn"
COUNT = 300  # worlds 0..299 (the static ones)
#: run.py's start for the static worlds since its 2024 revision (the 2022 one, with which the
#: published DWA figure was measured, started at x = -2; report_test.py still measures OT from -2)
START = (-2.25, 3.0, math.pi / 2)  # x, y (m), yaw (rad): facing +y
GOAL = (START[0], START[1] + 10.0)  # 10 m ahead
GOAL_RADIUS = 1.0  # m
TIME_LIMIT = 100.0  # s
REFERENCE_SPEED = 2.0  # m/s: OT = path length / 2 m/s
CYLINDER_RADIUS = 0.075  # m
CELL = 0.15  # m, the lattice pitch
FIELD_ROW0 = 34  # lattice row of BARN grid column 0
#: the map around the lattice (x -4.5..0, y 0..9.6) and the goal: 0.5 m beyond the side walls,
#: 0.5 m behind the back wall, 1.5 m beyond the goal
BOUNDS = (-5.0, -0.5, 0.5, 14.5)  # x_min, y_min, x_max, y_max (m)


@lru_cache(maxsize=1)
def _data() -> dict[str, np.ndarray]:
    with np.load(DATA / "barn.npz") as data:
        return {key: data[key] for key in data.files}


def check_index(n: int) -> int:
    """``n`` if it names a static BARN world, else ``ValueError`` (one line)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 0 <= n < COUNT:
        raise ValueError(f"BARN worlds are numbered 0-{COUNT - 1}, got {n!r}")
    return int(n)


def parse_range(text: str) -> list[int]:
    """``"A-B"`` (inclusive) or ``"N"`` as world numbers; ``ValueError`` (one line) otherwise."""
    from curlnav.files import decimal_int

    first, sep, last = text.partition("-")
    try:
        a, b = decimal_int(first), decimal_int(last) if sep else decimal_int(first)
    except ValueError:
        raise ValueError(f"--worlds takes A-B or N (BARN worlds 0-{COUNT - 1}), got {text!r}") from None
    if not (0 <= a <= b < COUNT):
        raise ValueError(f"--worlds {text}: BARN worlds are numbered 0-{COUNT - 1}, and A-B needs A <= B")
    return list(range(a, b + 1))


def lattice(n: int) -> np.ndarray:
    """World ``n``'s cylinder lattice, bool (64, 30): ``[j, k]`` (see the module docstring)."""
    return _data()["lattice"][check_index(n)]


def grid(n: int) -> np.ndarray:
    """World ``n``'s 30 x 30 BARN grid (1 = obstacle), oriented as its path file."""
    return lattice(n)[FIELD_ROW0:FIELD_ROW0 + 30, ::-1].T


def path_cells(n: int) -> np.ndarray:
    """World ``n``'s reference path, (L, 2) grid cells ``(row, col)`` (its start listed twice)."""
    return np.load(DATA / "paths" / f"path_{check_index(n)}.npy")


def path_length(n: int) -> float:
    """World ``n``'s reference path length (m) as ``run.py`` measures it, from ``START`` to ``GOAL``."""
    return float(_data()["path_length_m"][check_index(n)])


def optimal_time(n: int) -> float:
    """``OT`` of world ``n``: its path length over ``REFERENCE_SPEED`` (s)."""
    return path_length(n) / REFERENCE_SPEED


def score(success: bool, time_s: float, n: int) -> float:
    """The challenge's score of one trial: ``success * OT / clip(T, 2 OT, 8 OT)``."""
    ot = optimal_time(n)
    return float(success) * ot / min(max(time_s, 2 * ot), 8 * ot)


def world_file(n: int) -> bytes:
    """World ``n``'s Gazebo file, byte for byte (decompressed from the vendored copy)."""
    return lzma.decompress((DATA / "worlds" / f"world_{check_index(n)}.world.xz").read_bytes())


def lattice_cylinders(cells: np.ndarray) -> list[Shape]:
    """A ``(64, 30)`` lattice's cylinders as footprints (m, world frame)."""
    j, k = np.nonzero(cells)
    return [Shape("cylinder", f"unit_cylinder_{i}", -(kk + 0.5) * CELL, (jj + 0.5) * CELL, radius=CYLINDER_RADIUS)
            for i, (jj, kk) in enumerate(zip(j.tolist(), k.tolist()))]


def cylinders(n: int) -> list[Shape]:
    """World ``n``'s cylinders as footprints (m, world frame)."""
    return lattice_cylinders(lattice(n))


def start_area() -> np.ndarray:
    """The lattice every challenge world shares outside its BARN grid, bool (64, 30): the back wall
    (row 0) and the side walls (columns 0 and 29); the grid's rows 34..63 are left free."""
    cells = np.zeros((64, 30), dtype=bool)
    cells[0, :] = True
    cells[:, 0] = cells[:, -1] = True
    return cells


def lattice_of_grid(grid_cells: np.ndarray) -> np.ndarray:
    """The challenge's lattice around a 30 x 30 BARN grid oriented as the path files (the inverse
    of ``grid``): ``start_area`` with the grid in rows 34..63."""
    if grid_cells.shape != (30, 30):
        raise ValueError(f"a BARN grid is 30 x 30 cells, got {grid_cells.shape}")
    cells = start_area()
    cells[FIELD_ROW0:FIELD_ROW0 + 30, :] = np.asarray(grid_cells, dtype=bool).T[:, ::-1]
    return cells


def lattice_world(cells: np.ndarray, name: str, source: str, resolution: float = DEFAULT_RESOLUTION) -> World:
    """A ``(64, 30)`` lattice as a curlnav ``World`` on ``BOUNDS`` at ``resolution`` (m; a cell is
    occupied when its centre lies in a cylinder), with the challenge's start/goal pair ``"barn"``."""
    x0, y0, x1, y1 = BOUNDS
    shape = (round((y1 - y0) / resolution), round((x1 - x0) / resolution))
    occupancy = rasterise(lattice_cylinders(cells), resolution, (x0, y0), shape)
    pair = StartGoal("barn", START[0], START[1], START[2], GOAL[0], GOAL[1])
    return World(name=name, occupancy=occupancy, resolution=resolution, origin=(x0, y0), wall_height=0.5,
                 pairs=(pair,), source=source)


def world(n: int, resolution: float = DEFAULT_RESOLUTION) -> World:
    """World ``n`` as a curlnav ``World`` (``lattice_world``), with the challenge's pair ``"barn"``."""
    return lattice_world(lattice(n), f"barn-world-{check_index(n)}", f"barn-challenge:world_{n}", resolution)
