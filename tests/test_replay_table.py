"""Replay: n-step returns, frame de-duplication, FIFO, rate limiting, persistence."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import REPLAY_LAYOUT as LAYOUT
from conftest import expected_stack, obs_for

from curlnav.layout import ObservationLayout
from curlnav.replay import FrameBatch, NStepWriter, RateLimiterTimeout, ReplayInputError, ReplayTable, SampleToInsertRatio


def run_episode(writer: NStepWriter, rewards: list[float], terminated: bool, episode: int = 0) -> FrameBatch:
    writer.first(obs_for(0, episode))
    for t, r in enumerate(rewards):
        last = t == len(rewards) - 1
        writer.step(np.array([0.1 * t, 0, 0]), r, obs_for(t + 1, episode), terminated and last, (not terminated) and last)
    return writer.flush()


def test_n_step_returns_match_hand_computed_values():
    g = 0.9
    writer = NStepWriter(LAYOUT, n_step=3, discount=g)
    batch = run_episode(writer, [1.0, 2.0, 3.0, 4.0, 5.0], terminated=True)
    assert batch.num_transitions == 5 and batch.num_frames == 6
    # t=0: 1 + .9*2 + .81*3, bootstrap from frame 3 with gamma^3
    assert batch.reward[0] == pytest.approx(1 + g * 2 + g * g * 3)
    assert batch.discount[0] == pytest.approx(g ** 3)
    assert (batch.obs_id[0], batch.next_id[0]) == (0, 3)
    # t=2: 3 + .9*4 + .81*5 ends on the terminal step: no bootstrap
    assert batch.reward[2] == pytest.approx(3 + g * 4 + g * g * 5)
    assert batch.discount[2] == 0.0
    # the episode ends inside the window: t=3 has 2 steps, t=4 one, both terminal
    assert batch.reward[3] == pytest.approx(4 + g * 5) and batch.discount[3] == 0.0
    assert batch.reward[4] == pytest.approx(5.0) and batch.discount[4] == 0.0
    assert list(batch.next_id[2:]) == [5, 5, 5]


def test_truncation_bootstraps_but_termination_does_not():
    g = 0.9
    writer = NStepWriter(LAYOUT, n_step=3, discount=g)
    batch = run_episode(writer, [1.0, 1.0], terminated=False)  # timeout after two steps
    assert batch.reward[0] == pytest.approx(1 + g) and batch.discount[0] == pytest.approx(g ** 2)
    assert batch.reward[1] == pytest.approx(1.0) and batch.discount[1] == pytest.approx(g)
    batch = run_episode(writer, [1.0, 1.0], terminated=True)
    assert list(batch.discount) == [0.0, 0.0]


def test_table_rebuilds_stacked_observations_from_frames_of_interleaved_writers():
    table = ReplayTable(LAYOUT, max_size=100)
    writers = {s: NStepWriter(LAYOUT, n_step=2, discount=0.5) for s in ("a", "b")}
    for s, w in writers.items():
        w.first(obs_for(0, episode=(ord(s) - 96)))
    for t in range(12):  # the two writers' frames interleave in the table
        for s, w in writers.items():
            w.step(np.zeros(3), 1.0, obs_for(t + 1, episode=(ord(s) - 96)), False, False)
            table.insert(w.flush(), stream=s)
    assert table.size == 2 * 11
    sample = table.sample(64)
    for i in range(64):
        episode = int(round(sample.obs[i][-1]))
        step = int(round(sample.obs[i][-3]))
        assert np.allclose(sample.obs[i], expected_stack(list(range(step + 1)), episode), atol=1e-2)
        assert np.allclose(sample.next_obs[i], expected_stack(list(range(step + 3)), episode), atol=1e-2)


def test_frames_are_stored_once_and_transitions_are_compact():
    table = ReplayTable(ObservationLayout(), max_size=50_000)
    assert table.bytes_per_transition < 1100, "no stacked frame stored four times"
    assert table.bytes_per_transition * 10 < 2 * 1958 * 4


def test_fifo_eviction_keeps_the_newest_transitions():
    table = ReplayTable(LAYOUT, max_size=10)
    writer = NStepWriter(LAYOUT, n_step=1, discount=0.9)
    table.insert(run_episode(writer, [float(r) for r in range(30)], terminated=True))
    assert table.size == 10
    sample = table.sample(200)
    assert sorted(set(sample.reward.tolist())) == [float(r) for r in range(20, 30)]
    assert sample.keys.min() >= 20


def test_bad_batches_are_rejected_counted_and_nothing_is_lost():
    table = ReplayTable(LAYOUT, max_size=100)
    writer = NStepWriter(LAYOUT, n_step=1, discount=0.9)
    table.insert(run_episode(writer, [1.0, 2.0], terminated=True))
    bad = run_episode(writer, [1.0, 2.0], terminated=True)
    bad.reward[0] = np.nan
    with pytest.raises(ReplayInputError, match="NaN") as info:
        table.insert(bad)
    assert info.value.reason == "non_finite"
    bad = run_episode(writer, [1.0], terminated=True)
    bad.ranges = bad.ranges[:, :3]
    with pytest.raises(ReplayInputError, match="ranges has shape"):
        table.insert(bad)
    assert table.size == 2 and table.rejected == {"non_finite": 1, "shape": 1}


def test_rate_limiter_blocks_samples_below_min_size_and_keeps_the_ratio():
    limiter = SampleToInsertRatio(samples_per_insert=4, min_size_to_sample=10, error_buffer=8)
    table = ReplayTable(LAYOUT, max_size=1000, rate_limiter=limiter)
    writer = NStepWriter(LAYOUT, n_step=1, discount=0.9)
    table.insert(run_episode(writer, [1.0] * 9, terminated=True))
    assert not table.can_sample(1), "samples wait until min_size_to_sample items"
    with pytest.raises(RateLimiterTimeout):
        table.sample(1, timeout=0.05)
    table.insert(run_episode(writer, [1.0], terminated=True))
    # error = 10*4 - samples must stay >= 40 - 8: eight samples allowed, not nine
    assert table.can_sample(8) and not table.can_sample(9)
    table.sample(8)
    assert not table.can_sample(1)
    # inserts may run ahead by at most error_buffer / spi = 2 items
    assert table.can_insert(4) and not table.can_insert(5)


def test_a_blocked_sample_wakes_up_when_an_insert_arrives():
    limiter = SampleToInsertRatio(samples_per_insert=1, min_size_to_sample=2, error_buffer=2)
    table = ReplayTable(LAYOUT, max_size=100, rate_limiter=limiter)
    writer = NStepWriter(LAYOUT, n_step=1, discount=0.9)
    got = []
    thread = threading.Thread(target=lambda: got.append(table.sample(1, timeout=10)))
    thread.start()
    time.sleep(0.05)
    assert not got
    table.insert(run_episode(writer, [1.0, 2.0], terminated=True))
    thread.join(timeout=10)
    assert len(got) == 1


def test_limiter_refuses_settings_that_could_deadlock():
    limiter = SampleToInsertRatio(samples_per_insert=64, min_size_to_sample=100, error_buffer=100)
    with pytest.raises(ValueError, match="could both block"):
        limiter.check_batch(256)
    SampleToInsertRatio(64, 100, 160).check_batch(256)


def test_prioritised_sampling_follows_priorities():
    table = ReplayTable(LAYOUT, max_size=100, sampler="prioritized", priority_exponent=1.0)
    writer = NStepWriter(LAYOUT, n_step=1, discount=0.9)
    table.insert(run_episode(writer, [float(r) for r in range(4)], terminated=True))
    keys = np.arange(4)
    assert table.update_priorities(keys, np.array([0.0, 0.0, 1.0, 3.0])) == 4
    sample = table.sample(4000)
    counts = np.bincount(sample.keys, minlength=4)
    assert counts[0] == counts[1] == 0
    assert 2.5 < counts[3] / counts[2] < 3.5
    assert np.allclose(sample.probabilities[sample.keys == 3], 0.75)


def test_save_and_restore_round_trip(tmp_path):
    limiter = SampleToInsertRatio(samples_per_insert=2, min_size_to_sample=5, error_buffer=40)
    table = ReplayTable(LAYOUT, max_size=50, rate_limiter=limiter, seed=1)
    writer = NStepWriter(LAYOUT, n_step=2, discount=0.9)
    for episode in range(3):
        table.insert(run_episode(writer, [1.0, 2.0, 3.0, 4.0], terminated=episode % 2 == 0, episode=episode))
    table.sample(6)
    path = table.save(tmp_path / "replay.npz")
    restored = ReplayTable.restore(path, SampleToInsertRatio(2, 5, 4), seed=1)  # a tight limiter
    assert restored.size == table.size == 12
    assert restored.info()["total_inserted"] == 12
    a, b = ReplayTable.restore(path, seed=7), ReplayTable.restore(path, seed=7)
    sa, sb = a.sample(20), b.sample(20)
    assert np.array_equal(sa.obs, sb.obs) and np.array_equal(sa.keys, sb.keys)
    # the same keys give the same data as in the original table
    for key, obs, reward in zip(sa.keys, sa.obs, sa.reward):
        slot = key % table.max_size
        assert table._t_reward[slot] == reward
        assert np.array_equal(table._observations(np.array([table._t_obs[slot]]), 0)[0], obs)
    # the restored limiter is re-centred: sampling is possible at once, never blocked forever
    assert restored.can_sample(4)
