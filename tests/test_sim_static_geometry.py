"""Every wall is in the physics and in the LiDAR, on every world family and on a large SLAM-like map.

Truth here is the occupancy grid itself, read by a brute-force ray cast written in this file
(each beam against every obstacle cell in range, no grid traversal), and PyBullet's own ray
test on the scene's bodies. A scene that loses walls (PyBullet keeps only 16 shapes of a compound) fails both.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from curlnav.sim import scene as scene_module
from curlnav.sim.config import EnvConfig
from curlnav.sim.env import NamoEnv
from curlnav.sim.geometry import face_segments, merge_cells_into_rectangles, wall_faces
from curlnav.sim.scene import GROUP_STATIC, RAY_MASK, Scene, StaticGeometryError
from curlnav.worlds.builtin import get_world
from curlnav.worlds.core.pairs import footprint_free
from curlnav.worlds.core.world import RandomPairs, StartGoal, World
from curlnav.worlds.families import FAMILIES, generate

CFG = EnvConfig()
POSES_PER_WORLD = 12
LIDAR_TOLERANCE = 0.01  # m; the LiDAR's static part is exact, up to float rounding
FAMILY_NAMES = sorted(FAMILIES)
BUILTIN_NAMES = ["open-room", "door-corridor", "bench-36m"]


def _world(spec: str) -> World:
    if spec in BUILTIN_NAMES:
        return get_world(spec)
    if spec.startswith("rotated:"):  # barn-3x3-0's grid turned by a ROS-style origin yaw
        yaw = float(spec.split(":")[1])
        base = generate("barn-3x3", 0)
        return base.with_changes(name=f"barn-3x3-0-yaw{yaw}", origin=(3.0, -2.0), origin_yaw=yaw, pairs=(), balls=(),
                                 ball_regions=(), random_pairs=RandomPairs(min_distance=8.0))
    return generate(spec, 0)


WORLDS = FAMILY_NAMES + BUILTIN_NAMES + ["rotated:3.14", "rotated:-1.57"]


@pytest.fixture(scope="module")
def large_map() -> World:
    world = generate("slam-office", 0)
    assert world.size[0] >= 90 and world.size[1] >= 70 and world.resolution == 0.05
    assert len(merge_cells_into_rectangles(world.occupancy)) > 5000, "the large map must be thousands of rectangles"
    return world


def _exact_first_hits(world: World, x: float, y: float, angles: np.ndarray, max_range: float,
                      grow: float = 0.0) -> np.ndarray:
    """Brute force: the distance (m) along each beam to the nearest obstacle cell (each grown by
    ``grow`` m on every side), by a slab test of the beam against *every* obstacle cell within
    range (and the solid ring around the map), no grid traversal; ``max_range`` where none is
    nearer."""
    res = world.resolution
    rows, cols = world.occupancy.shape
    u, v = world.grid_from_map(x, y)
    reach = max_range + 2 * res
    r0, r1 = max(int((v - reach) // res), 0), min(int((v + reach) // res) + 1, rows)
    c0, c1 = max(int((u - reach) // res), 0), min(int((u + reach) // res) + 1, cols)
    iy, ix = np.nonzero(world.occupancy[r0:r1, c0:c1])
    lo = np.column_stack([(ix + c0) * res, (iy + r0) * res]) - grow
    hi = lo + res + 2 * grow
    big = 1e6  # the solid region outside the map, as four boxes
    width, height = world.size
    lo = np.vstack([lo, [[-big, -big], [-big, height], [-big, -big], [width, -big]]])
    hi = np.vstack([hi, [[big, 0.0], [big, big], [0.0, big], [big, big]]])
    a = angles - world.origin_yaw
    d = np.column_stack([np.cos(a), np.sin(a)])
    best = np.full(len(angles), max_range)
    with np.errstate(divide="ignore", invalid="ignore"):
        for start in range(0, len(lo), 4096):
            t_near = np.full((len(angles), len(lo[start:start + 4096])), -np.inf)
            t_far = np.full_like(t_near, np.inf)
            for axis, origin in ((0, u), (1, v)):
                da = d[:, axis:axis + 1]
                t1 = (lo[start:start + 4096, axis][None, :] - origin) / da
                t2 = (hi[start:start + 4096, axis][None, :] - origin) / da
                parallel = da == 0
                inside = (lo[start:start + 4096, axis] <= origin) & (origin <= hi[start:start + 4096, axis])
                t1 = np.where(parallel, np.where(inside, -np.inf, np.inf), t1)
                t2 = np.where(parallel, np.where(inside, np.inf, -np.inf), t2)
                t_near = np.maximum(t_near, np.minimum(t1, t2))
                t_far = np.minimum(t_far, np.maximum(t1, t2))
            hit = (t_near <= t_far) & (t_far >= 0)
            t_hit = np.where(hit, np.maximum(t_near, 0.0), np.inf)
            best = np.minimum(best, t_hit.min(axis=1))
    return best


GRAZE = 1e-5  # rad; a beam that grazes a cell's corner may count as a hit or a miss either way
# m; Bullet's ray-triangle test takes hits up to 1e-4 x a face's size beyond its edges
# (btTriangleRaycastCallback's edge tolerance): 0.6 mm past the end of a 6 m wall face
BULLET_EDGE_SLACK = 2e-3


def _disagreements(ranges: np.ndarray, exact: np.ndarray, check: np.ndarray, tolerance: float) -> list[str]:
    """``exact``: shape ``(k, beams)``, the truth for each beam, for it turned by -GRAZE and
    +GRAZE (and, for Bullet's rays, with the cells grown by its edge slack); a range agrees when
    it is within ``tolerance`` of any of them."""
    bad = check & (np.abs(ranges[None, :] - exact) > tolerance).all(axis=0)
    return [f"beam {k}: range {ranges[k]:.3f} m, the grid's first obstacle at {exact[0, k]:.3f} m"
            for k in np.flatnonzero(bad)]


def _random_free_poses(world: World, count: int, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    free = np.argwhere(~world.occupancy)
    poses = []
    for iy, ix in free[rng.choice(len(free), size=count, replace=False)]:
        u = (ix + rng.uniform(0.05, 0.95)) * world.resolution
        v = (iy + rng.uniform(0.05, 0.95)) * world.resolution
        x, y = world.map_from_grid(u, v)
        poses.append((float(x), float(y), float(rng.uniform(-math.pi, math.pi))))
    return poses


def _check_world_lidar_and_physics(world: World) -> None:
    scene = Scene(world, CFG)
    try:
        assert scene.static_segments_in_physics == len(scene.static_segments) > 0
        rng = np.random.default_rng(7)
        max_range = CFG.lidar_max_range
        lidar_problems, physics_problems = [], []
        for x, y, yaw in _random_free_poses(world, POSES_PER_WORLD, rng):
            # balls stay where the file puts them; a beam that first meets one is not a static beam
            scene.reset((x, y, yaw), [(b.x, b.y) for b in world.balls])
            ranges, labels, _ = scene.scan(x, y, yaw)
            angles = yaw + scene.beam_angles
            exact = np.stack([_exact_first_hits(world, x, y, angles + turn, max_range) for turn in (0, -GRAZE, GRAZE)])
            lidar_problems += [f"pose ({x:.2f}, {y:.2f}, {yaw:.2f}) {p}" for p in
                               _disagreements(ranges, exact, labels == 0, LIDAR_TOLERANCE)]
            # PyBullet's ray test against the wall bodies alone: the physics holds every wall
            starts = np.column_stack([np.full(len(angles), x), np.full(len(angles), y),
                                      np.full(len(angles), CFG.lidar_height)])
            ends = starts.copy()
            ends[:, 0] += max_range * np.cos(angles)
            ends[:, 1] += max_range * np.sin(angles)
            hits = pb.rayTestBatch(starts, ends, collisionFilterMask=GROUP_STATIC, physicsClientId=scene.client)
            bullet = np.array([h[2] if h[0] >= 0 else 1.0 for h in hits]) * max_range
            slack = exact[0].copy()  # the truth with Bullet's edge slack, for the beams that need it
            off = (np.abs(bullet[None, :] - exact) > world.resolution).all(axis=0)
            slack[off] = _exact_first_hits(world, x, y, angles[off], max_range, grow=BULLET_EDGE_SLACK)
            physics_problems += [f"pose ({x:.2f}, {y:.2f}, {yaw:.2f}) {p}" for p in
                                 _disagreements(bullet, np.vstack([exact, slack]), np.ones(len(angles), bool),
                                                world.resolution)]
        assert not lidar_problems, (f"{world.name}: {len(lidar_problems)} static LiDAR beams disagree with the grid, "
                                    f"e.g. {lidar_problems[:3]}")
        assert not physics_problems, (f"{world.name}: {len(physics_problems)} PyBullet rays on the wall bodies "
                                      f"disagree with the grid (walls missing from the physics), e.g. {physics_problems[:3]}")
    finally:
        scene.close()


@pytest.mark.parametrize("spec", WORLDS)
def test_every_static_lidar_beam_and_every_wall_in_physics_match_the_grid(spec):
    _check_world_lidar_and_physics(_world(spec))


def test_every_static_beam_matches_the_grid_on_a_large_slam_like_map(large_map):
    _check_world_lidar_and_physics(large_map)


def _drive_into_walls(world: World, places: int, seed: int = 3) -> None:
    """From random free spots near a wall face, facing it, drive full speed: the base must
    register a wall collision and its centre must never enter an obstacle cell."""
    env = NamoEnv(world, CFG.replace(end_on_base_collision=False))
    robot = CFG.robot
    rng = np.random.default_rng(seed)
    horizontal, vertical = wall_faces(world.occupancy)
    rows, cols = world.occupancy.shape
    segments = face_segments(horizontal, vertical, 0, 0, rows + 1, cols + 1)
    res = world.resolution
    tried = 0
    try:
        for index in rng.permutation(len(segments)):
            if tried == places:
                break
            x0, y0, x1, y1 = segments[index].astype(float) * res
            mu, mv = (x0 + x1) / 2, (y0 + y1) / 2
            normal = np.array([0.0, 1.0]) if y0 == y1 else np.array([1.0, 0.0])
            for side in (1.0, -1.0):  # the free side of the face
                n = side * normal
                probe_u, probe_v = mu + n[0] * res / 2, mv + n[1] * res / 2
                iy, ix = int(probe_v // res), int(probe_u // res)
                if 0 <= iy < rows and 0 <= ix < cols and not world.occupancy[iy, ix]:
                    break
            else:
                continue
            back = robot.base_length / 2 + 0.25
            su, sv = mu + n[0] * back, mv + n[1] * back
            x, y = world.map_from_grid(su, sv)
            yaw = math.atan2(-n[1], -n[0]) + world.origin_yaw
            if not footprint_free(world, x, y, yaw, robot.base_length, robot.base_width, margin=0.05):
                continue
            tried += 1
            env.reset(seed=int(index), options={"pair": StartGoal("wall", x, y, yaw, x, y + 100.0)})
            collided = False
            for _ in range(12):
                _, _, _, _, info = env.step([1.0, 0.0, 0.0])
                px, py, _ = info["pose"]
                assert not world.is_occupied(px, py), (
                    f"{world.name}: the base's centre drove into a wall at ({px:.2f}, {py:.2f}) from ({x:.2f}, {y:.2f})")
                if info["base_collisions"] > 0:
                    collided = True
                    break
            assert collided, (f"{world.name}: driving from ({x:.2f}, {y:.2f}) at yaw {yaw:.2f} into the wall face "
                              f"0.25 m ahead registered no base collision")
        assert tried == places, f"{world.name}: found only {tried} places to drive into a wall"
    finally:
        env.close()


@pytest.mark.parametrize("spec", WORLDS)
def test_driving_the_base_into_walls_registers_base_collisions(spec):
    _drive_into_walls(_world(spec), places=4)


def test_driving_into_walls_of_the_large_map_registers_base_collisions(large_map):
    _drive_into_walls(large_map, places=6)


def test_wall_segments_cover_every_face_of_the_grid_once(large_map):
    """The mesh segments, drawn back onto the cell edges, are exactly the grid's wall faces."""
    occupancy = large_map.occupancy[:400, :500]
    horizontal, vertical = wall_faces(occupancy)
    rows, cols = occupancy.shape
    got_h = np.zeros(horizontal.shape, int)
    got_v = np.zeros(vertical.shape, int)
    for r0 in range(0, rows, 128):  # blocks as the scene makes them, the last owning the far edge
        for c0 in range(0, cols, 128):
            r1 = r0 + 128 if r0 + 128 < rows else rows + 1
            c1 = c0 + 128 if c0 + 128 < cols else cols + 1
            for x0, y0, x1, y1 in face_segments(horizontal, vertical, r0, c0, r1, c1):
                if y0 == y1:
                    got_h[y0, x0:x1] += 1
                else:
                    got_v[y0:y1, x0] += 1
    assert np.array_equal(got_h, horizontal.astype(int))
    assert np.array_equal(got_v, vertical.astype(int))


def test_a_wall_mesh_pybullet_refuses_stops_the_build_with_one_line_naming_the_limit(large_map, monkeypatch):
    monkeypatch.setattr(scene_module, "STATIC_TILE_CELLS", 10 ** 6)
    monkeypatch.setattr(scene_module, "MAX_SEGMENTS_PER_MESH", 10 ** 9)
    with pytest.raises(StaticGeometryError, match=r"PyBullet refused a wall mesh of \d+ vertices") as caught:
        Scene(large_map, CFG).close()
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("spec", ["t-maze", "barn-3x3"])
def test_movable_beams_agree_with_pybullet_after_objects_were_pushed(spec):
    """Balls and door panels, after random driving has pushed them: ranges within 3 cm of
    PyBullet's ray test on the same scene, and the same movable labels (grazing beams aside)."""
    world = _world(spec)
    env = NamoEnv(world, CFG.replace(end_on_base_collision=False))
    rng = np.random.default_rng(1)
    compared = mismatched = movable_beams = 0
    try:
        for episode in range(3):
            env.reset(seed=episode)
            for _ in range(40):
                env.step([rng.uniform(0.5, 1.0), rng.uniform(-0.6, 0.6), rng.uniform(0, 1)])
                scene = env.scene
                x, y, yaw = env._pose
                ranges, labels, _ = scene.scan(x, y, yaw)
                angles = yaw + scene.beam_angles
                starts = np.column_stack([np.full(len(angles), x), np.full(len(angles), y),
                                          np.full(len(angles), CFG.lidar_height)])
                ends = starts.copy()
                ends[:, 0] += CFG.lidar_max_range * np.cos(angles)
                ends[:, 1] += CFG.lidar_max_range * np.sin(angles)
                hits = pb.rayTestBatch(starts, ends, collisionFilterMask=RAY_MASK, physicsClientId=scene.client)
                bullet = np.array([h[2] if h[0] >= 0 else 1.0 for h in hits]) * CFG.lidar_max_range
                bullet_labels = np.array([1.0 if h[0] in scene.movable_set else 0.0 for h in hits])
                bad = (np.abs(bullet - ranges) > 0.03) | (bullet_labels != labels)
                compared += len(angles)
                mismatched += int(bad.sum())
                movable_beams += int(labels.sum())
    finally:
        env.close()
    assert movable_beams > 100, "the drives should have seen movable objects"
    assert mismatched <= 0.005 * compared, f"{mismatched} of {compared} beams disagree with PyBullet's ray test"


def test_building_world_after_world_keeps_no_memory_behind():
    """An actor draws a new world every few episodes for hours: each build's wall meshes must not
    leave memory behind (PyBullet 3.2.7 keeps the vertex lists it is given; ``_MeshArguments``).
    Python allocations over 12 ``barn-course`` scenes built and closed one after another."""
    import gc
    import tracemalloc

    from curlnav.worlds.barn_challenge.barn_course import barn_course

    env = NamoEnv(barn_course(0), CFG)
    try:
        for seed in range(1, 4):  # warm-up: the reused lists reach their size
            env.set_world(barn_course(seed))
            env.reset(seed=seed)
        gc.collect()
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        meshes = 0
        for seed in range(4, 16):
            env.set_world(barn_course(seed))
            env.reset(seed=seed)
            meshes += env.scene.static_mesh_count
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
    finally:
        env.close()
    assert meshes >= 12
    assert grown < 1.5e6, f"12 worlds left {grown / 1e6:.1f} MB behind ({meshes} wall meshes built)"
