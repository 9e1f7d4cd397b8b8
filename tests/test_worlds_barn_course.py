"""``barn-course``: training worlds laid out as the BARN Challenge's, never one of its 300 test worlds."""

from __future__ import annotations

import numpy as np
import pytest

from curlnav.worlds.barn_challenge import barn
from curlnav.worlds.barn_challenge.barn_course import _challenge_grids, barn_course, passable
from curlnav.worlds.distribution import DistributionError, WorldDistribution
from curlnav.worlds.families import generate


def test_the_lattice_round_trips_every_challenge_grid():
    for n in range(barn.COUNT):
        assert (barn.lattice_of_grid(barn.grid(n)) == barn.lattice(n)).all(), n
    # every challenge world shares the start area outside its grid
    assert all((barn.lattice(n)[:barn.FIELD_ROW0] == barn.start_area()[:barn.FIELD_ROW0]).all() for n in range(0, 300, 7))
    for n in (0, 123, 299):  # the grid read back from a world's cells is the grid (what the tests below compare)
        assert (_grid_of(barn.world(n)) == barn.grid(n)).all()


def test_a_course_has_the_challenges_layout_start_and_goal():
    world = generate("barn-course", 3, fill_pct=0.2, smooth_iter=3)
    challenge = barn.world(0)
    assert (world.resolution, world.origin, world.occupancy.shape) == (challenge.resolution, challenge.origin,
                                                                        challenge.occupancy.shape)
    assert world.pairs == challenge.pairs  # the Jackal's start facing +y, the goal 10 m ahead
    # outside the BARN grid (y < 5.1 m: the start area) the two are the same cylinders
    rows = int((barn.FIELD_ROW0 * barn.CELL - world.origin[1]) / world.resolution)
    assert (world.occupancy[:rows] == challenge.occupancy[:rows]).all()
    assert generate("barn-course", 3, fill_pct=0.2, smooth_iter=3).occupancy.tobytes() == world.occupancy.tobytes()


def test_no_training_course_is_a_challenge_world_and_every_course_is_passable():
    """Seeds 0-99 at the curriculum's parameter ranges: none of the 300 test grids, each passable."""
    challenge = _challenge_grids()
    assert len(challenge) == barn.COUNT
    dist = WorldDistribution.from_spec({"family": "barn-course", "seeds": [0, 99],
                                        "params": {"fill_pct": [0.08, 0.30], "smooth_iter": [2, 5]}})
    for seed in range(0, 100, 3):
        world = dist.world(seed)
        grid = _grid_of(world)
        assert np.packbits(grid).tobytes() not in challenge, seed
        assert passable(world, 0.22), seed


def test_the_test_set_is_never_drawn_even_when_the_automaton_makes_it(monkeypatch):
    """Force the automaton to give a challenge grid first: the course takes the next draw."""
    import curlnav.worlds.barn_challenge.barn_course as course

    draws = iter([barn.grid(17), barn.grid(17), np.pad(np.zeros((28, 30), bool), ((1, 1), (0, 0)),
                                                       constant_values=True)])
    monkeypatch.setattr(course, "barn_cellular_automaton", lambda rng, fill, smooth: next(draws))
    world = barn_course(0)
    assert not (_grid_of(world) == barn.grid(17)).all()


def test_held_out_seeds_are_refused():
    with pytest.raises(DistributionError, match="held-out"):
        WorldDistribution.from_spec({"family": "barn-course", "seeds": [0, 100]})


def _grid_of(world) -> np.ndarray:
    """The 30 x 30 BARN grid of a course (cylinder centres sampled on the world's grid)."""
    grid = np.zeros((30, 30), bool)
    for r in range(30):
        for c in range(30):
            j, k = barn.FIELD_ROW0 + c, 29 - r
            x, y = -(k + 0.5) * barn.CELL, (j + 0.5) * barn.CELL
            col = int((x - world.origin[0]) / world.resolution)
            row = int((y - world.origin[1]) / world.resolution)
            grid[r, c] = world.occupancy[row, col]
    return grid
