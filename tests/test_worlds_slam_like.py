"""Worlds that look like SLAM maps (issue 37): ``curlnav.worlds.procedural.degrade`` and the ``slam-floor`` and
``slam-namo-*`` families. The truths they are held to: the C-space grid searched by Dijkstra
(pairs connected with the doors open, none round the closed doors), the source world resampled
(what was removed and what added), obstacle runs counted by a plain loop, and the simulator."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import ndimage

from curlnav.sim import NamoEnv
from curlnav.worlds.core.heldout import HeldOutSeedError, check_training_world
from curlnav.worlds.core.pairs import HUSKY_FOOTPRINT, check_pairs_possible, clearance_map, footprint_free
from curlnav.worlds.difficulty.metrics import inflate
from curlnav.worlds.difficulty.rank import CSPACE_RADIUS_M, world_paths
from curlnav.worlds.distribution import DistributionError, WorldDistribution, WorldDraws
from curlnav.worlds.families import generate
from curlnav.worlds.procedural.degrade import MAX_GAP, degrade, degrade_layers, obstacle_runs, wall_thickness
from curlnav.worlds.procedural.namo import door_segment, namo_auditorium, namo_indoor, namo_office, reachable
from curlnav.worlds.procedural.slam_like import SLAM_RESOLUTION, floor_plan

SOURCES = {"slam-floor": floor_plan, "slam-namo-office": namo_office, "slam-namo-indoor": namo_indoor,
           "slam-namo-auditorium": namo_auditorium}
SEED = 3
EIGHT = np.ones((3, 3), dtype=bool)


@pytest.fixture(scope="module")
def made():
    """family -> (source, the family's world of SEED, the layers of degrading the source)."""
    out = {}
    for family, make in SOURCES.items():
        source = make(SEED)
        resolution = None if source.resolution == SLAM_RESOLUTION else SLAM_RESOLUTION
        world, layers = degrade_layers(source, SEED, resolution=resolution)
        out[family] = (source, generate(family, SEED), world, layers)
    return out


@pytest.mark.parametrize("family", sorted(SOURCES))
def test_same_seed_gives_the_same_world_and_another_seed_another(family, made):
    _, world, degraded, _ = made[family]
    again = generate(family, SEED)
    assert np.array_equal(again.occupancy, world.occupancy) and np.array_equal(degraded.occupancy, world.occupancy)
    assert again.doors == world.doors and again.pairs == world.pairs and again.balls == world.balls
    assert world.name == f"{family}-{SEED}" and world.resolution == SLAM_RESOLUTION
    assert len(world.pairs) == 12 and len(world.balls) == 8 and world.doors
    other = generate(family, SEED + 1)
    assert other.occupancy.shape != world.occupancy.shape or not np.array_equal(other.occupancy, world.occupancy)


@pytest.mark.parametrize("family", sorted(SOURCES))
def test_every_pair_is_connected_with_the_doors_open_and_has_no_way_round_them_closed(family, made):
    source, world, _, _ = made[family]
    world_paths(world)  # the 0.15 m C-space grid of the metrics, the balls and levels: raises on a lost pair
    for pair in world.pairs:
        assert reachable(world, pair), f"{world.name} {pair.name}: disconnected on the C-space grid"
        if not reachable(source, pair, doors_closed=True):
            assert not reachable(world, pair, doors_closed=True), f"{world.name} {pair.name}: a way round the doors"


@pytest.mark.parametrize("family", sorted(SOURCES))
def test_balls_doors_starts_and_goals_are_kept_clear(family, made):
    _, world, _, layers = made[family]
    clearance = clearance_map(world)
    for ball in world.balls:
        assert clearance[world.cell_of(ball.x, ball.y)] >= ball.radius, f"{world.name}: a ball in a wall"
    rows, cols = world.occupancy.shape
    centres = np.stack(np.meshgrid((np.arange(cols) + 0.5) * world.resolution,
                                   (np.arange(rows) + 0.5) * world.resolution), axis=-1)
    new = world.occupancy & ~layers.source
    for door in world.doors:
        hinge, tip = door_segment(door)
        for t in np.linspace(0.05, 0.95, 19):  # the closed panel's line lies in a free doorway
            assert not world.is_occupied(*(hinge + t * (tip - hinge))), f"{world.name}: a door panel in a wall"
        dx, dy = (centres - hinge).transpose(2, 0, 1)
        turn = (np.arctan2(dy, dx) - door.closed_angle) * (1 if door.swing == "left" else -1)
        swing = (np.hypot(dx, dy) <= door.width + 0.05) & (np.mod(turn + 0.1, 2 * np.pi) <= door.max_open + 0.2)
        assert not (new & swing).any(), f"{world.name}: something added where a door swings"
    for pair in world.pairs:
        assert footprint_free(world, pair.x, pair.y, pair.yaw, *HUSKY_FOOTPRINT, margin=0.1), pair.name
        assert not world.is_occupied(pair.gx, pair.gy)


def test_obstacle_runs_match_a_plain_loop():
    grid = np.random.default_rng(0).random((23, 31)) < 0.55
    length, index, bounded = obstacle_runs(grid, 1)
    for r in range(grid.shape[0]):
        c = 0
        while c < grid.shape[1]:
            if not grid[r, c]:
                assert length[r, c] == 0 and not bounded[r, c]
                c += 1
                continue
            end = c
            while end + 1 < grid.shape[1] and grid[r, end + 1]:
                end += 1
            for k in range(c, end + 1):
                assert (length[r, k], index[r, k], bounded[r, k]) == (end - c + 1, k - c, c > 0 and end < grid.shape[1] - 1)
            c = end + 1
    assert np.array_equal(obstacle_runs(grid, 0)[0], obstacle_runs(grid.T, 1)[0].T)


def isolated(grid: np.ndarray) -> int:
    """Obstacle cells with no obstacle among their eight neighbours."""
    neighbours = ndimage.convolve(grid.astype(int), EIGHT.astype(int), mode="constant") - grid
    return int((grid & (neighbours == 0)).sum())


@pytest.mark.parametrize("family", sorted(SOURCES))
def test_walls_come_out_thinner_broken_speckled_and_bumpy(family, made):
    _, world, _, layers = made[family]
    source, grid, res = layers.source, world.occupancy, world.resolution
    before, after = wall_thickness(source, res), wall_thickness(grid, res)
    print(f"{family}: wall thickness median {np.median(before):.2f} -> {np.median(after):.2f} m, "
          f"isolated cells {isolated(source)} -> {isolated(grid)}")
    assert np.median(before) >= 0.15 and np.median(after) <= 0.1 + 1e-9
    assert np.mean(after <= 0.1 + 1e-9) > 0.8, "most wall sections are at most two cells thick"
    assert isolated(grid) >= isolated(source) + 15, "specks of noise"
    # holes split walls: the source's walls that are left fall into more pieces, each hole short
    assert ndimage.label(source & grid, EIGHT)[1] > ndimage.label(source, EIGHT)[1]
    holes, count = ndimage.label(layers.gaps, EIGHT)
    assert count >= 1
    for box in ndimage.find_objects(holes):
        assert min(s.stop - s.start for s in box) * res <= MAX_GAP + 1e-9, "a hole a robot or a ball could pass"
    new = grid & ~source
    touching = new & ndimage.binary_dilation(source & grid)
    assert touching.sum() >= 50, "bumps along the walls"


@pytest.mark.parametrize("family", sorted(SOURCES))
def test_unknown_cells_are_obstacles_where_no_robot_can_go(family, made):
    source, world, _, layers = made[family]
    assert layers.unknown.any() and not (layers.unknown & ~world.occupancy).any()
    assert (layers.values(world.occupancy) == -1).sum() == layers.unknown.sum()
    # where a robot can be: free cells within its circumradius (0.6 m), through free space, of a
    # C-space cell reachable from a start
    fine = source.with_changes(occupancy=layers.source, resolution=world.resolution)
    cs = inflate(fine.occupancy, int(round(CSPACE_RADIUS_M / fine.resolution)))
    labels, _ = ndimage.label(~cs, EIGHT)
    reach = np.isin(labels, [labels[fine.cell_of(p.x, p.y)] for p in fine.pairs])
    body = ndimage.binary_dilation(reach, EIGHT, iterations=int(round(0.6 / fine.resolution)), mask=~fine.occupancy)
    solid = layers.source | layers.clutter | layers.bumps | layers.speckles  # the building and what stands in it
    assert not (layers.unknown & body & ~solid).any(), "unknown on floor a robot drives on"
    assert not (layers.voids & body).any()
    if family == "slam-floor":  # unmapped ground round the building, closed shafts
        assert (layers.unknown & ~layers.source).sum() * world.resolution ** 2 > 20.0


def test_generation_is_fast_enough_to_draw_worlds_in_training():
    for family in sorted(SOURCES):
        t0 = time.perf_counter()
        generate(family, 7)
        elapsed = time.perf_counter() - t0
        print(f"{family}:7 generated in {elapsed:.2f} s")
        assert elapsed < 10.0


def test_a_curriculum_distribution_over_slam_floors_parses_draws_and_keeps_held_out_seeds():
    spec = {"family": "slam-floor", "seeds": [0, 99], "params": {"speckle": [0.05, 0.2], "corridor_max": [1.8, 2.4],
                                                                   "broken": 0.2}, "every": 4}
    dist = WorldDistribution.from_spec(spec)
    assert WorldDistribution.parse(dist.key) == dist
    world = dist.world(5)
    assert world.resolution == SLAM_RESOLUTION and len(world.pairs) == 12
    drawn = WorldDraws(seed=0).resolve(dist.key)
    assert drawn.name.startswith("slam-floor-") and drawn.pairs
    assert WorldDistribution.parse("slam-namo-office:0-9(thin=0.05,clutter=0.0~0.05)").params_of(3)["thin"] == 0.05
    with pytest.raises(DistributionError, match="held-out"):
        WorldDistribution.from_spec({**spec, "seeds": [0, 100]})
    with pytest.raises(DistributionError, match="no parameter"):
        WorldDistribution.from_spec({**spec, "params": {"sparkle": 1.0}})
    for name in ("slam-floor:100", "slam-namo-indoor:300"):
        with pytest.raises(HeldOutSeedError):
            check_training_world(name)


def test_the_simulator_loads_and_steps_a_degraded_world(made):
    _, world, _, _ = made["slam-namo-office"]
    env = NamoEnv(world)
    try:
        obs, _ = env.reset(seed=0, options={"pair": "p1"})
        for _ in range(20):
            obs, _, terminated, truncated, _ = env.step(np.array([0.6, 0.1, 0.0], dtype=np.float32))
            assert np.isfinite(obs).all()
            if terminated or truncated:
                break
        assert env.scene.static_segments_in_physics == len(env.scene.static_segments)
    finally:
        env.close()


def test_any_world_degrades_a_t_maze_and_a_map_of_random_pairs():
    t_maze = generate("t-maze-doors", 3)
    degraded = degrade(t_maze, 3, resolution=0.05)
    for pair in degraded.pairs:
        assert reachable(degraded, pair) and not reachable(degraded, pair, doors_closed=True)
    barn = degrade(generate("barn-3x3", 0), 0)
    assert barn.random_pairs is not None and check_pairs_possible(barn) is not None


def test_bad_parameters_are_refused_in_one_line():
    world = namo_office(0)
    for params, match in (({"resolution": 0.3}, "resolution"), ({"thin": -1.0}, "thin"),
                          ({"unknown": 2.0}, "unknown")):
        with pytest.raises(ValueError, match=match):
            degrade(world, 0, **params)
    with pytest.raises(ValueError, match="bad parameters for slam-floor"):
        generate("slam-floor", 0, sparkle=1.0)
    with pytest.raises(ValueError, match="door_min"):
        generate("slam-floor", 0, door_min=0.6)
