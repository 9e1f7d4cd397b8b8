"""``curlnav bench metrics``: the five metrics on a 240 x 240 grid with 10 pairs, and the
BARN parameter grid's metric ranges."""

from __future__ import annotations

import argparse
import os
import platform
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

HELP = "difficulty metrics: 240 x 240 timing and the BARN parameter grid"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--per-setting", type=int, default=25, help="worlds per fill/smoothing setting (BARN: 25)")


def main(args: argparse.Namespace) -> int:
    run_metrics_bench(per_setting=args.per_setting)
    return 0

REFERENCE = {  # the real BARN set, recomputed with the specification (min, median, mean, max)
    "distance": (1.18, 2.13, 2.37, 6.96), "visibility": (2.92, 5.28, 5.91, 12.16),
    "dispersion": (0.65, 4.51, 4.35, 6.13), "characteristic_dimension": (0.73, 3.22, 4.05, 14.77),
    "tortuosity": (1.00, 1.17, 1.21, 1.71),
}


def barn_parameter_grid(per_setting: int = 25) -> tuple[np.ndarray, list[int]]:
    """Metrics of ``per_setting`` worlds for each fill_pct x smooth_iter setting of BARN's set."""
    import numpy as np

    from curlnav.worlds.difficulty.metrics import MetricMaps
    from curlnav.worlds.difficulty.rank import world_paths
    from curlnav.worlds.procedural.generators import barn

    rows, lengths = [], []
    for fi, fill in enumerate((0.15, 0.20, 0.25, 0.30)):
        for smooth in (2, 3, 4):
            for i in range(per_setting):
                world = barn(seed=i + 100 * smooth + 1000 * fi, fill_pct=fill, smooth_iter=smooth)
                cs, paths = world_paths(world)
                rows.append(MetricMaps.of(cs).along(paths[0]))
                lengths.append(len(paths[0]))
    return np.array(rows), lengths


def run_metrics_bench(per_setting: int = 25, repeats: int = 5) -> None:
    import numpy as np

    from curlnav.worlds.difficulty.metrics import METRIC_NAMES
    from curlnav.worlds.difficulty.rank import measure
    from curlnav.worlds.procedural.generators import barn_3x3

    print(f"machine: {platform.machine()} cpus={os.cpu_count()} python={platform.python_version()}")
    world = barn_3x3(seed=0, pairs=10)
    rows, cols = world.occupancy.shape
    measure(world)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        d = measure(world)
        times.append(time.perf_counter() - t0)
    print(f"{rows} x {cols} grid, {d.pairs} pairs: {min(times):.3f} s best, {np.median(times):.3f} s median of {repeats} "
          f"(five metric maps, 10 shortest paths, averages)")
    t0 = time.perf_counter()
    values, lengths = barn_parameter_grid(per_setting)
    print(f"BARN parameter grid: {len(values)} worlds (fill 0.15-0.30 x smoothing 2-4 x {per_setting}) generated and "
          f"measured in {time.perf_counter() - t0:.1f} s; path lengths {min(lengths)}-{max(lengths)} cells")
    print(f"{'metric':<26}{'min':>7}{'median':>8}{'mean':>7}{'max':>7}   reference min/median/mean/max")
    for i, name in enumerate(METRIC_NAMES):
        v = values[:, i]
        ref = "/".join(f"{x:.2f}" for x in REFERENCE[name])
        print(f"{name:<26}{v.min():7.2f}{np.median(v):8.2f}{v.mean():7.2f}{v.max():7.2f}   {ref}")
