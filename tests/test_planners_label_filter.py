"""``+track`` (``curlnav.nav.perception.label_filter``): on a NAMO floor, a segmenter's flickering false
movable runs are voted away while the balls and doors it labels stay movable, measured against the
simulator's true labels; on exact labels almost nothing changes; the suffix stacks last."""

from __future__ import annotations

import numpy as np
import pytest

from curlnav.layout import ObservationLayout
from curlnav.nav import make_agent
from curlnav.nav.perception.label_filter import LabelFilterConfig, LabelFilteredPolicy
from curlnav.nav.recovery.rescue import RescuedPolicy
from curlnav.nav.safety.shield import ShieldedPolicy
from curlnav.sim import EnvConfig, NamoEnv, SensorNoiseConfig
from curlnav.sim.controllers import GoalSeekingController

OFFICE = "namo-office:3"  # 22 x 14 m, 8 balls and 8 doors


class Recorder:
    """A goal-seeking policy that keeps the observations it was given."""

    def __init__(self, cfg: EnvConfig) -> None:
        self.seeker = GoalSeekingController(cfg)
        self.seen: list[np.ndarray] = []

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        self.seen.append(observation)
        return self.seeker.act(observation)


def label_counts(noise: SensorNoiseConfig, seeds=range(3), steps: int = 120) -> dict[str, int]:
    """Drive the office floor behind ``+track``; count movable beams against the true labels of
    the same scans: true movable ones kept (``kept``) or lost (``lost``), false ones shown to
    the policy (``false``), and the raw scan's false ones (``raw_false``) and true ones (``raw_true``)."""
    cfg = EnvConfig(sensor_noise=noise, end_on_base_collision=False)
    layout = ObservationLayout.from_env_config(cfg)
    counts = dict(kept=0, lost=0, false=0, raw_false=0, raw_true=0)
    env = NamoEnv(OFFICE, cfg)
    try:
        for seed in seeds:
            recorder = Recorder(cfg)
            agent = LabelFilteredPolicy(recorder, cfg)
            obs, info = env.reset(seed=seed)
            agent.reset(env.world, None)
            for _ in range(steps):
                ranges, true_labels, _ = env.scene.scan(*info["pose"])
                true_movable = (true_labels > 0.5) & (ranges < cfg.lidar_max_range - 1e-3)
                _, raw, _ = layout.newest_frame(obs)
                action = agent.act(obs, info)
                _, shown, _ = layout.newest_frame(recorder.seen[-1])
                counts["kept"] += int((true_movable & (shown > 0.5)).sum())
                counts["lost"] += int((true_movable & (shown < 0.5) & (raw > 0.5)).sum())
                counts["false"] += int((~true_movable & (shown > 0.5)).sum())
                counts["raw_false"] += int((~true_movable & (raw > 0.5)).sum())
                counts["raw_true"] += int((true_movable & (raw > 0.5)).sum())
                obs, _, terminated, truncated, info = env.step(action)
                if terminated or truncated:
                    break
    finally:
        env.close()
    return counts


def test_flickering_false_movable_runs_are_voted_away_and_true_objects_stay_movable():
    # the realistic preset's segmenter errors alone: 5 % of the other beams in runs of 6, objects missed whole
    counts = label_counts(SensorNoiseConfig("none", label_error=0.05, label_run=6.0))
    assert counts["raw_true"] > 200 and counts["raw_false"] > 200  # the drive saw balls and doors, and errors
    assert counts["false"] < 0.25 * counts["raw_false"], counts  # most false runs gone
    assert counts["kept"] > 0.85 * counts["raw_true"], counts  # the objects the segmenter saw stay movable


def test_on_exact_labels_the_vote_changes_almost_nothing():
    counts = label_counts(SensorNoiseConfig())
    assert counts["raw_false"] == 0 and counts["false"] == 0
    assert counts["lost"] <= 0.05 * counts["raw_true"], counts  # only where an object first comes into view


def test_the_vote_reads_the_scan_from_where_a_late_observation_was_seen():
    # one control period late: the newest frame was measured from the pose one step ago; a vote
    # placed from the pose now would smear every ball by a step's motion and lose it when turning
    counts = label_counts(SensorNoiseConfig("none", label_error=0.05, label_run=6.0, latency_steps=1), seeds=range(2))
    assert counts["kept"] > 0.85 * counts["raw_true"], counts


def test_track_stacks_last_and_its_settings_are_checked():
    cfg = EnvConfig()
    label, agent = make_agent("seeker+rescue+shield+track", cfg, lambda name: GoalSeekingController(cfg).act)
    assert label == "seeker+rescue+shield+track" and isinstance(agent, LabelFilteredPolicy)
    assert isinstance(agent.policy, ShieldedPolicy) and isinstance(agent.policy.policy, RescuedPolicy)
    with pytest.raises(ValueError, match=r"in the order POLICY\[\+global-plan\|\+scan-plan\]\[\+rescue\]\[\+shield\]\[\+track\]"):
        make_agent("seeker+track+shield", cfg, lambda name: GoalSeekingController(cfg).act)
    _, planner = make_agent("dwa+track", cfg, lambda name: None)
    assert isinstance(planner, LabelFilteredPolicy)
    with pytest.raises(ValueError, match="scans"):
        LabelFilterConfig(scans=0)
    with pytest.raises(ValueError, match="cell_m"):
        LabelFilterConfig(cell_m=0.0)
    with pytest.raises(TypeError, match="needs odometry"):
        agent(np.zeros(ObservationLayout.from_env_config(cfg).size, np.float32))
