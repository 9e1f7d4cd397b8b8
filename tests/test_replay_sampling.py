"""The sampling path for a fast learner (issue 31): the replay gathers a batch as frames straight
into raw buffers with a versioned header; the learner checks the buffers, refuses malformed ones
by reason, and turns them into tensors on its device; priorities travel the same way."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch
from conftest import REPLAY_LAYOUT as LAYOUT
from conftest import expected_stack, obs_for

from curlnav.layout import ObservationLayout
from curlnav.learner.feed import BatchAssembler, SampleFeed, describe_device, resolve_device
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import PriorityUpdate, SampledBatch
from curlnav.proto.rawbuf import peek_raw
from curlnav.replay import NStepWriter, ReplayTable


def filled_table(steps: int = 40) -> ReplayTable:
    table = ReplayTable(LAYOUT, 1000, seed=3)
    writer = NStepWriter(LAYOUT, n_step=2, discount=0.5)
    writer.first(obs_for(0, episode=1))
    for t in range(steps):
        writer.step(np.array([t, 0, 0], np.float32), 1.0, obs_for(t + 1, episode=1), False, False)
        table.insert(writer.flush())
    return table


def sampled_message(table: ReplayTable, n: int) -> bytearray:
    writer = SampledBatch.writer(n, LAYOUT)
    table.sample_frames(n, out={name: writer.view(name) for name in writer.schema})
    return writer.payload()


def test_a_sampled_message_rebuilds_the_observations_the_environment_stacked():
    table = filled_table()
    batch = SampledBatch.decode(bytes(sampled_message(table, 64)), LAYOUT)
    obs, next_obs = batch.obs(), batch.next_obs()
    assert obs.shape == next_obs.shape == (64, LAYOUT.size) and obs.dtype == np.float32
    for i in range(64):
        step = int(batch.action[i, 0])  # the action of step t names t: an independent key to the truth
        assert np.allclose(obs[i], expected_stack(list(range(step + 1)), 1), atol=1e-2)
        assert np.allclose(next_obs[i], expected_stack(list(range(step + 3)), 1), atol=1e-2)
    assert np.all(batch.discount == 0.25) and np.all(batch.reward == 1.5)
    assert np.allclose(batch.probabilities, 1 / table.size)
    # and the tensors the learner steps on are the same numbers
    tensors = BatchAssembler(torch.device("cpu"))(batch)
    assert torch.equal(tensors.obs, torch.from_numpy(obs)) and torch.equal(tensors.next_obs, torch.from_numpy(next_obs))


def corrupt(payload: bytes, offset: int, value: bytes) -> bytes:
    data = bytearray(payload)
    data[offset:offset + len(value)] = value
    return bytes(data)


def test_malformed_sampled_batches_are_refused_by_reason_and_counted():
    table = filled_table()
    good = bytes(sampled_message(table, 8))
    head = 20  # magic, kind, version, arrays, reserved, total bytes
    kind, version, arrays = peek_raw(good)
    assert (kind, version, arrays) == (1, SampledBatch.VERSION, len(SampledBatch.FIELDS))
    reward_offset = struct.unpack_from("<Q", good, head + 7 * 40 + 24)[0]  # entries of 40 bytes
    cases = {
        "malformed": [b"", b"junk", corrupt(good, 0, b"XXXX")],
        "shape": [good[:-64], good + b"\0" * 64,  # truncated, padded
                  corrupt(good, head + 8, struct.pack("<I", 9))],  # the first array claims 9 items
        "version": [corrupt(good, 6, struct.pack("<H", 2))],
        "kind": [corrupt(good, 4, struct.pack("<H", 2))],
        "dtype": [corrupt(good, head, b"<f4 ")],  # ranges claim float32
        "non_finite": [corrupt(good, reward_offset, struct.pack("<f", float("nan")))],
    }
    feed = SampleFeed(session=None, key="k", batch_size=8, layout=LAYOUT)
    for reason, payloads in cases.items():
        for payload in payloads:
            with pytest.raises(ProtoError) as info:
                SampledBatch.decode(payload, LAYOUT)
            assert info.value.reason == reason, (reason, str(info.value))
            assert feed.decode(payload) is None
    assert feed.rejected == {reason: len(p) for reason, p in cases.items()}
    # another layout (more beams) is a shape error, not garbage
    with pytest.raises(ProtoError, match="shape"):
        SampledBatch.decode(good, ObservationLayout(beams=7, range_frames=4, label_frames=4, goal_frames=10))
    assert feed.decode(good) is not None and feed.received == 1


def test_priority_updates_travel_batched_in_raw_buffers():
    a = PriorityUpdate(np.arange(4, dtype=np.int64), np.full(4, 0.5, np.float32))
    b = PriorityUpdate(np.arange(2, 6, dtype=np.int64), np.full(4, 2.0, np.float32))
    merged = PriorityUpdate.decode(bytes(PriorityUpdate.merge([a, b]).encode()))
    assert merged.keys.tolist() == [0, 1, 2, 3, 2, 3, 4, 5] and merged.priorities.tolist() == [0.5] * 4 + [2.0] * 4
    table = filled_table()
    table.sampler = "prioritized"
    assert table.update_priorities(merged.keys, merged.priorities) == 8
    assert table._t_priority[2] == 2.0  # the later update of a key sampled twice wins
    bad = bytes(PriorityUpdate(np.arange(2, dtype=np.int64), np.array([1.0, -1.0], np.float32)).encode())
    with pytest.raises(ProtoError, match="non_finite"):
        PriorityUpdate.decode(bad)
    with pytest.raises(ProtoError, match="kind"):
        PriorityUpdate.decode(bytes(sampled_message(table, 4)))


def test_the_learner_names_its_device_and_runs_on_cpu_without_a_gpu():
    assert resolve_device("cpu").type == "cpu"
    auto = resolve_device("auto")
    assert auto.type == ("cuda" if torch.cuda.is_available() else "cpu")
    line = describe_device(auto)
    assert line.startswith(f"learner device: {auto.type}")
    if not torch.cuda.is_available():
        assert "no CUDA device present" in line
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")


def test_one_reply_carrying_several_batches_splits_into_the_learners_batches():
    """``batches_per_request``: one query for 4 x 8 transitions gives the learner 4 batches of 8,
    each rebuilding the observations the environment stacked; a reply of another size is refused."""
    table = filled_table()
    feed = SampleFeed(session=None, key="k", batch_size=8, layout=LAYOUT, batches_per_request=4,
                      assembler=BatchAssembler(torch.device("cpu")))
    parts = feed.decode(bytes(sampled_message(table, 32)))
    assert len(parts) == 4 and feed.received == 1
    for batch, tensors in parts:
        assert batch.obs().shape == (8, LAYOUT.size) and tensors.obs.shape == (8, LAYOUT.size)
        for i in range(8):
            step = int(batch.action[i, 0])
            assert np.allclose(batch.obs()[i], expected_stack(list(range(step + 1)), 1), atol=1e-2)
        assert torch.equal(tensors.obs, torch.from_numpy(batch.obs()))
    keys = np.concatenate([b.keys for b, _ in parts])
    assert len(keys) == 32
    assert feed.decode(bytes(sampled_message(table, 8))) is None and feed.rejected == {"shape": 1}
    with pytest.raises(ValueError, match="1..8192"):
        SampleFeed(session=None, key="k", batch_size=4096, layout=LAYOUT, batches_per_request=4)


def test_the_learner_asks_only_for_requests_the_replays_rate_limiter_can_admit(tmp_path):
    """A request larger than the limiter's slack would wait for ever: the learner asks for fewer
    batches per request, and a replay refuses such a request at once instead of hanging."""
    from curlnav.builder import D4PGBuilder
    from curlnav.bus.service import Deployment
    from curlnav.config import ExperimentConfig, apply_overrides
    from curlnav.proto.messages import SampleRequest
    from curlnav.replay.service import ReplayServiceConfig

    base = ExperimentConfig()
    assert D4PGBuilder(base).batches_per_request(4) == 4  # the default config's slack admits 4 x 256
    tight = apply_overrides(base, ["replay.samples_per_insert=1", "replay.min_size=256", "replay.insert_batch=256"])
    builder = D4PGBuilder(tight)
    k = builder.batches_per_request(8)
    limiter = builder.make_rate_limiter()
    limiter.check_batch(k * 256)  # admitted
    with pytest.raises(ValueError):
        limiter.check_batch((k + 1) * 256)
    assert 1 <= k < 8
    service = D4PGBuilder(tight).make_replay_service(ReplayServiceConfig(Deployment(data_dir=str(tmp_path))))
    with pytest.raises(ProtoError, match="range"):
        service.handle_sample(SampleRequest((k + 1) * 256, 0.1).encode())
    assert service.rejected().get("range") == 1


def test_requests_are_admitted_only_beside_inserts_of_a_whole_actor_batch():
    """A sample of k batches must never be refused while an actor's insert of ``insert_batch`` is
    refused too (both would wait for ever): the learner's k accounts for the insert's size."""
    from curlnav.builder import D4PGBuilder
    from curlnav.config import ExperimentConfig, apply_overrides

    cfg = apply_overrides(ExperimentConfig(), ["replay.samples_per_insert=6", "replay.min_size=1000"])
    builder = D4PGBuilder(cfg)
    k = builder.batches_per_request(4)
    limiter = builder.make_rate_limiter()
    lo, hi = limiter.window
    request, insert = k * 256, cfg.replay.insert_batch
    for error in np.linspace(lo, hi, 401):  # wherever the error stands, one of the two may go on
        limiter.inserts, limiter.samples = 0, -error
        assert limiter.can_insert(10**6, insert) or limiter.can_sample(10**6, request), (k, error)
    big = apply_overrides(ExperimentConfig(), ["d4pg.batch_size=4096", "replay.min_size=4096"])
    assert D4PGBuilder(big).batches_per_request(4) * 4096 <= SampledBatch.MAX_BATCH
