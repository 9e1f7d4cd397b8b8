"""Rank worlds by navigation difficulty: the paper's Table I and Fig. 3.

For each world: resample its grid to ``METRIC_RESOLUTION`` (BARN's 0.15 m), inflate it by
``CSPACE_RADIUS_M`` (BARN's 2 cells), find the shortest path of every start/goal pair (for
worlds of the ``barn`` family, BARN's own planner, which keeps away from walls), average
the five BARN metrics along each path (start cell counted twice, as in BARN's path files) and
then over pairs.

Easy/hard rule. The paper found Tortuosity and Distance to be the metrics that decide whether a
world can be trained from scratch. We z-score both across the ranked set and call
``difficulty = z(Tor) - z(Dist)`` (bendier paths and closer obstacles are harder); worlds with
``difficulty <= 0`` are *easy* (train them from scratch, curriculum stage 1), the rest *hard*.
The curriculum reads the worlds in ascending difficulty.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from curlnav.worlds.core.pairs import sample_pairs
from curlnav.worlds.core.world import StartGoal, World
from curlnav.worlds.difficulty.metrics import GridGraph, MetricMaps, MetricsError, barn_astar, inflate

METRIC_RESOLUTION = 0.15  # m per cell
CSPACE_RADIUS_M = 0.3  # m


@dataclass(frozen=True)
class WorldDifficulty:
    name: str
    width_m: float
    height_m: float
    distance: float
    visibility: float
    dispersion: float
    characteristic_dimension: float
    tortuosity: float
    pairs: int
    difficulty: float = float("nan")
    category: str = ""
    mds_x: float = float("nan")
    mds_y: float = float("nan")

    @property
    def metrics(self) -> np.ndarray:
        return np.array([self.distance, self.visibility, self.dispersion, self.characteristic_dimension,
                         self.tortuosity])


def resample(occupancy: np.ndarray, resolution: float, target: float) -> np.ndarray:
    """Occupancy at ``target`` m per cell: a target cell is an obstacle if any source cell it
    covers is (coarsening), or if the source cell under its centre is (refining)."""
    occupancy = np.asarray(occupancy, dtype=bool)
    if math.isclose(resolution, target):
        return occupancy.copy()
    rows, cols = occupancy.shape
    out_rows = max(1, int(round(rows * resolution / target)))
    out_cols = max(1, int(round(cols * resolution / target)))
    if target > resolution:
        out = np.zeros((out_rows, out_cols), dtype=bool)
        r = np.minimum((np.arange(rows) * resolution / target).astype(int), out_rows - 1)
        c = np.minimum((np.arange(cols) * resolution / target).astype(int), out_cols - 1)
        rr, cc = np.nonzero(occupancy)
        out[r[rr], c[cc]] = True
        return out
    r = np.minimum(((np.arange(out_rows) + 0.5) * target / resolution).astype(int), rows - 1)
    c = np.minimum(((np.arange(out_cols) + 0.5) * target / resolution).astype(int), cols - 1)
    return occupancy[np.ix_(r, c)]


MEASURE_PAIRS = 5  # seeded random pairs measured on a world with no pairs of its own
MEASURE_SEED = 0


def measured_pairs(world: World) -> tuple[StartGoal, ...]:
    """The pairs a world is measured (and drawn) with: its own, or for a plain map
    ``MEASURE_PAIRS`` seeded random pairs (``curlnav.worlds.core.pairs``; ``WorldError`` when no pair is
    possible)."""
    if world.pairs:
        return world.pairs
    return sample_pairs(world, MEASURE_PAIRS, seed=MEASURE_SEED)


def world_paths(world: World, resolution: float = METRIC_RESOLUTION, radius_m: float = CSPACE_RADIUS_M
                ) -> tuple[np.ndarray, list[np.ndarray]]:
    """The C-space grid at ``resolution`` (in the world's grid frame) and one shortest cell path
    per pair of ``measured_pairs`` (start twice). ``MetricsError`` names the world and pair when
    a pair is blocked or unreachable. ``path_points`` turns a path into map-frame points."""
    grid = resample(world.occupancy, world.resolution, resolution)
    cs = inflate(grid, int(round(radius_m / resolution)))
    pairs = measured_pairs(world)
    rows, cols = cs.shape
    starts, goals = [], []
    for pair in pairs:
        cells = []
        for label, (x, y) in (("start", (pair.x, pair.y)), ("goal", (pair.gx, pair.gy))):
            u, v = world.grid_from_map(x, y)
            r = int(math.floor(v / resolution))
            c = int(math.floor(u / resolution))
            if not (0 <= r < rows and 0 <= c < cols) or cs[r, c]:
                raise MetricsError(f"{world.source}: pair {pair.name!r} {label} ({x:.2f}, {y:.2f}) lies inside an "
                                   f"obstacle of the C-space grid (static map inflated by {radius_m} m)")
            cells.append((r, c))
        starts.append(cells[0])
        goals.append(cells[1])
    if world.source.startswith("generated:barn ") and math.isclose(world.resolution, resolution):
        # a BARN world: BARN's own planner, so the path-averaged metrics compare with the benchmark's
        paths = [barn_astar(cs, s, g, int(round(radius_m / resolution))) for s, g in zip(starts, goals)]
    else:
        paths = GridGraph(cs).shortest_paths(starts, goals)
    for pair, path in zip(pairs, paths):
        if path is None:
            raise MetricsError(f"{world.source}: pair {pair.name!r} has no path on the C-space grid")
    return cs, paths


def path_points(world: World, path: np.ndarray, resolution: float = METRIC_RESOLUTION) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame ``(x, y)`` arrays (m) of the cell centres of a ``world_paths`` path."""
    path = np.asarray(path)
    return world.map_from_grid((path[:, 1] + 0.5) * resolution, (path[:, 0] + 0.5) * resolution)


def measure(world: World) -> WorldDifficulty:
    """The five metrics of ``world``, averaged over its pairs' shortest paths."""
    cs, paths = world_paths(world)
    maps = MetricMaps.of(cs)
    values = np.mean([maps.along(p) for p in paths], axis=0)
    width, height = world.size
    return WorldDifficulty(world.name, width, height, *map(float, values), pairs=len(paths))


def classical_mds(points: np.ndarray, dims: int = 2) -> np.ndarray:
    """Torgerson's classical multidimensional scaling of the rows of ``points`` (Euclidean)."""
    n = len(points)
    if n < 2:
        return np.zeros((n, dims))
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    j = np.eye(n) - np.ones((n, n)) / n
    b = -0.5 * j @ d2 @ j
    values, vectors = np.linalg.eigh(b)
    order = np.argsort(values)[::-1][:dims]
    coords = vectors[:, order] * np.sqrt(np.maximum(values[order], 0))
    for k in range(coords.shape[1]):  # a deterministic sign
        if coords[np.argmax(np.abs(coords[:, k])), k] < 0:
            coords[:, k] *= -1
    if coords.shape[1] < dims:
        coords = np.pad(coords, ((0, 0), (0, dims - coords.shape[1])))
    return coords


def zscore(values: np.ndarray) -> np.ndarray:
    std = values.std(axis=0)  # population standard deviation, as BARN
    return (values - values.mean(axis=0)) / np.where(std > 0, std, 1.0)


def rank(worlds: list[World]) -> list[WorldDifficulty]:
    """Measure, z-score, split easy/hard, place by MDS; sorted from easiest to hardest."""
    measured = [measure(w) for w in worlds]
    m = np.array([d.metrics for d in measured])
    z = zscore(m)
    difficulty = z[:, 4] - z[:, 0]
    coords = classical_mds(z)
    out = [WorldDifficulty(**{**asdict(d), "difficulty": float(difficulty[i]),
                              "category": "easy" if difficulty[i] <= 0 else "hard",
                              "mds_x": float(coords[i, 0]), "mds_y": float(coords[i, 1])})
           for i, d in enumerate(measured)]
    return sorted(out, key=lambda d: d.difficulty)


def ranking_table(rows: list[WorldDifficulty]) -> str:
    """A text table like the paper's Table I."""
    head = (f"{'world':<16} {'size (m)':>11} {'Dist':>6} {'Vis':>6} {'Disp':>6} {'CD':>6} {'Tor':>6} "
            f"{'pairs':>5} {'difficulty':>10}  class")
    lines = [head, "-" * len(head)]
    for d in rows:
        size = f"{d.width_m:.0f} x {d.height_m:.0f}"
        lines.append(f"{d.name:<16} {size:>11} {d.distance:6.2f} {d.visibility:6.2f} {d.dispersion:6.2f} "
                     f"{d.characteristic_dimension:6.2f} {d.tortuosity:6.2f} {d.pairs:5d} {d.difficulty:10.2f}  {d.category}")
    return "\n".join(lines)


def write_outputs(rows: list[WorldDifficulty], out_dir: str | Path) -> dict[str, Path]:
    """``ranking.csv``, ``ranking.json`` (the scheduler reads its ``order``) and ``mds.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = list(asdict(rows[0]).keys()) if rows else []
    with open(out_dir / "ranking.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for d in rows:
            writer.writerow(asdict(d))
    (out_dir / "ranking.json").write_text(json.dumps({
        "metric_resolution_m": METRIC_RESOLUTION, "cspace_radius_m": CSPACE_RADIUS_M,
        "rule": "difficulty = z(tortuosity) - z(distance); easy if difficulty <= 0",
        "order": [d.name for d in rows], "easy": [d.name for d in rows if d.category == "easy"],
        "hard": [d.name for d in rows if d.category == "hard"], "worlds": [asdict(d) for d in rows]}, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5.5), dpi=110)
    for d in rows:
        colour = "tab:green" if d.category == "easy" else "tab:red"
        ax.scatter([d.mds_x], [d.mds_y], s=60, color=colour)
        ax.annotate(d.name, (d.mds_x, d.mds_y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.scatter([], [], color="tab:green", label="easy (train from scratch)")
    ax.scatter([], [], color="tab:red", label="hard (curriculum)")
    ax.set_xlabel("MDS coordinate 1")
    ax.set_ylabel("MDS coordinate 2")
    ax.set_title("Worlds by navigation difficulty (MDS of z-scored BARN metrics)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_dir / "mds.png")
    plt.close(fig)
    return {"csv": out_dir / "ranking.csv", "json": out_dir / "ranking.json", "png": out_dir / "mds.png"}
