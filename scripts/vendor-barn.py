#!/usr/bin/env python3
"""Vendor the BARN Challenge's 300 static worlds into curlnav (``curlnav/worlds/data/barn/``).

Reads a checkout of https://github.com/Daffan/the-barn-challenge (MIT licence) and writes:

- ``worlds/world_N.world.xz`` (N = 0..299): the Gazebo world files, xz-compressed; decompressed
  they are byte for byte the originals (``MANIFEST.sha256`` holds the originals' sha256).
- ``paths/path_N.npy``: the reference paths (grid cells), byte for byte.
- ``LICENSE``: the challenge's licence, byte for byte; ``SOURCE.md``: where and when from.
- ``barn.npz``, what the suite needs, precomputed from the originals:
  ``lattice`` (300, 64, 30) bool, the cylinder lattice: ``lattice[n, j, k]`` is a cylinder of
  radius 0.075 m centred at ``x = -(k + 0.5) * 0.15``, ``y = (j + 0.5) * 0.15`` (m, world frame);
  ``path_length_m`` (300,), the reference path length as the challenge's ``run.py`` measures it
  (start, the path cells converted to metres, goal).

Checks made while vendoring (the script stops on the first failure): every cylinder sits on the
lattice, and every path cell is free on the 30 x 30 BARN grid inflated by 2 cells (BARN's
C-space), with grid row ``r`` at lattice column ``k = 29 - r`` and grid column ``c`` at lattice
row ``j = c + 34``: the challenge's own planner confirms the alignment.

Usage: ``scripts/vendor-barn.py CHECKOUT [--commit SHA --date YYYY-MM-DD]`` (commit and date are
read with git when CHECKOUT is a git work tree).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import io
import lzma
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

WORLDS = range(300)  # the static worlds; 300-359 (DynaBARN) move and are left out
CELL = 0.15  # m, the lattice pitch (twice the cylinder radius)
LATTICE_ROWS, LATTICE_COLS = 64, 30  # y (0..9.6 m) by x (-4.5..0 m)
FIELD_ROW0 = 34  # lattice row of BARN grid column 0
# run.py (static worlds, since its 2024 revision): the start in the world frame and the goal 10 m
# ahead; its path-cell-to-metre conversion: x = row * 0.15 - 4.575, y = col * 0.15 + 5.075
START = (-2.25, 3.0)
GOAL = (START[0], START[1] + 10.0)
PATH_X0, PATH_Y0 = -(30 * CELL + CELL / 2), 5.0 + CELL / 2
REPOSITORY = "https://github.com/Daffan/the-barn-challenge"
OUT = Path(__file__).resolve().parent.parent / "curlnav" / "worlds" / "data" / "barn"
_CYLINDER = re.compile(r"<model name='unit_cylinder_\d+'>\s*<static>1</static>\s*<pose frame=''>([^<]*)</pose>")


def lattice_of(text: str, name: str) -> np.ndarray:
    """The cylinder lattice of one world file's text (its ``<state>`` snapshot left out)."""
    body = text.split("<state", 1)[0]
    poses = np.array([[float(v) for v in s.split()] for s in _CYLINDER.findall(body)])
    if len(poses) == 0 or body.count("<cylinder>") != 2 * len(poses):  # collision + visual
        raise SystemExit(f"{name}: expected static unit cylinders only")
    k = np.rint(-poses[:, 0] / CELL - 0.5).astype(int)
    j = np.rint(poses[:, 1] / CELL - 0.5).astype(int)
    if not (np.allclose(-(k + 0.5) * CELL, poses[:, 0], atol=1e-6) and np.allclose((j + 0.5) * CELL, poses[:, 1], atol=1e-6)
            and np.allclose(poses[:, 2:], 0.0)):
        raise SystemExit(f"{name}: a cylinder off the 0.15 m lattice")
    grid = np.zeros((LATTICE_ROWS, LATTICE_COLS), bool)
    grid[j, k] = True
    return grid


def barn_grid(lattice: np.ndarray) -> np.ndarray:
    """The 30 x 30 BARN grid (row r, column c as in the path files) of a lattice."""
    return lattice[FIELD_ROW0:FIELD_ROW0 + 30, ::-1].T


def path_length(path: np.ndarray) -> float:
    """The reference path's length (m) as run.py measures it: start, cells in metres, goal."""
    points = np.vstack([START, np.column_stack([path[:, 0] * CELL + PATH_X0, path[:, 1] * CELL + PATH_Y0]), GOAL])
    return float(np.hypot(*np.diff(points, axis=0).T).sum())


def git_facts(checkout: Path) -> tuple[str, str]:
    try:
        out = subprocess.run(["git", "-C", str(checkout), "log", "-1", "--format=%H %cs"], capture_output=True,
                             text=True, check=True).stdout.split()
        return out[0], out[1]
    except (OSError, subprocess.CalledProcessError, IndexError):
        return "", ""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkout", type=Path, help="a checkout of the-barn-challenge")
    parser.add_argument("--commit", default=None, help="the checkout's commit (default: from git)")
    parser.add_argument("--date", default=None, help="the commit's date, YYYY-MM-DD (default: from git)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    barn = args.checkout / "jackal_helper" / "worlds" / "BARN"
    commit, date = git_facts(args.checkout)
    commit, date = args.commit or commit, args.date or date
    if not commit or not date:
        raise SystemExit("give --commit and --date (the checkout is not a git work tree)")
    (args.out / "worlds").mkdir(parents=True, exist_ok=True)
    (args.out / "paths").mkdir(parents=True, exist_ok=True)
    manifest, lattices, lengths = [], [], []
    for n in WORLDS:
        world, path_file = barn / f"world_{n}.world", barn / "path_files" / f"path_{n}.npy"
        raw, path_raw = world.read_bytes(), path_file.read_bytes()
        lattice = lattice_of(raw.decode(), world.name)
        path = np.load(io.BytesIO(path_raw))
        blocked = ndimage.binary_dilation(barn_grid(lattice), np.ones((5, 5), bool))
        if blocked[path[:, 0], path[:, 1]].any():
            raise SystemExit(f"{path_file.name}: a path cell is blocked on the lattice's C-space grid")
        (args.out / "worlds" / f"{world.name}.xz").write_bytes(lzma.compress(raw, preset=9 | lzma.PRESET_EXTREME))
        (args.out / "paths" / path_file.name).write_bytes(path_raw)
        manifest += [f"{hashlib.sha256(raw).hexdigest()}  jackal_helper/worlds/BARN/{world.name}",
                     f"{hashlib.sha256(path_raw).hexdigest()}  jackal_helper/worlds/BARN/path_files/{path_file.name}"]
        lattices.append(lattice)
        lengths.append(path_length(path))
    licence = (args.checkout / "LICENSE").read_bytes()
    (args.out / "LICENSE").write_bytes(licence)
    manifest.append(f"{hashlib.sha256(licence).hexdigest()}  LICENSE")
    (args.out / "MANIFEST.sha256").write_text("\n".join(manifest) + "\n")
    with open(args.out / "barn.npz", "wb") as f:
        np.savez_compressed(f, lattice=np.array(lattices), path_length_m=np.array(lengths), start=np.array(START),
                            goal=np.array(GOAL))
    today = datetime.date.today().isoformat()
    (args.out / "SOURCE.md").write_text(f"""# The BARN Challenge's static worlds

From {REPOSITORY} (MIT licence, `LICENSE` here, byte for byte), commit `{commit}` ({date}),
vendored on {today} by `scripts/vendor-barn.py`.

- `worlds/world_N.world.xz`, N = 0..299: `jackal_helper/worlds/BARN/world_N.world`, xz-compressed
  (decompressed: byte for byte; `MANIFEST.sha256` holds the originals' sha256).
- `paths/path_N.npy`: `jackal_helper/worlds/BARN/path_files/path_N.npy`, byte for byte.
- `barn.npz`: computed from those files by `scripts/vendor-barn.py` (the cylinder lattice and each
  reference path's length as the challenge's `run.py` measures it, from the start {START} to the
  goal {GOAL}).

The 60 dynamic worlds (DynaBARN, 300-359), the Gazebo plugins and the challenge's code are not
vendored.
""")
    print(f"wrote {len(manifest) - 1} files, LICENSE, MANIFEST.sha256, SOURCE.md and barn.npz in {args.out} "
          f"(commit {commit[:12]}, {date})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
