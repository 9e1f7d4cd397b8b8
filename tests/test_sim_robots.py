"""Robot profiles end to end (issue 38): ``robot: husky | jackal | FILE.yaml`` in the config, the
simulator, the artefact, ``curlnav eval`` and ``curlnav ros2 run``; an artefact refuses, in one line,
a robot it was not trained for."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_curlnav

from curlnav.config import (
    ConfigError,
    ExperimentConfig,
    apply_overrides,
    config_hash,
    config_to_yaml,
    load_config,
    resolve_config,
)
from curlnav.layout import ObservationLayout
from curlnav.sim import EnvConfig, NamoEnv
from curlnav.sim.robots import (
    PROFILES,
    check_observation,
    check_robot,
    load_profile,
    profile_of_env,
    recorded_robot,
    sensor_metadata,
)

PROFILE_FILE = """\
name: turtlebot4
base_length: 0.34
base_width: 0.34
base_mass: 3.3
max_linear_speed: 0.31
max_angular_speed: 1.9
arm: false
lidar: {beams: 361, fov_deg: 360, range_m: 12.0}
"""


@pytest.fixture(scope="module")
def jackal_artefact(tmp_path_factory) -> Path:
    """An untrained policy exported for the Jackal profile."""
    from curlnav.config import D4PGConfig
    from curlnav.learner.artefact import export_policy
    from curlnav.learner.d4pg import init_state

    env = PROFILES["jackal"].apply(EnvConfig())
    state = init_state(D4PGConfig(seed=2), ObservationLayout.from_env_config(env), "cpu")
    return export_policy(state, tmp_path_factory.mktemp("jackal") / "policy", env, worlds=["barn-course:0"])


def test_the_jackal_profile_has_clearpaths_figures_and_the_challenges_lidar():
    jackal = PROFILES["jackal"]
    r = jackal.robot
    assert (r.name, r.base_length, r.base_width, r.base_height, r.base_mass) == ("jackal", 0.508, 0.430, 0.25, 17.0)
    assert r.max_linear_speed == 2.0 and not r.arm
    # the UST-10LX's 1081 beams at 0.25 degree, every 4th: 271 beams 1 degree apart over 270 degrees
    assert jackal.lidar_beams == 271 and jackal.lidar_fov == pytest.approx(math.radians(270))
    assert math.degrees(jackal.lidar_fov) / (jackal.lidar_beams - 1) == pytest.approx(4 * 0.25)
    husky = PROFILES["husky"]
    assert profile_of_env(EnvConfig()) == husky  # the default environment is the Husky's


def test_robot_in_the_config_sets_the_robot_and_its_lidar_and_env_fields_still_win(tmp_path):
    cfg = resolve_config(overrides=["robot=jackal"])
    assert cfg.robot == "jackal" and cfg.env.robot == PROFILES["jackal"].robot and cfg.env.lidar_beams == 271
    path = tmp_path / "run.yaml"
    path.write_text("robot: jackal\nenv: {lidar_beams: 541, max_episode_steps: 500}\n")
    cfg = load_config(path)
    assert cfg.env.robot.name == "jackal" and cfg.env.lidar_beams == 541 and cfg.env.max_episode_steps == 500
    # containers: CURLNAV_ROBOT (docker compose passes it to every service); empty is unset
    assert resolve_config(environ={"CURLNAV_ROBOT": "jackal"}).env.robot.name == "jackal"
    assert resolve_config(environ={"CURLNAV_ROBOT": ""}).env.robot.name == "husky"
    # the default config's hash is the one of before profiles (runs resume, services agree)
    assert config_hash(ExperimentConfig()) == "e1337c51f22c6a058e25516fba3793a221e06f50df2e71a73f4a1bc2df38271a"
    assert config_hash(cfg) != config_hash(ExperimentConfig())


def test_a_profile_file_is_read_and_bad_ones_are_refused_naming_what(tmp_path):
    good = tmp_path / "tb4.yaml"
    good.write_text(PROFILE_FILE)
    profile = load_profile(str(good))
    assert profile.name == "turtlebot4" and profile.lidar_beams == 361
    assert profile.lidar_fov == pytest.approx(2 * math.pi) and profile.robot.max_linear_speed == 0.31
    cfg = apply_overrides(ExperimentConfig(), [f"robot={good}"])
    assert cfg.env.robot.name == "turtlebot4" and cfg.robot == "turtlebot4"  # the name, not the path
    # the same file by another path: the same config and hash; its saved config loads without the file
    moved = tmp_path / "elsewhere" / "profile.yaml"
    moved.parent.mkdir()
    moved.write_text(PROFILE_FILE)
    assert config_hash(apply_overrides(ExperimentConfig(), [f"robot={moved}"])) == config_hash(cfg)
    saved = tmp_path / "saved.yaml"
    saved.write_text(config_to_yaml(cfg))
    good.unlink()
    moved.unlink()
    assert config_hash(load_config(saved)) == config_hash(cfg)
    # naming the robot the config already has changes nothing made after it
    tuned = apply_overrides(ExperimentConfig(), ["robot=jackal", "env.lidar_beams=541", "robot=jackal"])
    assert tuned.env.lidar_beams == 541
    good.write_text(PROFILE_FILE)
    for text, fragment in [("base_length: 0.3\n", "needs a name"),
                           ("name: husky\n", "built-in profile's"),
                           ("name: r1\nlidar: {beams: -3}\n", "lidar.beams must be a positive number"),
                           ("name: r1\nlidar: {colour: red}\n", "unknown lidar key colour"),
                           ("name: r1\nbase_width: 0\n", "base_width must be a positive number"),
                           ("name: r1\nwheels: 6\n", "unknown key wheels in a robot profile; its keys: name, arm,"),
                           ("name: r1\nwheels: 6\n", "max_reverse_speed, lidar (beams, fov_deg, range_m, height_m)"),
                           ("name: R 1\n", "robot.name must be"),
                           ("name: [a]\n", "robot.name must be a text"),
                           ("name: 5\n", "robot.name must be a text")]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=re.escape(fragment)):
            load_profile(str(bad))
    with pytest.raises(ConfigError, match="unknown robot 'roomba'"):
        load_profile("roomba")


def test_a_robot_without_an_arm_never_extends_one_and_the_husky_does():
    for name, reach in (("jackal", 0.0), ("husky", 0.5)):
        env = NamoEnv("open-room", PROFILES[name].apply(EnvConfig(max_episode_steps=20)))
        try:
            env.reset(seed=0)
            for _ in range(5):
                env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
            assert env.scene.robot_pose()[3] == pytest.approx(reach, abs=0.02), name
            assert env.observation_space.shape == (ObservationLayout.from_env_config(env.config).size,)
        finally:
            env.close()


def test_an_artefact_records_its_robot_and_refuses_another_in_one_line(jackal_artefact, artefact):
    import json

    meta = json.loads((jackal_artefact / "metadata.json").read_text())
    assert recorded_robot(meta) == ("jackal", 0.508, 0.43) and meta["robot"]["arm"] is False
    assert meta["observation"]["layout"]["beams"] == 271
    husky_meta = json.loads((artefact / "metadata.json").read_text())
    check_robot(meta, PROFILES["jackal"].robot, "j")
    check_robot(husky_meta, PROFILES["husky"].robot, "h")
    refusal = r"^j: trained for the jackal \(0.508 x 0.43 m\), not the husky \(0.99 x 0.67 m\); refused$"
    with pytest.raises(ValueError, match=refusal):
        check_robot(meta, PROFILES["husky"].robot, "j")
    with pytest.raises(ValueError, match=r"^h: trained for the husky \(0.99 x 0.67 m\), not the jackal"):
        check_robot(husky_meta, PROFILES["jackal"].robot, "h")
    old = {"robot": {"base_length": 0.99, "base_width": 0.67}}  # before profiles: named by its footprint
    assert recorded_robot(old)[0] == "husky"
    # a top speed above the robot's, or an arm it has not, is another robot
    fast = {"robot": {**meta["robot"], "max_linear_speed": 3.0}}
    with pytest.raises(ValueError, match=r"top linear speed of 3 m/s, the jackal here has only 2 m/s; refused"):
        check_robot(fast, PROFILES["jackal"].robot, "j")
    with pytest.raises(ValueError, match=r"trained with an arm, the jackal here has none; refused"):
        check_robot({"robot": {**meta["robot"], "arm": True}}, PROFILES["jackal"].robot, "j")


def test_a_policy_reading_another_lidar_is_refused_in_one_line(jackal_artefact):
    import json

    meta = json.loads((jackal_artefact / "metadata.json").read_text())
    jackal = PROFILES["jackal"].apply(EnvConfig())
    check_observation(meta, jackal, "j")
    with pytest.raises(ValueError, match=r"^j: reads 271 beams, the jackal's LiDAR here gives 541 beams; refused$"):
        check_observation(meta, jackal.replace(lidar_beams=541), "j")
    with pytest.raises(ValueError, match=r"^j: reads a LiDAR of 270 deg, the jackal's here covers 240 deg; refused$"):
        check_observation(meta, jackal.replace(lidar_fov=math.radians(240)), "j")


def test_a_checkpoint_records_its_robot_and_is_refused_for_another(tmp_path):
    from curlnav.config import D4PGConfig
    from curlnav.evaluation.barn import jackal_env_config, policy_loader
    from curlnav.learner.artefact import load_policy
    from curlnav.learner.d4pg import init_state, save_checkpoint

    env = PROFILES["jackal"].apply(EnvConfig())
    state = init_state(D4PGConfig(seed=3), ObservationLayout.from_env_config(env), "cpu")
    path = save_checkpoint(state, tmp_path / "latest.safetensors", extra=sensor_metadata(env))
    policy = load_policy(path)
    assert recorded_robot(policy.metadata)[0] == "jackal" and policy.metadata["observation"]["layout"]["beams"] == 271
    husky_eval = ExperimentConfig().eval_env
    with pytest.raises(ValueError, match=r"trained for the jackal .* not the husky .*; refused"):
        policy_loader(husky_eval, load_policy, resample=False)(str(path))
    # the barn suite reads the full UST-10LX scan for it through the node's resampler, and it acts
    barn_policy = policy_loader(jackal_env_config(husky_eval), load_policy)(str(path))
    assert barn_policy(np.zeros(jackal_env_config(husky_eval).observation_size, np.float32)).shape == (3,)
    # a checkpoint from before it recorded a robot: its observation still has to fit
    bare = save_checkpoint(state, tmp_path / "old.safetensors")
    with pytest.raises(ValueError, match=r"reads 271 beams, the husky's LiDAR here gives 241 beams; refused"):
        policy_loader(husky_eval, load_policy, resample=False)(str(bare))


@pytest.mark.slow
def test_eval_and_the_ros2_node_refuse_the_wrong_robot_in_one_line(jackal_artefact, artefact):
    from curlnav.ros2.commands import _agent

    assert_one_line_error(run_curlnav("eval", str(jackal_artefact), "--world", "open-room", "--episodes", "1"),
                          "trained for the jackal", "not the husky", "refused")
    assert_one_line_error(run_curlnav("eval", str(artefact), "--robot", "jackal", "--world", "open-room",
                                      "--episodes", "1"), "trained for the husky", "not the jackal", "refused")
    assert_one_line_error(run_curlnav("eval", "oracle", "--suite", "barn", "--robot", "husky", "--worlds", "0"),
                          "--suite barn drives the Jackal")
    assert_one_line_error(run_curlnav("policy", "run", str(jackal_artefact), "--robot", "husky", "--world",
                                      "open-room"), "trained for the jackal", "not the husky", "refused")
    with pytest.raises(ValueError, match="trained for the jackal .* not the husky"):
        _agent(str(jackal_artefact), "husky")
    policy, layout = _agent(str(jackal_artefact), "jackal")
    assert layout.beams == 271 and not layout.arm and layout.max_linear_speed == 2.0


@pytest.mark.slow
def test_a_jackal_policy_drives_a_jackal_episode_through_eval(jackal_artefact):
    result = run_curlnav("eval", str(jackal_artefact), "--robot", "jackal", "--world", "open-room", "--episodes", "1",
                         timeout=300)
    assert result.returncode == 0, result.stderr[-1500:]
    assert "robot jackal: 0.508 x 0.43 m" in result.stdout



def test_a_policy_trained_slower_drives_the_faster_robot_at_its_own_top_speed(tmp_path):
    """A Jackal policy trained to command at most 1 m/s (``configs/barn-jackal-1mps.yaml``) drives the
    2 m/s Jackal at up to 1 m/s, in the simulator and on the ROS 2 node; measured on the base."""
    from curlnav.config import D4PGConfig, ExperimentConfig
    from curlnav.evaluation.barn import ResampledScanPolicy, jackal_env_config, policy_loader
    from curlnav.learner.artefact import export_policy, load_policy
    from curlnav.learner.d4pg import init_state
    from curlnav.ros2.commands import _agent
    from curlnav.sim.robots import SpeedLimitedPolicy, command_scale, replace_robot

    jackal = PROFILES["jackal"].apply(EnvConfig())
    slow_env = replace_robot(jackal, max_linear_speed=1.0)
    state = init_state(D4PGConfig(seed=3), ObservationLayout.from_env_config(slow_env), "cpu")
    path = export_policy(state, tmp_path / "slow", slow_env, worlds=["barn-course:0"])
    policy = load_policy(str(path))
    assert command_scale(policy.metadata, jackal.robot) == pytest.approx((0.5, 1.0))
    check_robot(policy.metadata, jackal.robot, "slow")  # slower than the robot: accepted

    env_config = jackal.replace(end_on_base_collision=False, max_episode_steps=50)
    loaded = policy_loader(env_config, load_policy, resample=False)(str(path))
    assert isinstance(loaded, SpeedLimitedPolicy)
    obs = np.random.default_rng(0).uniform(0.5, 5.0, policy.observation_size).astype(np.float32)
    assert loaded(obs)[0] == pytest.approx(0.5 * policy(obs)[0]) and loaded(obs)[1] == pytest.approx(policy(obs)[1])
    barn_loaded = policy_loader(jackal_env_config(ExperimentConfig().eval_env), load_policy)(str(path))
    assert isinstance(barn_loaded, ResampledScanPolicy) and isinstance(barn_loaded.policy, SpeedLimitedPolicy)
    faster = replace_robot(slow_env, max_angular_speed=3.0)
    with pytest.raises(ValueError, match="top angular speed of 3 rad/s, the jackal here has only 1.57 rad/s; refused"):
        check_robot({"robot": {**policy.metadata["robot"], "max_angular_speed": faster.robot.max_angular_speed}},
                    jackal.robot, "fast")
    flat_out = SpeedLimitedPolicy(lambda obs: np.array([1.0, 0.0, 0.0], np.float32),
                                  command_scale(policy.metadata, jackal.robot))
    env = NamoEnv("open-room", env_config)
    try:
        obs, _ = env.reset(seed=0, options={"pair": 0})
        x0, y0, _, _ = env.scene.robot_pose()
        steps = 10
        for _ in range(steps):
            obs, *_ = env.step(flat_out(obs))
        x1, y1, _, _ = env.scene.robot_pose()
    finally:
        env.close()
    speed = math.hypot(x1 - x0, y1 - y0) / (steps * env_config.control_period)
    assert 0.8 <= speed <= 1.05, f"the base moved at {speed:.2f} m/s; the policy was trained for at most 1 m/s"
    _, layout = _agent(str(path), "jackal")
    assert layout.max_linear_speed == 1.0  # the node commands v * 1 m/s
