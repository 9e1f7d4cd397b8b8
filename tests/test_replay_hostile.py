"""Silent drops (issue 35, deliverable 5): the replay counts every accepted transition it does not
store, by reason, in its ``/status`` and in Prometheus, across restarts; and the chaos bench
counts those transitions as lost (lost = generated - stored, not generated - accepted).

A transition names its frames by the writer's ids; the table remembers the last few hundred of
each writer (stream) and holds frames in a ring. A transition whose frames the table no longer
knows (``unknown_frame``) or no longer holds (``frame_overwritten``) cannot be stored: it used to
go without a trace (``unknown_frame``) or be stored with another writer's frames in its slots.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import SMALL, metrics, replay_in, wait_for
from prometheus_client import generate_latest

from curlnav.bench.chaos import Incarnation, account, summary_line
from curlnav.layout import ObservationLayout
from curlnav.proto.frames import FrameBatch
from curlnav.proto.messages import TransitionBatch
from curlnav.proto.topology import Topology
from curlnav.replay.service import ReplayService
from curlnav.replay.table import ReplayTable
from curlnav.run.launch import http_json_or_none

LAYOUT = ObservationLayout()


def now_us() -> int:
    return time.time_ns() // 1000


def frames_and_transitions(frame_ids: range, transitions: list[tuple[int, int]]) -> FrameBatch:
    """Frames ``frame_ids`` (one episode, each frame's previous the one before) and transitions
    (obs id, next id), all with writer ids."""
    ids = np.array(list(frame_ids), np.int64)
    rng = np.random.default_rng(int(ids[0]) if len(ids) else 0)
    n, t = len(ids), len(transitions)
    pairs = np.array(transitions, np.int64).reshape(t, 2)
    return FrameBatch(local_id=ids, prev_id=np.maximum(ids - 1, ids[:1]),
                      ranges=rng.uniform(0, 10, (n, LAYOUT.beams)).astype(np.float16),
                      labels=np.zeros((n, LAYOUT.beams), np.uint8), goal=np.ones((n, 3), np.float32),
                      obs_id=pairs[:, 0].copy(), next_id=pairs[:, 1].copy(),
                      action=np.full((t, 3), 0.5, np.float32), reward=np.ones(t, np.float32),
                      discount=np.full(t, 0.9, np.float32))


def forgotten_frames_batches(actor: str = "actor-0", seq: int | None = None) -> list[bytes]:
    """Two batches of one actor: 300 frames (3 transitions), then 2 frames and 3 transitions, one
    of which names two frames of the first batch that lie 300 frames back: beyond what the table
    remembers of the stream (about 200), so it is an ``unknown_frame``."""
    seq = now_us() if seq is None else seq
    first = frames_and_transitions(range(300), [(296, 297), (297, 298), (298, 299)])
    second = frames_and_transitions(range(300, 302), [(0, 1), (299, 300), (300, 301)])
    return [TransitionBatch(actor, seq, 1, first).encode(), TransitionBatch(actor, seq + 1, 1, second).encode()]


def dropped_metric(service: ReplayService, reason: str) -> float | None:
    for line in generate_latest(service.registry).decode().splitlines():
        if line.startswith(f'replay_transitions_dropped_total{{reason="{reason}"}} '):
            return float(line.split()[-1])
    return None


def test_a_transition_whose_frames_the_replay_forgot_is_counted_in_status_and_prometheus(tmp_path):
    service = replay_in(tmp_path)
    added = [service.handle_batch(p) for p in forgotten_frames_batches()]
    assert added == [3, 2]  # accepted: 6 transitions; stored: 5
    status = service.status()
    assert status["accepted"] == 6 and status["dropped"] == 1 and status["dropped/unknown_frame"] == 1
    assert dropped_metric(service, "unknown_frame") == 1
    assert service.rejected() == {}  # the batches were accepted: a drop is not a refused message


def test_the_drop_count_survives_a_kill_and_a_restart_without_counting_twice(tmp_path):
    service = replay_in(tmp_path)
    for p in forgotten_frames_batches():
        service.handle_batch(p)
    # kill -9: nothing closed; at start the log is inserted again, the same transition is dropped
    # again, and the count stays one (a run's figure, like accepted)
    again = replay_in(tmp_path)
    assert again.table.size == 5 and again.status()["dropped"] == 1
    assert dropped_metric(again, "unknown_frame") == 1
    # batches accepted but not yet in the table at the kill: their drops are counted at the restart
    payloads = forgotten_frames_batches("actor-1")
    assert len(again.accept_batches(payloads)) == 2  # in the log, not inserted
    third = replay_in(tmp_path)
    assert third.table.size == 10 and third.status()["dropped"] == 2 and third.status()["dropped/unknown_frame"] == 2


def test_a_transition_whose_frame_was_overwritten_is_not_stored_with_another_writers_frames():
    """Stream A's frames are still remembered by id, but B wrote a whole ring of frames since:
    A's next transition would be stored with B's frames in its slots."""
    table = ReplayTable(LAYOUT, max_size=50, frame_capacity=100)
    table.insert(frames_and_transitions(range(5), [(0, 1)]), stream="A")
    table.insert(frames_and_transitions(range(150), [(148, 149)]), stream="B")
    assert table.insert(frames_and_transitions(range(5, 7), [(3, 4), (5, 6)]), stream="A") == 1  # frames 3, 4 gone
    assert table.dropped == {"frame_overwritten": 1} and table.size == 2
    assert table.info()["dropped"] == {"frame_overwritten": 1}


@pytest.mark.net
@pytest.mark.slow
def test_a_real_replay_shows_its_drops_on_its_http_status_and_metrics(tmp_path):
    """The replay as a process behind a router: an actor's stream whose frames it forgot."""
    from curlnav.bus.transport import reliable_publisher
    from curlnav.run.launch import LocalCluster

    cluster = LocalCluster(tmp_path / "run", SMALL, actors=1, run="drops")
    cluster._spawn("router", "router")
    cluster._spawn("replay", "replay")
    session = None
    try:
        port_file = cluster.run_dir / "replay" / "http_port"
        url = wait_for("the replay to answer", lambda: port_file.exists() and http_json_or_none(
            f"http://127.0.0.1:{int(port_file.read_text())}/healthz") and f"http://127.0.0.1:{port_file.read_text()}",
            timeout=120)
        session = cluster.bus_session("actor", ident="actor-0")
        # as the actor publishes (reliable, BLOCK): a 200 kB batch under the default congestion
        # control (DROP) is dropped when the session's queue is full, as on a loaded 2-core machine
        publisher = reliable_publisher(session, Topology("drops").transitions("actor-0"))
        # a put before the router has the replay's subscription is dropped on the way: wait for it
        wait_for("the replay's subscription to reach this session", lambda: publisher.matching_status.matching,
                 timeout=60)
        for payload in forgotten_frames_batches():
            publisher.put(payload)
        seen: list = []  # every health read, for the message if the batches never come
        try:
            wait_for("the two batches accepted and inserted", lambda: (h := http_json_or_none(f"{url}/healthz"))
                     and not seen.append(h) and h["accepted"] == 6 and h["waiting"] == 0, timeout=60)
        except AssertionError as err:
            raise AssertionError(f"{err}; the replay's last health: {seen[-1:]}") from None
        status = http_json_or_none(f"{url}/status")
        assert status is not None and status["accepted"] == 6 and status["size"] == 5, status
        assert status["dropped"] == 1 and status["dropped/unknown_frame"] == 1, status
        assert metrics(f"{url}/metrics").get('replay_transitions_dropped_total{reason="unknown_frame"}') == 1
    finally:
        if session is not None:
            session.close()
        cluster.stop()


def test_the_chaos_bench_counts_the_replays_drops_as_lost():
    """Every transition generated was accepted, but the replay stored 84 fewer: 84 lost."""
    stopped = Incarnation("actor-0", 10, generated=1000, accepted=990, unacknowledged=10, ended="stopped")
    killed = Incarnation("actor-1", 5, generated=400, accepted=368, ended="killed")
    clean = account([stopped, killed], accepted_total=1358, accepted_seen=1358)
    assert (clean.generated, clean.in_flight, clean.lost, clean.dropped) == (1400, 42, 0, 0)
    acc = account([stopped, killed], accepted_total=1358, accepted_seen=1358, dropped=84)
    assert (acc.generated, acc.accepted, acc.in_flight, acc.dropped, acc.lost) == (1400, 1358, 42, 84, 84)
    # the replay's count is a run's figure: one it was seen to reach and then lost counts too
    assert account([stopped], 990, 990, dropped=3, dropped_seen=7).lost == 7
    line = summary_line(1.0, {"replay": 1}, acc, {"versions monotonic": True})
    assert "accepted 1358, dropped by the replay 84, in flight 42, lost 84" in line, line


def test_a_pruned_log_does_not_count_its_first_segments_transitions_again(tmp_path):
    """A log pruned while it ran starts with a segment whose transitions name frames of the one
    deleted before it: they left the table long ago, and were counted (or stored) then. So too
    when that first segment is the only one left."""
    for pruned in (1, 5):  # of 6 segments: 5 left, or 1
        pruned_log_counts_nothing(tmp_path / f"pruned-{pruned}", pruned)


def pruned_log_counts_nothing(tmp_path, pruned: int) -> None:
    from curlnav.replay.nstep import NStepWriter
    from curlnav.replay.wal import SegmentLog

    log = SegmentLog(tmp_path / "wal", segment_bytes=1, fsync=False)  # a segment per batch
    writer, rng, index, seq = NStepWriter(LAYOUT, n_step=3, discount=0.9), np.random.default_rng(0), 0, now_us()
    writer.first(rng.uniform(0, 10, LAYOUT.size).astype(np.float32))
    for k in range(6):  # one episode, a batch every 4 steps: each batch's first transitions start in the one before
        for _ in range(4):
            writer.step(np.zeros(3, np.float32), 1.0, rng.uniform(0, 10, LAYOUT.size).astype(np.float32), False, False)
        batch = writer.flush()
        log.append(TransitionBatch("actor-0", seq + k, 1, batch).encode(), index)
        index += batch.num_transitions
    log.close()
    segments = sorted((tmp_path / "wal").glob("seg-*.log"))
    assert len(segments) == 6
    for segment in segments[:pruned]:
        segment.unlink()  # pruned, as drop_before does
    (tmp_path / "dropped.json").write_text('{"through": 1000000, "dropped": {"unknown_frame": 7}}')  # another log's
    service = replay_in(tmp_path)
    assert service.table.dropped.get("unknown_frame", 0) > 0  # the first kept segment named deleted frames
    assert service.status()["dropped"] == 0 and dropped_metric(service, "unknown_frame") is None
