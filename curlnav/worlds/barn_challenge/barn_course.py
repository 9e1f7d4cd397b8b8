"""``barn-course``: training worlds laid out as the BARN Challenge's, never the challenge's own.

A 30 x 30 grid from BARN's cellular automaton (``curlnav.worlds.procedural.generators.barn_cellular_automaton``:
random fill, then smoothing) is set into the challenge's lattice (``curlnav.worlds.barn_challenge.barn``): 0.075 m
cylinders on a 0.15 m pitch, the walled start area, the Jackal's start at (-2.25, 3) m facing +y and
the goal 10 m ahead, reached within 1 m. A draw is kept only when a disc of ``clearance`` (m) can
get from the start to the goal between the cylinders (the free space eroded by the disc is
connected); otherwise the automaton draws again (``seed`` fixes the whole sequence).

The challenge's 300 worlds are the test set (``curlnav eval --suite barn``): no seed of this family
reproduces one of their grids (``tests/test_worlds_barn_course.py`` checks seeds 0-99, and
``barn_course`` refuses a draw equal to one), and seeds 100 and above are held out as in every
family.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import ndimage

from curlnav.worlds.barn_challenge import barn
from curlnav.worlds.core.world import World
from curlnav.worlds.procedural.generators import barn_cellular_automaton
from curlnav.worlds.real.sdf import DEFAULT_RESOLUTION

#: the Jackal's half width (0.215 m) and a little: narrower gaps are not passable
DEFAULT_CLEARANCE = 0.22  # m


@lru_cache(maxsize=1)
def _challenge_grids() -> frozenset[bytes]:
    return frozenset(np.packbits(barn.grid(n)).tobytes() for n in range(barn.COUNT))


def passable(world: World, clearance: float) -> bool:
    """Whether a disc of radius ``clearance`` (m) gets from the world's start to its goal."""
    r = int(np.ceil(clearance / world.resolution))
    yy, xx = np.ogrid[-r:r + 1, -r:r + 1]
    disc = xx * xx + yy * yy <= r * r
    free = ~ndimage.binary_dilation(world.occupancy, structure=disc)
    labels, _ = ndimage.label(free)
    pair = world.pairs[0]

    def label_at(x: float, y: float) -> int:
        col = int((x - world.origin[0]) / world.resolution)
        row = int((y - world.origin[1]) / world.resolution)
        return int(labels[row, col])

    start = label_at(pair.x, pair.y)
    return start > 0 and start == label_at(pair.gx, pair.gy)


def barn_course(seed: int = 0, fill_pct: float = 0.25, smooth_iter: int = 3, clearance: float = DEFAULT_CLEARANCE,
                resolution: float = DEFAULT_RESOLUTION, max_tries: int = 2000) -> World:
    """One training course (see the module docstring); ``fill_pct`` and ``smooth_iter`` are the
    automaton's, ``clearance`` and ``resolution`` in m. ``ValueError`` when ``max_tries`` draws
    leave no passable course."""
    if not 0.0 <= fill_pct < 1.0:
        raise ValueError(f"fill_pct must be in [0, 1), got {fill_pct}")
    if clearance <= 0:
        raise ValueError(f"clearance must be positive, got {clearance}")
    rng = np.random.default_rng([seed, 38])
    challenge = _challenge_grids()
    for _ in range(max_tries):
        automaton = barn_cellular_automaton(rng, fill_pct, int(smooth_iter))
        # the automaton walls its first and last rows: the challenge's side walls (path-file orientation)
        if np.packbits(automaton).tobytes() in challenge:
            continue  # the test set is never a training world
        world = barn.lattice_world(barn.lattice_of_grid(automaton), f"barn-course-{seed}",
                                   f"generated:barn-course seed={seed} fill_pct={fill_pct} smooth_iter={smooth_iter}",
                                   resolution)
        if passable(world, clearance):
            return world
    raise ValueError(f"no passable barn-course in {max_tries} draws (fill_pct={fill_pct}, clearance={clearance} m)")
