"""``curlnav bench chaos``: its pure parts (the fault schedule, the monotonic check, the loss
arithmetic, the replay log read as it grows, the curriculum and artefact checks) without a
network, and a short real run under chaos that must lose nothing."""

from __future__ import annotations

import hashlib
import json
import zlib

import numpy as np
import pytest

from curlnav.bench.chaos import (
    FAULT_KINDS,
    Incarnation,
    LogTally,
    account,
    artefact_problems,
    attribute,
    curriculum_problems,
    fault_schedule,
    prepare_run_dir,
    went_back,
)
from curlnav.layout import ObservationLayout
from curlnav.proto.messages import TransitionBatch
from curlnav.replay.nstep import NStepWriter
from curlnav.replay.wal import HEADER, SegmentLog

LAYOUT = ObservationLayout()


def a_batch(actor: str, seq: int, steps: int = 5) -> bytes:
    writer = NStepWriter(LAYOUT, 3, 0.9)
    rng = np.random.default_rng(seq % 1000)
    writer.first(rng.uniform(0, 10, LAYOUT.size).astype(np.float32))
    for t in range(steps):
        writer.step(np.array([0.5, 0, 0.1], np.float32), 0.1, rng.uniform(0, 10, LAYOUT.size).astype(np.float32),
                    False, t == steps - 1)
    return TransitionBatch(actor, seq, 1, writer.flush()).encode()


def test_the_fault_schedule_spaces_faults_by_every_s_and_hits_every_kind_each_round():
    schedule = fault_schedule(1800, 30, actors=3, seed=4)
    assert all(15 <= f.gap_s <= 45 for f in schedule) and sum(f.gap_s for f in schedule) <= 1800
    assert len(schedule) > 30
    for start in range(0, len(schedule) - 5, 6):  # shuffled rounds: each kind once per six faults
        assert sorted(f.kind for f in schedule[start:start + 6]) == sorted(FAULT_KINDS)
    for f in schedule:
        if f.kind == "actor":
            assert f.target in ("actor-0", "actor-1", "actor-2") and f.stall_s == 0
        elif f.kind == "stall":
            assert f.target in ("router", "actor-0", "actor-1", "actor-2") and 3 <= f.stall_s <= 15
        else:
            assert f.target == f.kind
    assert fault_schedule(1800, 30, 3, seed=4) == schedule and fault_schedule(1800, 30, 3, seed=5) != schedule
    assert fault_schedule(5, 30, 1) == []
    with pytest.raises(ValueError, match="every_s > 0"):
        fault_schedule(60, 0, 1)


def test_went_back_finds_every_sample_below_the_highest_before_it():
    assert went_back([(0, 0), (1, None), (2, 5), (3, 5), (4, 9)]) == []
    assert went_back([(0, 3), (1, 7), (2, None), (3, 6), (4, 8), (5, 7)]) == [(3, 7, 6), (5, 8, 7)]
    assert went_back([]) == []


def test_loss_arithmetic_counts_a_stopped_actors_missing_transitions_and_a_killed_ones_as_in_flight():
    stopped = Incarnation("actor-0", 10, generated=1000, accepted=990, unacknowledged=10, ended="stopped")
    killed = Incarnation("actor-0", 5, generated=400, accepted=368, ended="killed")
    late = Incarnation("actor-1", 7, generated=300, accepted=332, ended="killed")  # read just before its last batch
    acc = account([stopped, killed, late], accepted_total=1690, accepted_seen=1690)
    assert (acc.generated, acc.accepted, acc.in_flight, acc.lost) == (1732, 1690, 42, 0)
    short = Incarnation("actor-0", 10, generated=1000, accepted=960, unacknowledged=10, ended="stopped")
    assert account([short], 960, 960).lost == 30  # 30 neither accepted nor held
    over = Incarnation("actor-0", 10, generated=1000, accepted=1000, unacknowledged=64, ended="stopped")
    assert account([over], 1000).in_flight == 0  # held, but accepted after all: not in flight
    went = account([stopped], accepted_total=990, accepted_seen=1020)  # the replay's count went back by 30
    assert went.lost == 30 and went.accepted_went_back == 30


def test_the_log_tally_reads_complete_records_once_and_attributes_them_to_each_actor_process(tmp_path):
    log = SegmentLog(tmp_path / "wal", fsync=False)
    first = 0
    for actor, seq in (("actor-0", 1_000_000), ("actor-0", 1_000_001), ("actor-1", 1_500_000), ("actor-0", 3_000_000)):
        payload = a_batch(actor, seq)
        log.append(payload, first)
        first += TransitionBatch.decode(payload).batch.num_transitions
    log.commit()
    tally = LogTally(tmp_path / "wal")
    assert tally.read() == 4 and tally.total == first == tally.end and tally.gaps == []
    per_batch = first // 4
    segment = next((tmp_path / "wal").glob("seg-*.log"))
    payload = a_batch("actor-1", 1_500_001)
    with open(segment, "ab") as f:  # a record half written: not read until it is whole
        f.write(HEADER.pack(len(payload), zlib.crc32(payload), first) + payload[:100])
        f.flush()
        assert tally.read() == 0
        f.write(payload[100:])
    assert tally.read() == 1 and tally.accepted("actor-1") == 2 * per_batch
    incarnations = [Incarnation("actor-0", 900_000), Incarnation("actor-0", 2_000_000), Incarnation("actor-1", 1_400_000)]
    assert attribute(incarnations, tally) == 0
    assert [i.accepted for i in incarnations] == [2 * per_batch, per_batch, 2 * per_batch]
    log.close()


def a_status(stage=1, epoch=2, episodes=40, history=None) -> dict:
    history = history if history is not None else [{"epoch": e, "stage": "C2", "substep": 0, "episodes": 10 * e,
                                                    "reason": "budget"} for e in range(1, epoch + 1)]
    return {"curriculum": "chaos", "stage_index": stage, "substep": 0, "epoch": epoch, "episodes": episodes,
            "advances": history}


def test_curriculum_problems_accept_a_consistent_state_and_name_what_went_back_or_is_missing():
    final = a_status()
    saved = {"curriculum": "chaos", "state": {"stage": 1, "substep": 0, "epoch": 2, "episodes": 40,
                                              "history": final["advances"]}}
    samples = [(1.0, a_status(0, 0, 5, [])), (2.0, a_status(0, 1, 20, final["advances"][:1])), (3.0, final)]
    assert curriculum_problems(saved, final, samples) == []
    assert curriculum_problems(None, final, samples) == ["scheduler/state.json is missing or unreadable"]
    back = samples + [(4.0, a_status(0, 2, 41))]
    assert any("stage_index went back from 1 to 0" in p for p in curriculum_problems(saved, final, back))
    forgot = {"curriculum": "chaos", "state": {**saved["state"], "epoch": 1, "history": final["advances"][:1]}}
    problems = curriculum_problems(forgot, final, samples)
    assert any("epoch 1 but the scheduler's status says 2" in p for p in problems)
    assert any("not in state.json" in p for p in problems)


def test_artefact_problems_check_every_file_against_its_metadata(tmp_path):
    folder = tmp_path / "artefacts"
    for version in (3, 4):
        v = folder / f"v{version}"
        v.mkdir(parents=True)
        (v / "actor.onnx").write_bytes(b"onnx %d" % version)
        files = {"actor.onnx": hashlib.sha256(b"onnx %d" % version).hexdigest()}
        (v / "metadata.json").write_text(json.dumps({"format": "curlnav-policy", "files": files}))
    (folder / "v5.x1y2").mkdir()  # an export cut short
    assert artefact_problems(folder) == ([3, 4], [], ["v5.x1y2"])
    (folder / "v4" / "actor.onnx").write_bytes(b"changed")
    versions, problems, _ = artefact_problems(folder)
    assert problems == ["v4: actor.onnx does not match the sha256 in its metadata.json"]
    assert artefact_problems(tmp_path / "none")[1] == [f"no artefact in {tmp_path / 'none'}"]


def test_the_bench_never_clears_a_folder_it_did_not_make(tmp_path):
    run = tmp_path / "training"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    with pytest.raises(ValueError, match="holds something this bench did not make"):
        prepare_run_dir(run)
    assert (run / "config.yaml").exists()
    (run / "chaos.json").write_text("{}")
    assert prepare_run_dir(run) == run and list(run.iterdir()) == []


def test_bench_chaos_refuses_bad_input_in_one_line(capsys):
    from curlnav.cli import main

    assert main(["bench", "chaos", "--minutes", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("curlnav: error: bench chaos: --minutes and --every-s must be > 0")


@pytest.mark.benchmark  # 2.3-2.6 min on our 2-core machine beside two training runs (start-up alone 60-85 s)
def test_a_run_under_chaos_loses_nothing_and_keeps_versions_curriculum_and_policy_intact(tmp_path):
    """A minute of chaos with one actor and a fault every ~10 s (seed 1: the router first, the
    learner, a stall of the router, the replay, the actor): everything the actor generated is
    accepted or still held at its stop, versions only go forward, the curriculum and the policy
    artefacts are intact, and every service comes back."""
    from curlnav.bench.chaos import run_chaos_bench

    lines: list[str] = []
    result = run_chaos_bench(1.0, actors=1, every_s=10, seed=1, run_dir=tmp_path / "run", stage_steps=600,
                             stall_s=(3.0, 12.0), say=lines.append)
    text = "\n".join(lines)
    assert result.accounting.lost == 0, text
    assert result.ok and result.accounting.generated > 0, text
    assert len(result.faults) >= 3 and all(f.recovered for f in result.faults), text
