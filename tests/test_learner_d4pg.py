"""D4PG core: projection, learning signal, checkpoints, artefacts, the serial trainer."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import random_batch

from curlnav.config import D4PGConfig, ExperimentConfig
from curlnav.layout import ObservationLayout
from curlnav.learner.artefact import export_policy
from curlnav.learner.d4pg import (
    NETWORK_FIELDS,
    TensorBatch,
    act,
    adopt_training_config,
    anchored_copy,
    categorical_projection,
    init_state,
    load_checkpoint,
    save_checkpoint,
    sgd_step,
)
from curlnav.policy import ArtefactError, PolicyArtefact
from curlnav.sim import EnvConfig

LAYOUT = ObservationLayout()


def brute_force_projection(probs, reward, discount, support):
    """Each shifted atom's mass goes to its two neighbours, by linear interpolation, one by one."""
    z = support.tolist()
    dz = z[1] - z[0]
    out = np.zeros(probs.shape)
    for b in range(probs.shape[0]):
        for i, zi in enumerate(z):
            tz = min(max(float(reward[b]) + float(discount[b]) * zi, z[0]), z[-1])
            for j, zj in enumerate(z):
                out[b, j] += max(0.0, 1.0 - abs(tz - zj) / dz) * float(probs[b, i])
    return out


def test_categorical_projection_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    support = torch.linspace(-50.0, 250.0, 51)
    probs = torch.softmax(torch.randn(24, 51, generator=g) * 2, dim=-1)
    reward = torch.cat([torch.randn(20, generator=g) * 60, torch.tensor([400.0, -400.0, 0.0, 3.0])])
    discount = torch.cat([torch.rand(20, generator=g), torch.tensor([0.9, 0.9, 0.0, 1.0])])
    projected = categorical_projection(probs, reward, discount, support)
    assert np.allclose(projected.numpy(), brute_force_projection(probs, reward, discount, support), atol=1e-5)
    assert torch.allclose(projected.sum(-1), torch.ones(24), atol=1e-5)
    # a terminal transition (discount 0) puts all mass around the reward itself
    assert projected[22].argmax().item() == int((0.0 + 50) / 6)
    # the mean is preserved when no shifted atom falls off the support
    inside = (reward[:20] + discount[:20] * -50.0 >= -50.0) & (reward[:20] + discount[:20] * 250.0 <= 250.0)
    assert inside.sum() >= 5
    means = (projected * support).sum(-1)
    expected = reward + discount * (probs * support).sum(-1)
    assert torch.allclose(means[:20][inside], expected[:20][inside], atol=0.3)


@pytest.mark.slow  # more than 5 s
def test_critic_loss_falls_on_a_fixed_batch():
    torch.set_num_threads(2)
    state = init_state(D4PGConfig(seed=1, critic_lr=1e-3, actor_lr=1e-3), LAYOUT, "cpu")
    batch = random_batch()
    # Terminal transitions: the target is the projected n-step return itself, a fixed two-atom
    # distribution, so the cross-entropy can fall far (bootstrapped targets keep an entropy floor).
    batch.discount[:] = 0.0
    batch.reward[:] = torch.linspace(-40, 240, batch.reward.shape[0])
    losses = [sgd_step(state, batch)[1]["losses/critic"] for _ in range(200)]
    assert np.mean(losses[-20:]) < 0.5 * np.mean(losses[:20])
    assert state.steps == 200


@pytest.mark.slow  # more than 5 s
def test_an_actor_pinned_at_its_bounds_is_pulled_back_only_with_the_saturation_penalty():
    """An actor whose outputs sit on tanh's flat ends (linear speed pinned at 0: the stalled BARN
    policy of run 4) gets no gradient from the critic; ``actor_saturation_penalty`` brings its
    pre-tanh outputs back to where the critic can move them."""
    torch.set_num_threads(2)
    batch = random_batch(32)

    def pinned_after_updates(penalty: float) -> float:
        state = init_state(D4PGConfig(seed=4, actor_lr=1e-3, critic_lr=1e-3, actor_saturation_penalty=penalty),
                           LAYOUT, "cpu")
        with torch.no_grad():
            state.actor.head[-1].bias[:] = -12.0  # every action at its low bound
        for _ in range(60):
            _, metrics, _ = sgd_step(state, batch)
        with torch.no_grad():
            return float(state.actor.preactivation(batch.obs).abs().mean()), metrics

    pinned, _ = pinned_after_updates(0.0)
    released, metrics = pinned_after_updates(0.01)
    assert pinned > 10.0, f"without the penalty the pre-tanh outputs moved to {pinned:.1f}"
    assert released < pinned - 2.0, f"with the penalty they stayed at {released:.1f} (without: {pinned:.1f})"
    assert metrics["values/q_mean"] != pytest.approx(-metrics["losses/actor"])  # q_mean is the critic's, not the loss
    with pytest.raises(ValueError, match="actor_saturation_penalty"):
        D4PGConfig(actor_saturation_penalty=-1.0)


@pytest.mark.slow  # more than 5 s
def test_a_fine_tuned_actor_is_held_near_its_start_by_the_anchor_and_the_anchor_survives_a_checkpoint(tmp_path):
    """A critic that pays for the first action fraction pulls an actor to it; with
    ``d4pg.anchor_weight`` the fine-tuned actor stays near the actor it started from (its frozen
    copy, measured on the batch), without it it walks away; the anchor is saved and restored."""
    torch.set_num_threads(2)
    small = ObservationLayout(beams=16, range_frames=2, label_frames=2, goal_frames=2)
    g = torch.Generator().manual_seed(0)
    obs = torch.rand(64, small.size, generator=g) * 5
    action = torch.rand(64, 3, generator=g)
    # the critic learns: more of action 0 pays
    batch = TensorBatch(obs, action, 200.0 * action[:, 0], torch.zeros(64), obs.clone())

    def drift_after_updates(weight: float):
        state = init_state(D4PGConfig(seed=5, actor_lr=1e-3, critic_lr=1e-3, anchor_weight=weight, hidden=(64, 64)),
                           small, "cpu")
        state.anchor = anchored_copy(state.actor)
        start = state.actor(batch.obs).detach()
        for _ in range(80):
            before = float((state.actor(batch.obs).detach() - start).pow(2).sum(-1).mean())
            _, metrics, _ = sgd_step(state, batch)
        if weight:  # the update's drift is the actor's before it
            assert metrics["losses/anchor_drift"] == pytest.approx(before, rel=1e-3)
        return float((state.actor(batch.obs).detach() - start).pow(2).sum(-1).mean()), state, metrics

    free, _, _ = drift_after_updates(0.0)
    held, state, metrics = drift_after_updates(20.0)
    assert free > 0.1, f"without the anchor the actor moved only {free:.3f}"
    assert held < 0.25 * free, f"with the anchor it moved {held:.3f} (without: {free:.3f})"
    path = save_checkpoint(state, tmp_path / "ft.safetensors")
    restored, _ = load_checkpoint(path, "cpu")
    assert restored.anchor is not None and restored.config.anchor_weight == 20.0
    assert torch.equal(restored.anchor(batch.obs), state.anchor(batch.obs))
    assert not any(p.requires_grad for p in restored.anchor.parameters())
    with pytest.raises(ValueError, match="anchor_weight"):
        D4PGConfig(anchor_weight=-1.0)


def test_target_networks_are_hard_copies_every_period():
    state = init_state(D4PGConfig(target_update_period=3, actor_lr=1e-2, critic_lr=1e-2), LAYOUT, "cpu")
    batch = random_batch(8)
    before = [p.clone() for p in state.target_critic.parameters()]
    sgd_step(state, batch)
    sgd_step(state, batch)
    assert all(torch.equal(a, b) for a, b in zip(before, state.target_critic.parameters()))
    sgd_step(state, batch)
    assert all(torch.equal(a, b) for a, b in zip(state.critic.parameters(), state.target_critic.parameters()))


@pytest.mark.slow  # more than 5 s
def test_exploration_noise_stays_inside_the_action_bounds():
    state = init_state(D4PGConfig(), LAYOUT, "cpu")
    obs = np.random.default_rng(0).uniform(0, 10, LAYOUT.size).astype(np.float32)
    rng = np.random.default_rng(0)
    actions = np.stack([act(state.actor, obs, sigma=3.0, rng=rng) for _ in range(200)])
    assert actions[:, 0].min() >= 0 and actions[:, 0].max() <= 1
    assert actions[:, 1].min() >= -1 and actions[:, 1].max() <= 1
    assert actions[:, 2].min() >= 0 and actions[:, 2].max() <= 1
    assert actions.std(0).min() > 0.1


@pytest.mark.slow  # more than 5 s
@pytest.mark.parametrize("preset", ["default", "paper"])
def test_checkpoint_round_trip_restores_networks_and_optimisers(tmp_path, preset):
    state = init_state(dataclasses.replace(ExperimentConfig.preset(preset).d4pg, batch_size=8), LAYOUT, "cpu")
    batch = random_batch(8)
    for _ in range(3):
        sgd_step(state, batch)
    path = save_checkpoint(state, tmp_path / "ckpt.safetensors", extra={"counters": {"env_steps": 7}})
    loaded, extra = load_checkpoint(path, "cpu")
    assert extra == {"counters": {"env_steps": 7}} and loaded.steps == 3
    assert loaded.config == state.config
    for a, b in zip(state.critic.parameters(), loaded.critic.parameters()):
        assert torch.equal(a, b)
    # the next update is identical: the Adam moments came back too
    _, m1, _ = sgd_step(state, batch)
    _, m2, _ = sgd_step(loaded, batch)
    assert m1["losses/critic"] == pytest.approx(m2["losses/critic"], rel=1e-5)
    for a, b in zip(state.actor.parameters(), loaded.actor.parameters()):
        assert torch.allclose(a, b, atol=1e-6)


def test_fine_tuning_takes_another_n_step_and_learning_rate_but_refuses_other_networks(tmp_path):
    """--init-from with d4pg.n_step=1 and new learning rates continues a saved checkpoint's weights
    and Adam moments under the new rates (which survive the next save and load); another network
    width is refused, naming the field."""
    base = dataclasses.replace(ExperimentConfig.preset("default").d4pg, batch_size=8)
    trained = init_state(base, LAYOUT, "cpu")
    sgd_step(trained, random_batch(8))
    state, _ = load_checkpoint(save_checkpoint(trained, tmp_path / "a.safetensors"), "cpu")
    weights = [p.clone() for p in state.actor.parameters()]
    moments = [v["exp_avg"].clone() for v in state.critic_opt.state_dict()["state"].values()]
    tuned = dataclasses.replace(base, n_step=1, actor_lr=3e-5, critic_lr=7e-5)
    changes = adopt_training_config(state, tuned)
    assert state.config == tuned
    assert sorted(changes) == ["d4pg.actor_lr 0.0001 -> 3e-05", "d4pg.critic_lr 0.0001 -> 7e-05", "d4pg.n_step 5 -> 1"]
    assert all(torch.equal(a, b) for a, b in zip(weights, state.actor.parameters()))
    kept = [v["exp_avg"] for v in state.critic_opt.state_dict()["state"].values()]
    assert moments and all(torch.equal(a, b) for a, b in zip(moments, kept)), "the Adam moments carry over"
    sgd_step(state, random_batch(8))  # it trains under the new settings
    again, _ = load_checkpoint(save_checkpoint(state, tmp_path / "b.safetensors"), "cpu")
    assert again.config.n_step == 1
    assert [g["lr"] for g in again.actor_opt.param_groups] == [3e-5]
    assert [g["lr"] for g in again.critic_opt.param_groups] == [7e-5]
    with pytest.raises(ValueError, match=r"d4pg.hidden \(256, 256\) vs \(128,\)"):
        adopt_training_config(state, dataclasses.replace(tuned, hidden=(128,)))


def test_only_the_network_fields_change_the_networks_so_a_fine_tune_never_adopts_another_shape():
    """adopt_training_config takes every D4PG field outside NETWORK_FIELDS from the new config; a
    new field that shapes the networks but is missing from NETWORK_FIELDS would let a fine-tune
    describe networks its weights do not have. Checked by building the networks: each training
    field leaves every weight shape and the return support as they were, each network field changes
    one of them."""
    def networks(**change):
        state = init_state(dataclasses.replace(D4PGConfig(), **change), LAYOUT, "cpu")
        shapes = {k: tuple(v.shape) for net in (state.actor, state.critic) for k, v in net.state_dict().items()}
        return shapes, state.critic.support.tolist()

    training = {"n_step": 2, "discount": 0.9, "batch_size": 3, "actor_lr": 1e-3, "critic_lr": 1e-3,
                "target_update_period": 7, "grad_clip_norm": 1.0, "seed": 5, "preset": "paper",
                "actor_saturation_penalty": 0.01, "critic_warmup_updates": 5, "anchor_weight": 0.1}
    shaping = {"encoder": {"encoder": "conv"}, "pool": {"pool": 8},
               "conv_filters": {"encoder": "conv", "conv_filters": 8}, "hidden": {"hidden": (64,)},
               "atoms": {"atoms": 11}, "v_min": {"v_min": -10.0}, "v_max": {"v_max": 100.0}}
    assert set(D4PGConfig.__dataclass_fields__) == set(training) | set(NETWORK_FIELDS), \
        "sort the new D4PGConfig field into learner.d4pg.NETWORK_FIELDS or this test's training fields"
    assert set(shaping) == set(NETWORK_FIELDS)
    reference = networks()
    for field, value in training.items():
        assert networks(**{field: value}) == reference, f"d4pg.{field} changes the networks"
    conv = networks(encoder="conv")
    for field, change in shaping.items():
        assert networks(**change) != (conv if field == "conv_filters" else reference), f"d4pg.{field} shapes nothing"


def test_artefact_gives_the_same_actions_as_the_live_network(tmp_path):
    state = init_state(D4PGConfig(seed=3), LAYOUT, "cpu")
    sgd_step(state, random_batch(16))
    folder = export_policy(state, tmp_path / "policy", EnvConfig(), worlds=["open-room"], env_steps=123)
    meta = json.loads((folder / "metadata.json").read_text())
    assert meta["observation"]["size"] == 1958 and meta["action"]["scale"] == [1.0, 1.0, 0.5]
    assert meta["training"]["env_steps"] == 123 and set(meta["files"]) == {"actor.onnx", "policy.safetensors"}
    policy = PolicyArtefact(folder)
    obs = np.random.default_rng(0).uniform(0, 10, (32, LAYOUT.size)).astype(np.float32)
    with torch.no_grad():
        live = state.actor(torch.from_numpy(obs)).numpy()
    assert np.allclose(policy(obs), live, atol=1e-5)
    assert np.allclose(policy(obs[0]), live[0], atol=1e-5)


def test_a_tampered_artefact_is_refused(tmp_path):
    state = init_state(D4PGConfig(), LAYOUT, "cpu")
    folder = export_policy(state, tmp_path / "policy", EnvConfig(), worlds=["open-room"])
    with open(folder / "actor.onnx", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ArtefactError, match="sha256"):
        PolicyArtefact(folder)
    with pytest.raises(ArtefactError, match="no metadata.json"):
        PolicyArtefact(tmp_path)


@pytest.mark.slow
def test_serial_training_smoke_run_writes_logs_checkpoint_and_artefact_and_resumes(tmp_path):
    run = tmp_path / "run"
    base = [sys.executable, "-m", "curlnav.cli", "train", "--serial", "--run-dir", str(run), "--max-env-steps", "400",
            "--warmup-steps", "300", "--eval-episodes", "2", "--threads", "1", "--set", "replay.min_size=300"]
    result = subprocess.run(base + ["--minutes", "3"], capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "held-out evaluation: success" in result.stdout
    for name in ("metrics.csv", "eval.csv", "learning_curve.png", "summary.json", "checkpoints/latest.safetensors",
                 "checkpoints/replay.npz", "policy/actor.onnx", "policy/metadata.json"):
        assert (run / name).exists(), name
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env_steps"] == 400 and summary["updates"] > 0
    # resume: counters continue from the checkpoint instead of starting over
    # a budget well above the first session's (the budget counts every session; a resume needs a minute left)
    result = subprocess.run(base[:8] + ["500"] + base[9:] + ["--minutes", "10", "--resume"], capture_output=True,
                            text=True, timeout=400)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "resumed from" in result.stdout
    resumed = json.loads((run / "summary.json").read_text())
    assert resumed["env_steps"] == 500 and resumed["updates"] > summary["updates"]
    # the artefact drives the robot without training code
    out = subprocess.run([sys.executable, "-m", "curlnav.cli", "policy", "run", str(run / "policy"), "--world",
                          "open-room", "--pair", "across", "--out", str(tmp_path / "pics")], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert len(list((tmp_path / "pics").glob("*.png"))) == 1
