"""Messages, codec validation, and the service cores without a network."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from conftest import a_batch

from curlnav.builder import D4PGBuilder
from curlnav.bus.service import Deployment
from curlnav.config import resolve_config
from curlnav.layout import ObservationLayout
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import (
    Assignment,
    AssignmentRequest,
    EpisodeReport,
    SampledBatch,
    SampleRequest,
    ServiceStatus,
    TransitionBatch,
    Weights,
)
from curlnav.proto.topology import Topology
from curlnav.replay.service import ReplayServiceConfig
from curlnav.scheduler.curriculum import CurriculumError, CurriculumState, load_curriculum
from curlnav.scheduler.service import SchedulerCore

LAYOUT = ObservationLayout()


def test_messages_round_trip():
    msg = a_batch()
    back = TransitionBatch.decode(msg.encode(), beams=241)
    assert back.actor_id == "a" and back.weights_version == 3
    assert np.array_equal(back.batch.ranges, msg.batch.ranges) and np.array_equal(back.batch.reward, msg.batch.reward)
    report = EpisodeReport("a", "open-room", "", True, 201.5, 0, 1, 40, 7, 2)
    assert EpisodeReport.decode(report.encode()) == report
    assignment = Assignment("a", "t-maze.yaml", "p2", "S2", 1, 4)
    assert Assignment.decode(assignment.encode()) == assignment
    assert SampleRequest.decode(SampleRequest(256, 0.5).encode()) == SampleRequest(256, 0.5)
    assert AssignmentRequest.decode(AssignmentRequest("x").encode()).actor_id == "x"
    weights = Weights(5, 100, b"blob", {"preset": "default"})
    assert Weights.decode(weights.encode()) == weights


def tamper(payload: bytes, **changes) -> bytes:
    obj = msgpack.unpackb(payload, raw=False)
    obj.update(changes)
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize("make, reason", [
    (lambda good: b"\xc1garbage", "malformed"),
    (lambda good: msgpack.packb([1, 2, 3]), "malformed"),
    (lambda good: tamper(good, v=99), "version"),
    (lambda good: tamper(good, kind="weights"), "kind"),
    (lambda good: tamper(good, seq="one"), "field"),
    (lambda good: tamper(good, reward={"dtype": "<f8", "shape": [6], "data": b"\0" * 48}), "dtype"),
    (lambda good: tamper(good, reward={"dtype": "<f4", "shape": [7], "data": b"\0" * 28}), "shape"),
    (lambda good: tamper(good, reward={"dtype": "<f4", "shape": [6],
                                       "data": np.array([np.nan] * 6, "<f4").tobytes()}), "non_finite"),
    (lambda good: tamper(good, ranges={"dtype": "<f2", "shape": [7, 100], "data": b"\0" * 1400}), "shape"),
    (lambda good: b"\0" * (65 * 1024 * 1024), "oversize"),
])
def test_bad_transition_batches_are_refused_with_a_reason(make, reason):
    with pytest.raises(ProtoError) as info:
        TransitionBatch.decode(make(a_batch().encode()), beams=241)
    assert info.value.reason == reason


def test_keys_live_under_the_run_prefix():
    t = Topology("exp-1")
    assert t.transitions("a3") == "curlnav/exp-1/transitions/a3"
    assert t.alive("actor", "a3") == "curlnav/exp-1/alive/actor/a3"
    with pytest.raises(ValueError, match="run name"):
        Topology("bad/name")


def test_replay_core_counts_rejections_and_keeps_accepted_data(tmp_path):
    small = resolve_config(overrides=["d4pg.batch_size=8", "replay.min_size=8"])
    service = D4PGBuilder(small).make_replay_service(ReplayServiceConfig(Deployment(data_dir=str(tmp_path))))
    assert service.handle_batch(a_batch(seq=0).encode()) == 6
    for payload in (b"junk", tamper(a_batch().encode(), v=2), b""):
        assert service.handle_batch(payload) == 0
    assert service.handle_batch(a_batch(seq=1).encode()) == 6
    assert service.table.size == 12
    assert service.rejected() == {"malformed": 2, "version": 1}
    reply = service.handle_sample(SampleRequest(8, 0.1).encode())
    batch = SampledBatch.decode(reply, LAYOUT)  # raw buffers: frames, checked against the layout
    assert batch.obs().shape == batch.next_obs().shape == (8, LAYOUT.size) and len(batch.keys) == 8
    # no save, no close: as after kill -9, the log has every accepted batch
    restored = D4PGBuilder(small).make_replay_service(ReplayServiceConfig(Deployment(data_dir=str(tmp_path))))
    assert restored.table.size == 12 and restored.accepted_total == 12


CURRICULUM = """
name: s1+s2
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.7, window: 10}
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door, p2]
    substep_advance: {success_rate: 0.5, window: 4, compare: ">"}
"""


def test_curriculum_advances_on_its_criteria(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(CURRICULUM)
    state = CurriculumState(load_curriculum(path))
    assert state.assign() == ("open-room", "")
    for _i in range(9):
        assert not state.record("open-room", "", True, epoch=0)
    assert state.record("open-room", "", False, epoch=0)  # 9/10 >= 70 %
    assert state.current.name == "S2" and state.epoch == 1 and state.assign() == ("door-corridor", "through-door")
    assert not state.record("open-room", "", True, epoch=0), "episodes begun before the advance do not count"
    # window of 4: T T F F (50 %, not > 50 %), T -> T F F T (50 %), T -> F F T T (50 %), T -> F T T T (75 %)
    for ok in (True, True, False, False, True, True):
        assert not state.record("door-corridor", "through-door", ok, epoch=1)
    assert state.record("door-corridor", "through-door", True, epoch=1)
    assert state.substep == 1 and state.assign() == ("door-corridor", "p2")
    restored = CurriculumState.from_dict(state.curriculum, json.loads(json.dumps(state.to_dict())))
    assert (restored.stage, restored.substep, restored.epoch) == (1, 1, 2)


@pytest.mark.parametrize("body, message", [
    ("stages: []", "non-empty 'stages'"),
    ("stages: [{worlds: [a], advance: {success_rate: 2, window: 5}}]", "success_rate in"),
    ("stages: [{worlds: [a], colour: red}]", "unknown keys"),
    ("stages: [{worlds: []}]", "worlds must be"),
    ("stages: [oops", "not valid YAML"),
])
def test_malformed_curricula_are_refused_naming_the_file(tmp_path, body, message):
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(CurriculumError, match=message) as info:
        load_curriculum(path)
    assert str(path) in str(info.value)


def test_shipped_curricula_load():
    from pathlib import Path

    for path in sorted(Path("scheduler/curricula").glob("*.yaml")):
        curriculum = load_curriculum(path)
        assert curriculum.stages, path


def test_scheduler_core_tracks_actors_reports_and_status(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(CURRICULUM)
    core = SchedulerCore(load_curriculum(path))
    core.actor_joined("a1")
    assignment = Assignment.decode(core.assign(AssignmentRequest("a1").encode()))
    assert (assignment.world, assignment.stage, assignment.epoch) == ("open-room", "S1", 0)
    core.service_status(ServiceStatus("learner", {"version": 9, "updates": 450}).encode())
    core.report(EpisodeReport("a1", "open-room", "", True, 200.0, 0, 0, 30, 7, 0).encode())
    core.report(b"not a report")
    with pytest.raises(ProtoError):
        core.assign(b"nope")
    status = core.status()
    assert status["episodes"] == 1 and status["live_actors"]["a1"]["last_report"]["weights_version"] == 7
    assert status["learner"]["version"] == 9 and status["rejected"] == {"malformed": 1}
    core.actor_left("a1")
    assert core.status()["live_actors"] == {}
