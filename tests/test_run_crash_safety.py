"""Nothing accepted is lost: the replay's segment log, the one batch limit, weights versions that
only go forward, and the same through kill -9 of real service processes."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL, a_batch, replay_in, wait_for

from curlnav.builder import D4PGBuilder
from curlnav.bus.service import Deployment
from curlnav.config import resolve_config
from curlnav.replay.service import ReplayService
from curlnav.replay.wal import SegmentLog
from curlnav.run.launch import http_json_or_none


def table_contents(service: ReplayService) -> dict[str, np.ndarray]:
    t = service.table
    keys = (t._first_key + np.arange(t.size)) % t.max_size
    frames = t._t_obs[keys] % t.frame_capacity
    return {"action": t._t_action[keys].copy(), "reward": t._t_reward[keys].copy(),
            "ranges": t._f_ranges[frames].copy()}


def test_every_accepted_batch_survives_a_crash_in_order(tmp_path):
    service = replay_in(tmp_path)
    for seq in range(5):
        batch = a_batch(seq=seq)
        batch.batch.reward[:] = seq  # tell the batches apart
        assert service.handle_batch(batch.encode()) == 6
    before = table_contents(service)
    # kill -9: nothing closed, nothing saved; only what the log committed
    restored = replay_in(tmp_path)
    after = table_contents(restored)
    assert restored.table.size == 30 and restored.accepted_total == 30
    np.testing.assert_array_equal(after["reward"], before["reward"])
    np.testing.assert_array_equal(after["action"], before["action"])
    np.testing.assert_array_equal(after["ranges"], before["ranges"])
    assert restored.acked == {"a": 4}


def test_a_resent_batch_is_dropped_as_a_duplicate_and_a_restarted_actor_is_not(tmp_path):
    service = replay_in(tmp_path)
    assert service.handle_batch(a_batch(seq=10).encode()) == 6
    assert service.handle_batch(a_batch(seq=10).encode()) == 0  # the same batch again
    assert service.rejected() == {"duplicate": 1}
    restored = replay_in(tmp_path)
    assert restored.handle_batch(a_batch(seq=10).encode()) == 0  # remembered across a restart
    assert restored.handle_batch(a_batch(seq=11).encode()) == 6


def test_a_batch_above_the_one_limit_is_refused_once_and_counted_not_retried(tmp_path):
    limit = SMALL.replay.insert_batch
    service = replay_in(tmp_path)
    big = a_batch(seq=0, steps=limit + 10)
    assert big.batch.num_transitions > limit
    start = time.monotonic()
    assert service.handle_batch(big.encode(), timeout=0.1) == 0
    assert time.monotonic() - start < 1.0
    assert service.rejected() == {"too_large": 1}
    assert service.handle_batch(a_batch(seq=1).encode()) == 6  # the next batch goes in at once


def test_the_rate_limiter_always_admits_a_batch_of_the_limit():
    from curlnav.builder import D4PGBuilder

    for preset in ("default", "paper"):
        experiment = resolve_config(preset=preset)
        limiter = D4PGBuilder(experiment).make_rate_limiter()
        lo, hi = limiter.window
        assert hi - lo >= limiter.samples_per_insert * experiment.replay.insert_batch + experiment.d4pg.batch_size


@pytest.mark.parametrize("tail", [b"\x40\x00\x00\x00garbage-of-a-write-cut-short",
                                  b"\0" * 4096])  # zeros: a file that grew before its data landed
def test_a_torn_tail_is_cut_off_and_the_rest_restored(tmp_path, tail):
    service = replay_in(tmp_path)
    for seq in range(3):
        service.handle_batch(a_batch(seq=seq).encode())
    segment = sorted((tmp_path / "wal").glob("seg-*.log"))[-1]
    with open(segment, "ab") as f:
        f.write(tail)
    restored = replay_in(tmp_path)
    assert restored.table.size == 18
    assert restored.handle_batch(a_batch(seq=3).encode()) == 6
    assert replay_in(tmp_path).table.size == 24


def test_a_batch_is_counted_and_acknowledged_only_once_the_log_is_committed(tmp_path):
    service = replay_in(tmp_path)
    assert service.handle_batch(a_batch(seq=0).encode()) == 6

    def full_disk():
        raise OSError(28, "No space left on device")

    service.log.commit = full_disk
    try:
        service.accept_batches([a_batch(seq=1).encode()])
    except OSError:
        pass
    assert service.accepted_total == 6 and service.acked == {"a": 0}  # nothing claimed that is not on disk


def test_segments_that_left_the_table_are_deleted_and_a_restore_keeps_the_table(tmp_path):
    log = SegmentLog(tmp_path / "wal", segment_bytes=1)  # one record per segment
    service = replay_in(tmp_path)
    service.log = log
    for seq in range(40):  # 240 transitions through a table of 60 (no learner: past the rate limiter)
        service.handle_batch(a_batch(seq=seq).encode(), force=True)
    before = table_contents(service)
    dropped = service.prune_log()
    assert dropped > 25 and len(log.segments()) <= 40 - dropped
    restored = replay_in(tmp_path)
    assert restored.table.size == 60 and restored.accepted_total == 240
    np.testing.assert_array_equal(table_contents(restored)["action"], before["action"])


def test_a_restarted_learner_numbers_its_weights_above_every_version_published(tmp_path):
    from curlnav.learner.service import LearnerServiceConfig

    experiment = resolve_config(overrides=["d4pg.batch_size=8", "replay.min_size=8"])
    cfg = LearnerServiceConfig(Deployment(data_dir=str(tmp_path)))
    first = D4PGBuilder(experiment).make_learner_service(cfg)
    first.checkpoint()  # the checkpoint says version 0
    for _ in range(7):
        first.publish_version()  # versions 1..7 go out, then kill -9 before the next checkpoint
    second = D4PGBuilder(experiment).make_learner_service(cfg)
    assert second.version == 8
    third = D4PGBuilder(experiment).make_learner_service(cfg)  # and again, without publishing anything
    assert third.version == 9
    # a learner that crashed after publishing but before its first checkpoint
    fresh = tmp_path / "fresh"
    early = D4PGBuilder(experiment).make_learner_service(LearnerServiceConfig(Deployment(data_dir=str(fresh))))
    early.publish_version(), early.publish_version()
    again = D4PGBuilder(experiment).make_learner_service(LearnerServiceConfig(Deployment(data_dir=str(fresh))))
    assert again.version == 3


# -- real processes ---------------------------------------------------------------------------------

@pytest.mark.net
@pytest.mark.slow
def test_kill_9_of_replay_learner_and_scheduler_loses_nothing_accepted(tmp_path):
    """A training cluster of real processes; each stateful service is killed with SIGKILL and
    started again: the replay holds every transition it had accepted, the learner's versions
    only go forward, the curriculum keeps its episodes."""
    from curlnav.run.launch import LocalCluster

    experiment = resolve_config(overrides=["replay.min_size=200", "replay.samples_per_insert=8", "d4pg.batch_size=128",
                                           "exploration.warmup_steps=200"])
    cluster = LocalCluster(tmp_path / "run", experiment, actors=2, run="crash",
                           extra={"learner": ["--publish-every", "5", "--checkpoint-every-s", "2"]})
    cluster.start()
    try:
        status = cluster.status
        wait_for("learning under way", lambda: (s := status()) and (s["learner"]["version"] or 0) >= 3
                 and s["episodes"] >= 2 and s, timeout=240)
        replay_port = int((cluster.run_dir / "replay" / "http_port").read_text())
        # replay: what it reported accepted just before the kill is all there after the restart
        accepted = http_json_or_none(f"http://127.0.0.1:{replay_port}/healthz")["accepted"]
        cluster.kill_process("replay")
        cluster.restart("replay")
        replay_port = wait_for("replay back", lambda: (p := cluster.run_dir / "replay" / "http_port").exists()
                               and http_json_or_none(f"http://127.0.0.1:{int(p.read_text())}/healthz") and int(p.read_text()),
                               timeout=120)
        health = http_json_or_none(f"http://127.0.0.1:{replay_port}/healthz")
        assert health["restored"] >= accepted > 0 and health["accepted"] >= accepted
        # learner: versions go on above the last one published
        learner_url = cluster.learner_url
        before = http_json_or_none(f"{learner_url}/healthz")["version"]
        os.kill(cluster.processes["learner"].pid, signal.SIGKILL)
        cluster.processes.pop("learner").wait()
        cluster.restart("learner")
        after = wait_for("learner back", lambda: (h := http_json_or_none(f"{learner_url}/healthz")) and h["version"], timeout=120)
        assert after > before
        # scheduler: the episodes it counted are still counted
        episodes = status()["episodes"]
        cluster.kill_process("scheduler")
        cluster.restart("scheduler")
        back = wait_for("scheduler back", lambda: status(), timeout=120)
        assert back["episodes"] >= episodes
        wait_for("training goes on", lambda: (s := status()) and (s["learner"]["version"] or 0) > after
                 and (s["replay"]["size"] or 0) > health["size"], timeout=180)
        assert cluster.dead() == []
    finally:
        cluster.stop()


# -- bounded state -----------------------------------------------------------------------------------
def test_a_burst_of_reports_with_random_ids_keeps_status_small_and_memory_bounded():
    import tracemalloc
    import uuid

    from curlnav.proto.messages import AssignmentRequest, EpisodeReport
    from curlnav.scheduler.curriculum import load_curriculum
    from curlnav.scheduler.service import SchedulerCore

    root = Path(__file__).resolve().parents[1]
    curriculum = load_curriculum(root / "scheduler" / "curricula" / "s1+s2.yaml")
    core = SchedulerCore(curriculum)
    core.actor_joined("actor-0")
    world = curriculum.stages[0].worlds[0]
    core.assign(AssignmentRequest("actor-0").encode())  # an actor at work asks for a world first
    core.report(EpisodeReport("actor-0", world, "", True, 10.0, 0, 0, 50, 1, 0).encode())

    def burst(n: int) -> None:
        for i in range(n):
            forged = EpisodeReport(uuid.uuid4().hex, world if i % 2 else f"/x/{uuid.uuid4().hex}.yaml",
                                   uuid.uuid4().hex[:8] if i % 3 == 0 else "", True, 1.0, 0, 0, 10, 1, 0)
            core.report(forged.encode())
            core.actor_joined(f"fake-{uuid.uuid4().hex}") if i % 5 == 0 else None

    tracemalloc.start()
    burst(2_000)
    first = tracemalloc.get_traced_memory()[0]
    burst(10_000)
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    status = json.dumps(core.status())
    assert len(status) < 100_000, f"/status is {len(status)} bytes after the burst"
    assert core.status()["episodes"] == 1  # no forged report counted
    assert len(core.actors) <= 1024 and len(core.state.per_world) == 1
    assert after - first < 2_000_000, f"memory grew by {after - first} bytes over 10,000 more forged reports"
    rejected = core.status()["rejected"]
    assert rejected["unknown_actor"] >= 10_000 and rejected["too_many_actors"] > 0
