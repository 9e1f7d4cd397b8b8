"""The learner for a GPU (issue 31), on the parts a CPU can check: an update that never waits for
the device computes what the waiting one does; bf16 autocast and compiled networks train the same
networks; a learner or replay host needs no simulator installed."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from conftest import LAYOUT, random_batch

from curlnav.config import D4PGConfig
from curlnav.learner.d4pg import compile_networks, init_state, read_metrics, set_amp, sgd_step


@pytest.mark.slow  # more than 5 s
def test_an_update_that_leaves_its_metrics_on_the_device_computes_the_same_update():
    cfg = D4PGConfig(seed=3, hidden=(64, 64))
    waiting, not_waiting = init_state(cfg, LAYOUT, "cpu"), init_state(cfg, LAYOUT, "cpu")
    for i in range(5):
        _, m_sync, loss_sync = sgd_step(waiting, random_batch(32, seed=i))
        _, m_async, loss_async = sgd_step(not_waiting, random_batch(32, seed=i), sync=False)
    assert isinstance(m_sync["losses/critic"], float) and isinstance(m_async["losses/critic"], torch.Tensor)
    assert read_metrics(m_async) == pytest.approx(m_sync, rel=1e-5)
    assert torch.allclose(loss_async, torch.from_numpy(loss_sync))
    for a, b in zip(waiting.actor.parameters(), not_waiting.actor.parameters()):
        assert torch.equal(a, b)


@pytest.mark.slow  # more than 5 s
def test_bf16_autocast_keeps_the_critic_loss_of_float32_training_within_a_few_percent():
    cfg = D4PGConfig(seed=4, hidden=(64, 64), critic_lr=1e-3)
    losses = {}
    for amp in ("off", "bf16"):
        state = set_amp(init_state(cfg, LAYOUT, "cpu"), amp)
        trace = [sgd_step(state, random_batch(32, seed=i % 4))[1]["losses/critic"] for i in range(40)]
        losses[amp] = sum(trace[-10:]) / 10
        assert trace[-1] < trace[0]  # it learns
    assert abs(losses["bf16"] - losses["off"]) / losses["off"] < 0.05, losses
    with pytest.raises(ValueError, match="amp 'fp8'"):
        set_amp(init_state(cfg, LAYOUT, "cpu"), "fp8")
    with pytest.raises(ValueError, match="compile mode 'fast'"):
        compile_networks(init_state(cfg, LAYOUT, "cpu"), "fast")


@pytest.mark.slow
def test_a_learner_or_replay_host_imports_its_service_without_the_simulator():
    code = ("import sys; import curlnav.learner.service, curlnav.replay.service, curlnav.bench.learner, "
            "curlnav.bench.transport; print('pybullet' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_an_actor_on_onnx_runtime_acts_as_pytorch_does_and_follows_each_new_weights_broadcast():
    import numpy as np
    from safetensors.torch import save

    from curlnav.learner.networks import Actor, BehaviourPolicy

    cfg = D4PGConfig()
    obs = np.random.default_rng(0).uniform(0, 5, (8, LAYOUT.size)).astype(np.float32)
    policies = {b: BehaviourPolicy(LAYOUT, cfg, sigma=0.0, warmup_steps=0, rng=np.random.default_rng(1), inference=b)
                for b in ("onnx", "torch")}
    for seed in (1, 2):  # a first broadcast, then a second with other weights
        torch.manual_seed(seed)
        weights = save({k: v.contiguous() for k, v in Actor(LAYOUT, cfg).state_dict().items()})
        for policy in policies.values():
            policy.load_weights(weights)
        assert policies["onnx"].runner is not None and policies["torch"].runner is None
        batch = {b: p.batch(obs) for b, p in policies.items()}
        single = {b: p(obs[3]) for b, p in policies.items()}
        assert np.allclose(batch["onnx"], batch["torch"], atol=1e-5)
        assert np.allclose(single["onnx"], single["torch"], atol=1e-5)
        assert np.allclose(single["onnx"], batch["onnx"][3], atol=1e-5)
        if seed == 1:
            first = batch["onnx"]
    assert not np.allclose(first, batch["onnx"], atol=1e-3)  # the runner took the second weights
    with pytest.raises(ValueError, match="inference 'tf'"):
        BehaviourPolicy(LAYOUT, cfg, sigma=0.0, warmup_steps=0, rng=np.random.default_rng(1), inference="tf")


def test_eight_environments_per_actor_fit_their_batches_to_the_replays_insert_batch():
    """With the default 8 environments an actor's batch carries 8 n-step tails: a longer n-step
    makes the batches shorter instead of refusing to start; one that cannot fit is refused when
    the config is read, naming the fields."""
    from curlnav.actor.service import ActorServiceConfig
    from curlnav.builder import D4PGBuilder
    from curlnav.config import ConfigError, ExperimentConfig, apply_overrides

    longer = apply_overrides(ExperimentConfig(), ["d4pg.n_step=6"])
    core = D4PGBuilder(longer).make_actor_core(ActorServiceConfig(envs=longer.actor.envs_per_process))
    try:
        assert core.cfg.envs == 8 and core.cfg.batch_steps == 64 - 8 * 6
    finally:
        core.loop.close()
    with pytest.raises(ConfigError, match="actor.envs_per_process x d4pg.n_step"):
        apply_overrides(ExperimentConfig(), ["d4pg.n_step=8"])


def test_an_onnx_actor_taking_broadcast_after_broadcast_does_not_grow():
    """An actor loads new weights about once a second for hours. Each load used to leave 0.8 MB
    behind (protobuf kept every replaced initializer): 9 GB per actor over a 4-hour run. 150 loads
    now keep the process within a few MB (they left about 120 MB)."""
    import numpy as np

    from curlnav.learner.networks import Actor, OnnxActorRunner

    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * 4096 / 2**20

    network = Actor(LAYOUT, D4PGConfig())
    runner = OnnxActorRunner(network)
    obs = np.zeros((8, LAYOUT.size), np.float32)
    state = network.state_dict()
    for _ in range(20):  # warm up allocators
        runner.load(state)
        runner(obs)
    before = rss_mb()
    for _ in range(150):
        runner.load(state)
        runner(obs)
    assert rss_mb() - before < 40, "each weights load leaves memory behind"
