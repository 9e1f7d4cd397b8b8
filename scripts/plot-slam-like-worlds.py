#!/usr/bin/env python3
"""Worlds that look like SLAM maps: each source world beside its degraded version (a PNG).

Left, the source as its generator makes it; middle, the family's world (``curlnav.worlds.procedural.degrade``),
drawn as a ROS map is (free white, occupied black, unknown grey), with its doors, balls, starts
and goals; right, 6 m x 4 m of it round a door, holes in the walls red. Prints each world's
generation time and what the degradations changed.

Usage: ``scripts/plot-slam-like-worlds.py [OUT.png]`` (default ``docs/images/slam-like-worlds.png``).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from curlnav.worlds.families import generate
from curlnav.worlds.procedural.degrade import degrade_layers, wall_thickness
from curlnav.worlds.procedural.namo import namo_indoor, namo_office
from curlnav.worlds.procedural.slam_like import SLAM_RESOLUTION, floor_plan

EXAMPLES = [  # (title of the source, source, family, seed)
    ("namo-office:4", lambda: namo_office(4), "slam-namo-office", 4),
    ("namo-indoor:5", lambda: namo_indoor(5), "slam-namo-indoor", 5),
    ("slam-floor's plan, seed 2", lambda: floor_plan(2), "slam-floor", 2),
]


def draw_slam_map(ax, world, unknown: np.ndarray) -> None:
    """``world`` as a ROS map: free white, occupied black, unknown grey; then its objects."""
    from curlnav.worlds.core.picture import draw_world

    draw_world(ax, world, pairs=world.pairs)
    width, height = world.size
    grey = np.ma.masked_where(~unknown, np.ones(unknown.shape))
    ax.imshow(grey, origin="lower", extent=(0.0, width, 0.0, height), cmap="Greys", vmin=0.0, vmax=2.6,
              interpolation="nearest")


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from curlnav.worlds.core.picture import draw_world

    out = sys.argv[1] if len(sys.argv) > 1 else "docs/images/slam-like-worlds.png"
    fig, axes = plt.subplots(len(EXAMPLES), 3, figsize=(20, 5.0 * len(EXAMPLES)), dpi=90,
                             gridspec_kw={"width_ratios": [1.0, 1.0, 0.75]})
    for row, (title, make, family, seed) in zip(axes, EXAMPLES):
        source = make()
        t0 = time.perf_counter()
        world = generate(family, seed)
        elapsed = time.perf_counter() - t0
        base = source if source.resolution <= SLAM_RESOLUTION else None
        _, layers = degrade_layers(source, seed, resolution=None if base is not None else SLAM_RESOLUTION)
        draw_world(row[0], source, pairs=source.pairs)
        row[0].set_title(f"source: {title} ({source.resolution:g} m cells)", fontsize=10)
        draw_slam_map(row[1], world, layers.unknown)
        row[1].set_title(f"{family}:{seed} ({world.resolution:g} m cells)", fontsize=10)
        draw_slam_map(row[2], world, layers.unknown)
        holes = np.ma.masked_where(~layers.gaps, np.ones(layers.gaps.shape))
        row[2].imshow(holes, origin="lower", extent=(0.0, world.size[0], 0.0, world.size[1]), cmap="autumn",
                      interpolation="nearest")
        door = world.doors[len(world.doors) // 2]
        row[2].set_xlim(door.hinge_x - 3.0, door.hinge_x + 3.0)
        row[2].set_ylim(door.hinge_y - 2.0, door.hinge_y + 2.0)
        row[2].set_title(f"{family}:{seed}, 6 m x 4 m round a door (holes red)", fontsize=10)
        thick = np.median(wall_thickness(layers.source, world.resolution)), np.median(wall_thickness(world.occupancy,
                                                                                                     world.resolution))
        print(f"{family}:{seed}: generated in {elapsed:.2f} s; walls {thick[0]:.2f} -> {thick[1]:.2f} m (median); "
              f"{int(layers.gaps.sum())} hole cells, {int(layers.speckles.sum())} specks, {int(layers.bumps.sum())} "
              f"bump cells, {int(layers.clutter.sum())} clutter cells, {int(layers.unknown.sum())} unknown cells")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    print(f"picture: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
