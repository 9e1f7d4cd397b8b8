"""The NAMO simulator, by behaviour a user would see."""

from __future__ import annotations

import math

import numpy as np
import pytest

from curlnav.sim import Ball, EnvConfig, NamoEnv, StartGoal, World, WorldError
from curlnav.worlds.builtin import _walled_grid


def room_world(balls=(), pairs=None, size=10.0) -> World:
    """A walled square room (0.1 m cells); walls occupy the outer 0.1 m."""
    pairs = pairs or (StartGoal("east", 2.0, 5.0, 0.0, 9.0, 5.0),)
    return World(name="test-room", occupancy=_walled_grid(size, size, 0.1), resolution=0.1,
                 balls=tuple(balls), pairs=tuple(pairs))


@pytest.fixture
def make_env():
    envs = []

    def make(world, **cfg):
        env = NamoEnv(world, EnvConfig(**cfg))
        envs.append(env)
        return env

    yield make
    for env in envs:
        env.close()


def test_end_effector_pushes_a_ball_out_of_the_way(make_env):
    env = make_env(room_world(balls=[Ball(4.0, 5.0, radius=0.25, mass=0.5)]))
    env.reset(seed=0)
    before = env.scene.ball_positions()[0]
    pushed = False
    for _ in range(15):
        _, _, _, _, info = env.step([0.5, 0.0, 1.0])
        pushed |= info["contacts"].end_effector_movable
    after = env.scene.ball_positions()[0]
    assert pushed, "the extended end effector never touched the ball in its path"
    assert after[0] - before[0] > 0.3, f"ball barely moved: {before} -> {after}"
    assert info["base_collisions"] == 0 and info["end_effector_collisions"] == 0


def test_door_swings_open_and_the_robot_passes(make_env):
    env = make_env("door-corridor")
    env.reset(seed=0, options={"pair": "through-door"})
    assert env.scene.door_angles() == [0.0]
    max_opening = 0.0
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step([0.5, 0.0, 1.0])
        max_opening = max(max_opening, abs(env.scene.door_angles()[0]))
        if terminated or truncated:
            break
    assert max_opening > math.radians(45), f"door opened only {math.degrees(max_opening):.0f} deg"
    assert info["is_success"] and terminated
    assert info["pose"][0] > 9.0
    assert info["base_collisions"] == 0


def test_base_into_wall_is_counted_and_penalised_minus_10(make_env):
    # Start 1.0 m from the east wall's face, facing it, arm retracted.
    env = make_env(room_world(pairs=[StartGoal("wall", 8.9, 5.0, 0.0, 2.0, 5.0)]))
    env.reset(seed=0)
    for _ in range(10):
        _, reward, terminated, _, info = env.step([1.0, 0.0, 0.0])
        if terminated:
            break
    assert terminated and not info["is_success"], "a base collision ends a training episode"
    assert info["base_collisions"] == 1
    assert info["reward_terms"]["base_collision"] == -10.0
    assert reward == pytest.approx(sum(info["reward_terms"].values()))


def test_evaluation_mode_counts_base_collisions_and_goes_on(make_env):
    env = make_env(room_world(pairs=[StartGoal("wall", 8.9, 5.0, 0.0, 2.0, 5.0)]), end_on_base_collision=False)
    env.reset(seed=0)
    for _ in range(10):
        _, _, terminated, _, info = env.step([1.0, 0.0, 0.0])
        assert not terminated
    assert info["base_collisions"] >= 5
    assert info["base_collision_events"] == 1, "pressing on the wall for several steps is one collision"
    # turn round (pi rad at 1 rad/s), drive 1.2 m away, turn back and drive into it again
    for action in [[0.0, 1.0, 0.0]] * 16 + [[1.0, 0.0, 0.0]] * 6 + [[0.0, 1.0, 0.0]] * 16:
        _, _, _, _, info = env.step(action)
    assert info["base_collision_events"] == 1
    for _ in range(12):
        _, _, _, _, info = env.step([1.0, 0.0, 0.0])
    assert info["base_collision_events"] == 2, "a second contact after leaving the wall is a second collision"


def test_end_effector_on_wall_is_penalised_minus_half(make_env):
    # Bumper 0.3 m from the wall face: the extended arm (0.5 m) reaches it, the base does not.
    env = make_env(room_world(pairs=[StartGoal("wall", 9.9 - 0.8, 5.0, 0.0, 2.0, 5.0)]))
    env.reset(seed=0)
    for _ in range(5):
        _, _, terminated, _, info = env.step([0.0, 0.0, 1.0])
    assert info["reward_terms"]["end_effector_collision"] == -0.5
    assert info["end_effector_collisions"] >= 1
    assert info["base_collisions"] == 0 and not terminated


def test_reaching_the_goal_terminates_with_plus_200(make_env):
    env = make_env(room_world(pairs=[StartGoal("short", 2.0, 5.0, 0.0, 3.5, 5.0)]))
    env.reset(seed=0)
    for _ in range(20):
        _, reward, terminated, truncated, info = env.step([1.0, 0.0, 0.0])
        if terminated:
            break
    assert terminated and info["is_success"]
    assert info["reward_terms"]["goal"] == 200.0
    assert info["distance_to_goal"] <= 0.8
    assert reward == pytest.approx(200.0 + 0.2 + 0.1)


def test_the_progress_reward_pays_the_distance_gained_so_a_loop_earns_nothing(make_env):
    """``reward.progress`` (BARN recipe): k per metre the goal came closer, k per metre it went
    away; over a drive out and back its sum is k times the net change of the true distance."""
    from curlnav.sim.config import RewardConfig

    env = make_env(room_world(pairs=[StartGoal("far", 2.0, 5.0, 0.0, 8.0, 5.0)]), reward=RewardConfig(progress=2.0))
    _, info = env.reset(seed=0)
    start = info["distance_to_goal"]
    terms = []
    for action in [[1.0, 0.0, 0.0]] * 4 + [[0.0, 1.0, 0.0]] * 16 + [[1.0, 0.0, 0.0]] * 4:  # out, turn round, back
        _, _, _, _, info = env.step(action)
        terms.append(info["reward_terms"]["progress"])
    assert max(terms) > 0.2 and min(terms) < -0.2  # paid going, charged coming back
    assert sum(terms) == pytest.approx(2.0 * (start - info["distance_to_goal"]), abs=1e-6)
    assert abs(start - info["distance_to_goal"]) < 1.0  # back near the start: little net pay
    assert make_env(room_world(), reward=RewardConfig()).config.reward.progress == 0.0  # the paper's reward by default


def test_episode_is_truncated_at_the_step_limit(make_env):
    env = make_env(room_world(), max_episode_steps=5)
    env.reset(seed=0)
    for _i in range(5):
        _, _, terminated, truncated, info = env.step([0.0, 0.0, 0.0])
    assert truncated and not terminated and not info["is_success"]
    # Standing still is "not moving" and "not heading toward the goal".
    assert info["reward_terms"]["moving"] == -0.1 and info["reward_terms"]["heading"] == -0.2


def test_lidar_reads_a_wall_at_a_known_distance_and_labels_a_ball(make_env):
    # Robot at x = 5 facing +x; east wall face at x = 9.9 -> 4.9 m on the centre beam.
    # A ball at (5, 7) with radius 0.5 lies at +90 deg: its surface is 1.5 m away.
    env = make_env(room_world(balls=[Ball(5.0, 7.0, radius=0.5, mass=0.5)],
                              pairs=[StartGoal("c", 5.0, 5.0, 0.0, 8.0, 8.0)]))
    obs, _ = env.reset(seed=0)
    cfg = env.config
    beams = cfg.lidar_beams
    ranges = obs[(cfg.range_frames - 1) * beams: cfg.range_frames * beams]
    labels = obs[(cfg.range_frames + cfg.label_frames - 1) * beams: (cfg.range_frames + cfg.label_frames) * beams]
    centre = beams // 2  # 0 deg
    left = centre + 90  # +90 deg (counter-clockwise, to the robot's left)
    assert ranges[centre] == pytest.approx(4.9, abs=0.02)
    assert labels[centre] == 0.0
    assert ranges[left] == pytest.approx(1.5, abs=0.02)
    assert labels[left] == 1.0
    assert ranges.max() <= cfg.lidar_max_range


def test_observation_layout_is_as_documented(make_env):
    env = make_env(room_world(pairs=[StartGoal("c", 5.0, 5.0, math.pi / 2, 5.0, 8.0)]))
    obs, _ = env.reset(seed=0)
    assert obs.shape == (4 * 241 + 4 * 241 + 10 * 3,) == env.observation_space.shape
    assert obs.dtype == np.float32
    goal_block = obs[8 * 241:].reshape(10, 3)
    # Goal 3 m straight ahead in the robot frame (robot faces +y, goal at +3 y).
    assert goal_block[-1] == pytest.approx([math.log1p(3.0), 0.0, 0.0], abs=1e-4)
    assert np.allclose(goal_block, goal_block[-1]), "reset fills every goal frame with the first reading"
    obs2, *_ = env.step([1.0, 0.0, 0.0])
    ranges = obs2[:4 * 241].reshape(4, 241)
    assert np.allclose(ranges[0], obs[:241]) and not np.allclose(ranges[-1], ranges[0]), "newest frame last"
    goals = obs2[8 * 241:].reshape(10, 3)
    assert goals[-1][0] < goals[-2][0], "newest goal frame is last and the goal got closer"


def test_same_seed_and_actions_give_the_same_trajectory(make_env):
    actions = np.random.default_rng(3).uniform([0, -1, 0], [1, 1, 1], size=(60, 3))

    def run(env):
        obs, _ = env.reset(seed=11)
        trace = [obs]
        for a in actions:
            obs, reward, terminated, truncated, info = env.step(a)
            trace.append(np.concatenate([obs, [reward]]))
            if terminated or truncated:
                break
        return np.concatenate(trace), [tuple(p) for p in env.scene.ball_positions()]

    first = make_env("open-room")
    a, balls_a = run(first)
    b, balls_b = run(make_env("open-room"))
    c, balls_c = run(first)  # the same env reset again
    assert np.array_equal(a, b) and balls_a == balls_b
    assert np.array_equal(a, c) and balls_a == balls_c


def test_reset_assigns_world_and_pair_by_name(make_env):
    env = make_env("open-room")
    _, info = env.reset(seed=0, options={"world": "door-corridor", "pair": "through-door"})
    assert info["world"] == "door-corridor" and info["pair"] == "through-door"
    assert info["pose"][:2] == pytest.approx((2.0, 2.0), abs=1e-6)
    _, info = env.reset(seed=0, options={"world": "open-room", "pair": 1})
    assert info["pair"] == "across"


def test_random_pairs_are_far_enough_apart_and_balls_move_between_resets(make_env):
    env = make_env("open-room")
    placements = set()
    for seed in range(5):
        _, info = env.reset(seed=seed)
        pair = env.pair
        assert pair.distance >= 4.0
        assert not env.world.is_occupied(pair.x, pair.y) and not env.world.is_occupied(pair.gx, pair.gy)
        placements.add(tuple(np.round(env.scene.ball_positions(), 3).ravel()))
    assert len(placements) == 5, "balls in a region are re-placed at random on every reset"


@pytest.mark.parametrize("action, message", [
    ([float("nan"), 0.0, 0.0], "NaN"),
    ([0.5, 1.5, 0.0], "out of range"),
    ([-0.6, 0.0, 0.0], "out of range"),  # the Husky backs up at 0.5 m/s at most
    ([0.5, 0.0], "shape"),
    ("fast", "action"),
])
def test_bad_actions_raise_a_clear_error(make_env, action, message):
    env = make_env(room_world())
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(action)


def test_unknown_world_and_pair_raise_clear_errors(make_env):
    with pytest.raises(WorldError, match="unknown world 'atlantis'"):
        NamoEnv("atlantis")
    env = make_env("open-room")
    with pytest.raises(KeyError, match="no pair 'p9'.*diagonal"):
        env.reset(options={"pair": "p9"})
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"wrld": "open-room"})


def test_an_impulse_from_the_solver_cannot_launch_the_base_faster_than_twice_its_top_speed(make_env):
    """A door squeezed between the base and its jamb once handed the base 90 m/s (Bullet's own cap
    is 100 m/s) and it flew through a floor's outer wall (session 10). The same kick, given here
    as an 80 m/s joint velocity, carries the base at most twice its top speed for the control
    period, not metres."""
    import pybullet as pb

    from curlnav.sim.scene import JOINT_X

    env = make_env(room_world(pairs=(StartGoal("middle", 5.0, 5.0, 0.0, 9.0, 5.0),), size=40.0))
    env.reset(seed=0)
    robot = env.config.robot
    x0 = env.scene.robot_pose()[0]
    pb.resetJointState(env.scene.robot, JOINT_X, x0, targetVelocity=80.0, physicsClientId=env.scene.client)
    env.step([0.0, 0.0, 0.0])
    moved = env.scene.robot_pose()[0] - x0
    assert 0.0 < moved <= 2.0 * robot.max_linear_speed * env.config.control_period + 1e-6


def test_a_robot_that_turns_slowly_still_drives_at_its_top_speed_under_the_joint_cap(make_env):
    """Bullet keeps one joint velocity cap per body: were it set from the turn rate (0.3 rad/s
    here), the base could not reach its 1 m/s. Full speed for 1 s covers about 1 m."""
    import dataclasses

    cfg = EnvConfig()
    slow_turner = dataclasses.replace(cfg.robot, max_angular_speed=0.3, arm_speed=0.2)
    env = make_env(room_world(pairs=(StartGoal("middle", 5.0, 5.0, 0.0, 9.0, 5.0),), size=40.0),
                   robot=slow_turner)
    env.reset(seed=0)
    x0 = env.scene.robot_pose()[0]
    for _ in range(5):
        env.step([1.0, 0.0, 0.0])
    assert env.scene.robot_pose()[0] - x0 == pytest.approx(1.0, abs=0.08)
