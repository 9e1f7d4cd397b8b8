"""Doors everywhere they belong (issue 28): a T-Maze family that varies, whose pairs can only be
done by pushing doors open, and the NAMO families at training seeds as S2 material. The
independent truth is the C-space grid: reachable with the doors open, blocked with them closed."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from curlnav.sim import NamoEnv, get_world, load_world, save_world
from curlnav.worlds.difficulty.rank import path_points, world_paths
from curlnav.worlds.families import generate
from curlnav.worlds.procedural.namo import closed_door_grid, door_crossings, opening_direction, reachable


def test_a_closed_door_blocks_the_corridor_it_hangs_in():
    world = get_world("door-corridor")
    pair = world.pair("through-door")
    assert reachable(world, pair) and not reachable(world, pair, doors_closed=True)
    assert closed_door_grid(world).sum() > world.occupancy.sum()


def test_varying_t_mazes_are_reproducible_per_seed_and_vary_in_every_dimension():
    worlds = [generate("t-maze-doors", seed) for seed in range(40)]
    again = generate("t-maze-doors", 7)
    assert np.array_equal(again.occupancy, worlds[7].occupancy) and again.doors == worlds[7].doors
    assert again.pairs == worlds[7].pairs and again.balls == worlds[7].balls
    rooms = Counter(len(w.ball_regions) - 1 for w in worlds)  # bar rooms (one region per room, the stem too)
    assert set(rooms) == {3, 4, 5}
    assert len({w.size for w in worlds}) > 30, "room sizes vary"
    doors = [d for w in worlds for d in w.doors]
    assert {d.swing for d in doors} == {"left", "right"}
    assert len({round(d.closed_angle, 3) for d in doors}) == 4, "hinges at either end, in walls along x and y"
    assert len({round(d.width, 2) for d in doors}) >= 3, "door widths vary"
    assert min(len(w.doors) for w in worlds) >= 2 and max(len(w.doors) for w in worlds) >= 4
    assert len({len(w.balls) for w in worlds}) >= 3, "balls vary"
    for w in worlds:
        assert [p.name for p in w.pairs] == ["p1", "p2", "p3", "p4"] and [p.step for p in w.pairs] == [1, 2, 3, 4]


@pytest.mark.parametrize("seed", range(0, 40, 3))
def test_every_t_maze_pair_needs_a_door_pushed_open_and_never_a_pull(seed):
    world = generate("t-maze-doors", seed)
    _, paths = world_paths(world)
    for pair, path in zip(world.pairs, paths):
        assert reachable(world, pair), f"{world.name} {pair.name}: unreachable with the doors open"
        assert not reachable(world, pair, doors_closed=True), f"{world.name} {pair.name}: a way round the doors"
        crossings = door_crossings(world, np.column_stack(path_points(world, path)))
        assert crossings and all(forward for _, forward in crossings), f"{world.name} {pair.name}: a pull"


@pytest.mark.parametrize("family", ["namo-office", "namo-indoor", "namo-auditorium"])
def test_namo_worlds_at_training_seeds_need_their_doors_pushed(family):
    world = generate(family, 4)
    for pair in world.pairs[:6]:
        assert reachable(world, pair) and not reachable(world, pair, doors_closed=True), f"{world.name} {pair.name}"


def test_a_varying_t_maze_saves_loads_and_runs_with_its_door_opening_away_from_the_start(tmp_path):
    world = generate("t-maze-doors", 3)
    loaded = load_world(save_world(world, tmp_path / "w.yaml"))
    assert loaded.doors == world.doors and loaded.pairs == world.pairs
    env = NamoEnv("t-maze-doors:3")
    try:
        env.reset(seed=0, options={"pair": "p1"})
        for _ in range(3):
            env.step(np.array([0.5, 0.0, 0.0], dtype=np.float32))
    finally:
        env.close()
    pair = world.pair("p1")
    _, paths = world_paths(world)
    index, forward = door_crossings(world, np.column_stack(path_points(world, paths[0])))[0]
    hinge = np.array([world.doors[index].hinge_x, world.doors[index].hinge_y])
    assert forward and float(opening_direction(world.doors[index]) @ (hinge - [pair.x, pair.y])) > 0, \
        "the first door on p1's way opens away from its start"
