"""Sensor errors that persist for an episode (``curlnav.sim.lidar_faults``), by what a user would
see: a wall block or an object errs the same way at every step and from every pose, glass returns
only head-on, a dark surface never, a phantom reads short by the same distance, a LiDAR mounted
off turns the whole scan, the extended arm hides the beams behind it; the frame-by-frame presets
are today's, draw for draw."""

from __future__ import annotations

import math

import numpy as np

from curlnav.sim import EnvConfig, NamoEnv, StartGoal, World
from curlnav.sim.config import PERSISTENT_FIELDS, SENSOR_NOISE_PRESETS, SensorNoiseConfig
from curlnav.sim.controllers import GoalSeekingController
from curlnav.sim.lidar_faults import BLOCK_M, GLASS_RETURN_ANGLE, PHANTOM_OFFSET_M
from curlnav.worlds.builtin import _walled_grid

OFFICE = "namo-office:3"


def only(**values) -> SensorNoiseConfig:
    """Exact senses but for these persistent errors."""
    return SensorNoiseConfig("none", **values)


def long_wall_room() -> World:
    """A 20 m x 8 m room; the robot at (12, 2) facing +x, the long wall y = 0 to its right."""
    res = 0.05
    grid = _walled_grid(20.0, 8.0, res)
    return World(name="long-wall", occupancy=grid, resolution=res, wall_height=1.0,
                 pairs=(StartGoal("p", 12.0, 2.0, 0.0, 18.0, 2.0),), source="test:long-wall")


def newest(env: NamoEnv, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cfg = env.config
    b = cfg.lidar_beams
    return (obs[(cfg.range_frames - 1) * b:cfg.range_frames * b],
            obs[(cfg.range_frames + cfg.label_frames - 1) * b:(cfg.range_frames + cfg.label_frames) * b])


def episode(env: NamoEnv, steps: int, seed: int = 7):
    """Reset with ``seed``, drive the goal-seeking controller; yields (seen ranges, seen labels,
    true ranges, true labels, hits, bodies, pose) each step."""
    obs, info = env.reset(seed=seed)
    controller = GoalSeekingController(env.config)
    for _ in range(steps):
        obs, _, terminated, truncated, info = env.step(controller.act(obs))
        x, y, yaw = info["pose"]
        ranges, labels, hits = env.scene.scan(x, y, yaw)
        yield (*newest(env, obs), ranges, labels, hits, env.scene.last_bodies.copy(), (x, y, yaw))
        if terminated or truncated:
            return


def blocks_of(hits: np.ndarray, pose) -> np.ndarray:
    direction = hits - np.asarray(pose[:2])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return np.floor((hits + 0.01 * direction) / BLOCK_M).astype(int)


def test_the_frame_presets_are_the_presets_of_before_and_draw_nothing_more(make_env):
    for name in ("realistic", "harsh"):
        frame = SensorNoiseConfig(f"{name}-frame")
        assert all(getattr(frame, f) == 0 for f in PERSISTENT_FIELDS)
        assert all(getattr(SensorNoiseConfig(name), f) > 0 for f in PERSISTENT_FIELDS)
        persistent_off = SensorNoiseConfig(name, **dict.fromkeys(PERSISTENT_FIELDS, 0.0))
        a, b = make_env(noise=frame), make_env(noise=persistent_off)
        for one, other in zip(episode(a, 20), episode(b, 20)):
            assert np.array_equal(one[0], other[0]) and np.array_equal(one[1], other[1])


def test_a_mislabelled_wall_block_is_labelled_movable_at_every_step_from_every_pose(make_env):
    env = make_env(noise=only(block_label_error=0.3))
    shares = []
    for seed in (7, 8, 9, 10):
        verdicts: dict[tuple, set] = {}
        for seen_r, seen_l, ranges, labels, hits, bodies, pose in episode(env, 60, seed):
            static = (ranges < env.config.lidar_max_range) & (bodies < 0)
            assert np.array_equal(seen_r, ranges)  # labels only
            for block, label in zip(map(tuple, blocks_of(hits[static], pose)), seen_l[static]):
                verdicts.setdefault(block, set()).add(float(label))
        assert all(len(v) == 1 for v in verdicts.values())  # never one way here and another there
        shares += [v == {1.0} for v in verdicts.values()]
    assert len(shares) > 100
    assert 0.2 < np.mean(shares) < 0.4, np.mean(shares)


def test_a_missed_object_is_labelled_static_for_the_whole_episode(make_env):
    env = make_env(noise=only(object_label_error=0.5))
    verdicts = []
    for seed in range(6):
        seen_by_body: dict[int, set] = {}
        for _, seen_l, ranges, labels, hits, bodies, pose in episode(env, 80, seed):
            for body, label in zip(bodies[bodies >= 0], seen_l[bodies >= 0]):
                seen_by_body.setdefault(int(body), set()).add(float(label))
        assert all(len(v) == 1 for v in seen_by_body.values())
        verdicts += list(seen_by_body.values())
    assert len(verdicts) >= 6 and {0.0} in verdicts and {1.0} in verdicts


def test_a_dark_surface_returns_nothing_and_glass_returns_only_near_its_normal(make_env):
    world = long_wall_room()
    dark = make_env(world, only(dark_blocks=1.0))
    obs, _ = dark.reset(seed=0)
    ranges, _ = newest(dark, obs)
    assert np.all(ranges >= dark.config.lidar_max_range - 1e-6)
    glass = make_env(world, only(glass_blocks=1.0))
    obs, _ = glass.reset(seed=0)
    ranges, _ = newest(glass, obs)
    true, _, _ = glass.scene.scan(12.0, 2.0, 0.0)
    angles = glass.scene.beam_angles
    # the wall y = 0 (its face at y = 0.05): a beam at angle a from +x meets it at incidence |a + 90 deg|
    toward = (true < 9.99) & (np.abs(angles + math.pi / 2) < math.radians(60))
    head_on = toward & (np.abs(angles + math.pi / 2) < GLASS_RETURN_ANGLE - math.radians(3))
    grazing = toward & (np.abs(angles + math.pi / 2) > GLASS_RETURN_ANGLE + math.radians(3))
    assert head_on.sum() >= 20 and grazing.sum() >= 20
    assert np.allclose(ranges[head_on], true[head_on])
    assert np.all(ranges[grazing] >= glass.config.lidar_max_range - 1e-6)


def test_a_phantom_surface_reads_short_by_the_same_distance_at_every_step(make_env):
    env = make_env(noise=only(phantom_blocks=1.0))
    offsets: dict[tuple, set] = {}
    for seen_r, seen_l, ranges, labels, hits, bodies, pose in episode(env, 30):
        static = (ranges < env.config.lidar_max_range) & (bodies < 0) & (ranges > 1.2)
        short = ranges[static] - seen_r[static]
        assert np.all(short >= PHANTOM_OFFSET_M[0] - 1e-4) and np.all(short <= PHANTOM_OFFSET_M[1] + 1e-4)
        assert np.all(seen_l[static] == 0)
        for block, d in zip(map(tuple, blocks_of(hits[static], pose)), np.round(short, 3)):
            offsets.setdefault(block, set()).add(float(d))
    assert all(len(v) == 1 for v in offsets.values())


def test_a_lidar_mounted_off_turns_every_scan_by_its_yaw(make_env):
    env = make_env(noise=only(mount_yaw=0.05))
    obs, info = env.reset(seed=3)
    yaw_error, _ = env.sensors.mount
    assert yaw_error != 0
    x, y, yaw = info["pose"] if "pose" in info else env._pose
    ranges, _ = newest(env, obs)
    turned, _, _ = env.scene.scan(x, y, yaw + yaw_error, env.config.lidar_height + env.sensors.mount[1])
    straight, _, _ = env.scene.scan(x, y, yaw)
    assert np.allclose(ranges, turned) and not np.allclose(ranges, straight)


def test_the_extended_arm_hides_the_beams_straight_ahead_and_the_retracted_arm_none(make_env):
    env = make_env(long_wall_room(), only(arm_occlusion=1.0))
    env.reset(seed=0)
    robot = env.config.robot
    ahead = np.abs(env.scene.beam_angles) <= math.atan2(robot.arm_width / 2, robot.base_length / 2)
    assert 5 <= ahead.sum() <= 15
    obs, *_ = env.step(np.array([0.0, 0.0, 0.0], np.float32))
    ranges, _ = newest(env, obs)
    assert np.all(ranges[ahead] < 8.5)  # the wall 7.95 m ahead
    for _ in range(5):
        obs, *_ = env.step(np.array([0.0, 0.0, 1.0], np.float32))
    ranges, _ = newest(env, obs)
    assert np.all(ranges[ahead] >= env.config.lidar_max_range - 1e-6)
    assert np.all(ranges[~ahead] < env.config.lidar_max_range)
    jackal = make_env(long_wall_room(), SensorNoiseConfig("realistic"), robot=EnvConfig().robot.jackal())
    assert not jackal.reset(seed=0) or not jackal.sensors.faults.arm_beams.any()  # no arm, nothing hidden


def test_the_same_seed_gives_the_same_persistent_errors_and_another_seed_others(make_env):
    env = make_env(noise=SensorNoiseConfig("harsh"))
    first = [s[1].copy() for s in episode(env, 10, seed=4)]
    again = [s[1].copy() for s in episode(env, 10, seed=4)]
    other = [s[1].copy() for s in episode(env, 10, seed=5)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other))


def test_realistic_and_harsh_include_the_persistent_errors_harsh_about_double():
    realistic, harsh = SENSOR_NOISE_PRESETS["realistic"], SENSOR_NOISE_PRESETS["harsh"]
    for name in PERSISTENT_FIELDS:
        assert realistic[name] > 0
        if name != "arm_occlusion":  # the whole arm in both
            assert harsh[name] >= 1.5 * realistic[name], name
