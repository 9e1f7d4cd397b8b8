"""`curlnav eval AGENT... --suite barn`: the BARN Challenge's rules, score and robot."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from conftest import assert_one_line_error, run_curlnav

from curlnav.config import ExperimentConfig
from curlnav.evaluation.barn import BarnTrial, check_robot, jackal_env_config, summarise
from curlnav.worlds.barn_challenge import barn

LAST_LINE = re.compile(r"^barn: (\S+) success (\d+\.\d)%, collisions (\d+\.\d)%, timeouts (\d+\.\d)%, "
                       r"mean time (\d+\.\d|-) s, score (\d\.\d{4}) over (\d+) worlds; senses (.+)$")


def test_path_lengths_are_measured_as_run_py_measures_them():
    # run.py: start, each path cell at x = row * 0.15 - 4.575, y = col * 0.15 + 5.075, goal 10 m ahead
    for n in (0, 150, 299):
        cells = barn.path_cells(n)
        points = [barn.START[:2], *[(r * 0.15 - 4.575, c * 0.15 + 5.075) for r, c in cells], barn.GOAL]
        length = sum(math.dist(a, b) for a, b in zip(points[:-1], points[1:]))
        assert barn.path_length(n) == pytest.approx(length, abs=1e-9)
        assert barn.optimal_time(n) == pytest.approx(length / 2.0)
    lengths = [barn.path_length(n) for n in range(barn.COUNT)]
    assert 10.0 < min(lengths) and max(lengths) < 14.0  # 10 m ahead, round the cylinders


def test_the_score_is_success_times_ot_over_the_clipped_time():
    ot = barn.optimal_time(3)
    assert barn.score(True, 0.5 * ot, 3) == pytest.approx(0.5)  # faster than 2 OT: clipped, 0.5 is the best
    assert barn.score(True, 4 * ot, 3) == pytest.approx(0.25)
    assert barn.score(True, 99.0, 3) == pytest.approx(1 / 8)  # slower than 8 OT: clipped
    assert barn.score(False, 4 * ot, 3) == 0.0


def test_a_collision_ends_the_trial_and_outranks_reaching_the_goal():
    assert BarnTrial.of("a", 0, True, 1, 9.0).outcome == "collided"
    assert BarnTrial.of("a", 0, True, 1, 9.0).score == 0.0
    assert BarnTrial.of("a", 0, False, 0, 100.0).outcome == "timeout"
    trials = [BarnTrial.of("a", 0, True, 0, 10.0), BarnTrial.of("a", 1, False, 2, 3.0),
              BarnTrial.of("a", 2, False, 0, 100.0), BarnTrial.of("a", 3, True, 0, 20.0)]
    (s,) = summarise(trials)
    assert (s.success, s.collisions, s.timeouts, s.mean_time_s) == (0.5, 0.25, 0.25, 15.0)
    assert s.score == pytest.approx(np.mean([t.score for t in trials]))
    m = LAST_LINE.match(s.line())
    assert m and m.groups() == ("a", "50.0", "25.0", "25.0", "15.0", f"{s.score:.4f}", "4", "exact"), s.line()


def test_the_robot_is_the_jackal_with_the_challenges_lidar():
    cfg = jackal_env_config(ExperimentConfig().eval_env)
    assert (cfg.robot.base_length, cfg.robot.base_width, cfg.robot.max_linear_speed) == (0.508, 0.430, 2.0)
    assert cfg.lidar_beams == 1081 and cfg.lidar_fov == pytest.approx(math.radians(270)) and cfg.lidar_max_range == 10.0
    assert cfg.goal_tolerance == 1.0 and cfg.max_episode_steps * cfg.control_period == pytest.approx(100.0)
    assert cfg.end_on_base_collision
    world = barn.world(0)
    (pair,) = world.pairs
    assert (pair.x, pair.y, pair.yaw, pair.gx, pair.gy) == (-2.25, 3.0, math.pi / 2, -2.25, 13.0)


def artefact(tmp_path, robot: dict, name: str = "artefact"):
    folder = tmp_path / name
    folder.mkdir()
    (folder / "metadata.json").write_text(json.dumps({"format": "curlnav-policy", "robot": robot}))
    return str(folder)


def test_an_artefact_for_another_robot_is_refused_and_a_jackal_one_is_not(tmp_path):
    husky = {"base_length": 0.99, "base_width": 0.67, "max_linear_speed": 1.0}
    with pytest.raises(ValueError, match=r"trained for the husky \(0.99 x 0.67 m\), not the jackal \(0.508 x 0.43 m\); refused"):
        check_robot(artefact(tmp_path, husky))
    check_robot(artefact(tmp_path, {"name": "jackal", "base_length": 0.508, "base_width": 0.43}, "jackal"))
    check_robot(artefact(tmp_path, {"base_length": 0.51, "base_width": 0.43}, "jackal-unnamed"))
    with pytest.raises(ValueError, match=r"trained for the turtlebot \(0.508 x 0.43 m\), not the jackal"):
        check_robot(artefact(tmp_path, {"name": "turtlebot", "base_length": 0.508, "base_width": 0.43}, "turtlebot"))


@pytest.mark.slow
def test_eval_refuses_the_husky_policy_on_the_barn_suite_in_one_line():
    assert_one_line_error(run_curlnav("eval", "policies/namo-general", "--suite", "barn", "--worlds", "0-1"),
                          "policies/namo-general: trained for the husky (0.99 x 0.67 m), not the jackal", "refused")


@pytest.mark.slow
@pytest.mark.parametrize("args, fragment", [
    (["--suite", "barn", "--worlds", "5-300"], "numbered 0-299"),
    (["--suite", "barn", "--worlds", "x"], "--worlds takes A-B"),
    (["--suite", "barn", "--world", "open-room"], "drop --world"),
    (["--worlds", "0-3"], "--worlds A-B picks worlds of --suite barn"),
])
def test_bad_world_choices_are_one_line_errors(args, fragment):
    assert_one_line_error(run_curlnav("eval", "oracle", *args), fragment)


@pytest.mark.slow
def test_the_suite_prints_per_world_lines_the_reference_and_the_last_line(tmp_path):
    result = run_curlnav("eval", "oracle", "--suite", "barn", "--worlds", "1-2", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert any("published reference" in line and "score 0.1693" in line and "success 88.0%" in line for line in lines)
    assert any(line.startswith("barn: oracle world 1: ") for line in lines)
    m = LAST_LINE.match([line for line in lines if line.startswith("barn: ")][-1])
    assert m and m.group(1) == "oracle" and m.group(7) == "2", lines[-3:]
    assert (tmp_path / "barn-trials.csv").read_text().count("\n") == 3


def test_a_jackal_policy_reads_the_full_scan_as_its_own_lidar_through_the_nodes_resampler():
    """The suite's 1081-beam UST-10LX scan, resampled for a 271-beam Jackal policy, against the
    271-beam LiDAR it was trained with, at the challenge's start in world 0: the full scan holds every
    policy angle, so the resampler decimates it and the policy reads what it read in training."""
    from curlnav.evaluation.barn import ResampledScanPolicy
    from curlnav.layout import ObservationLayout
    from curlnav.sim import NamoEnv
    from curlnav.sim.robots import PROFILES

    suite_cfg = jackal_env_config(ExperimentConfig().eval_env)
    own_cfg = PROFILES["jackal"].apply(suite_cfg)
    seen = []
    meta = {"observation": {"layout": ObservationLayout.from_env_config(own_cfg).to_dict(),
                            "lidar_fov_rad": own_cfg.lidar_fov, "control_period_s": 0.2},
            "action": {"scale": [2.0, 1.57, 0.3]}}
    wrapped = ResampledScanPolicy(lambda obs: seen.append(obs) or np.zeros(3, np.float32), suite_cfg, meta)
    observations = []
    for cfg in (suite_cfg, own_cfg):
        env = NamoEnv(barn.world(0), cfg)
        try:
            observations.append(env.reset(seed=0, options={"pair": "barn"})[0])
        finally:
            env.close()
    wrapped(observations[0])
    layout = ObservationLayout.from_env_config(own_cfg)
    assert seen[0].shape == observations[1].shape == (layout.size,)
    resampled, own = layout.newest_frame(seen[0]), layout.newest_frame(observations[1])
    np.testing.assert_allclose(resampled[0], own[0], atol=1e-4)
    assert own[0].min() < 3.0  # it sees the walls and cylinders around the start
    assert (resampled[1] == own[1]).all() and (resampled[2] == own[2]).all()
