"""Fine-tuning from a shipped policy (``curlnav train --init-from``), in both modes: the networks
start from the artefact's actor, its critic warms up alone first, nobody acts at random, a policy of
another robot or LiDAR is refused before anything is written, and the run records where it started
(the sha256 of the artefact's files) and how that policy did before any update."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import output_of, random_batch, wait_for
from safetensors.torch import load_file

from curlnav.cli import main
from curlnav.config import ConfigError, D4PGConfig, ExperimentConfig, apply_overrides, config_to_dict, resolve_config
from curlnav.layout import ObservationLayout
from curlnav.learner.d4pg import init_state, load_checkpoint, save_checkpoint, sgd_step

ROOT = Path(__file__).resolve().parents[1]
ARTEFACT = ROOT / "policies" / "namo-general"  # a shipped Husky policy: its actor only
JACKAL = ROOT / "policies" / "barn-jackal"
#: a tiny run on open-room: the learner starts after 200 transitions, the budget is 300 (well under
#: the 1000 critic-only updates, so the actor the run exports is still the artefact's)
TINY = ["--world", "open-room", "--init-from", str(ARTEFACT), "--eval-episodes", "2", "--max-env-steps", "300",
        "--minutes", "3", "--set", "replay.min_size=200", "--set", "d4pg.batch_size=128",
        "--set", "replay.samples_per_insert=8"]


def same_tensors(a: Path, b: Path) -> bool:
    x, y = load_file(str(a)), load_file(str(b))
    return x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)


def assert_records_its_start(run: Path) -> dict:
    """summary.json's init_from (the sha256 of every file of the artefact, computed here), before
    (held-out success and collisions of the artefact as it came)."""
    summary = json.loads((run / "summary.json").read_text())
    listed = json.loads((ARTEFACT / "metadata.json").read_text())["files"]
    files = [*listed, "metadata.json"]
    assert summary["init_from"]["path"] == str(ARTEFACT) and summary["init_from"]["kind"] == "artefact"
    assert summary["init_from"]["sha256"] == {name: hashlib.sha256((ARTEFACT / name).read_bytes()).hexdigest()
                                              for name in files}
    before = summary["before"]
    assert before["target"] == "open-room/held-out" and before["episodes"] == 2, before
    assert 0.0 <= before["success_rate"] <= 1.0 and before["collisions_per_episode"] >= 0.0
    return summary


def test_the_critic_learns_alone_while_the_actor_is_frozen_and_a_checkpoint_keeps_the_count(tmp_path):
    state = init_state(dataclasses.replace(D4PGConfig(), hidden=(32,)), ObservationLayout(), "cpu")
    state.actor_frozen_until = 2
    actor = [p.clone() for p in state.actor.parameters()]
    critic = [p.clone() for p in state.critic.parameters()]
    for _ in range(2):
        sgd_step(state, random_batch(16))
    assert all(torch.equal(a, b) for a, b in zip(actor, state.actor.parameters())), "the actor moved in its warm-up"
    assert not all(torch.equal(a, b) for a, b in zip(critic, state.critic.parameters()))
    assert not state.actor_opt.state_dict()["state"], "no Adam moments for a frozen actor"
    restored, _ = load_checkpoint(save_checkpoint(state, tmp_path / "c.safetensors"), "cpu")
    assert restored.actor_frozen_until == 2  # a learner restarted in the warm-up does not restart it
    sgd_step(state, random_batch(16))
    assert not all(torch.equal(a, b) for a, b in zip(actor, state.actor.parameters())), "the actor never started"


def test_a_run_from_a_policy_takes_no_random_warm_up_and_reaches_the_services_by_their_variable():
    with pytest.raises(ConfigError, match="d4pg.critic_warmup_updates must be a whole number"):
        apply_overrides(ExperimentConfig(), ["d4pg.critic_warmup_updates=-1"])
    default = config_to_dict(ExperimentConfig(), for_hash=True)
    assert "init_from" not in default and "critic_warmup_updates" not in default["d4pg"], \
        "every existing config keeps its hash"
    cfg = resolve_config(environ={"CURLNAV_INIT_FROM": "/policies/namo-general"})  # compose's variable
    assert cfg.init_from == "/policies/namo-general"
    assert "init_from" in config_to_dict(cfg, for_hash=True)
    from curlnav.builder import D4PGBuilder

    assert D4PGBuilder(ExperimentConfig()).make_behaviour_policy(0, 2).warmup_steps == 1000
    assert D4PGBuilder(cfg).make_behaviour_policy(0, 2).warmup_steps == 0, "a trained policy acts from its first step"


@pytest.mark.parametrize("mode", [["--serial"], ["--actors", "1"]], ids=["serial", "distributed"])
@pytest.mark.parametrize("source, options, message", [
    (JACKAL, [], "trained for the jackal (0.508 x 0.43 m), not the husky"),
    (JACKAL, ["--robot", "jackal", "--set", "env.lidar_beams=200"], "reads 271 beams, the jackal's LiDAR here gives 200"),
    (ARTEFACT, ["--set", "d4pg.hidden=[64]"], "d4pg.hidden (256, 256) vs (64,)"),
], ids=["jackal-into-husky", "other-beam-count", "other-widths"])
def test_a_policy_of_another_robot_lidar_or_network_is_refused_in_one_line_and_nothing_is_written(
        tmp_path, capsys, mode, source, options, message):
    run = tmp_path / "run"
    assert main(["train", *mode, "--init-from", str(source), *options, "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not run.exists(), "a refused run writes nothing"


def test_an_anchor_without_a_policy_to_start_from_is_refused_in_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--serial", "--world", "open-room", "--set", "d4pg.anchor_weight=0.4", "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    assert "d4pg.anchor_weight (0.4) holds the actor near the policy the run started from: give --init-from" in err
    assert err.count("\n") == 1 and not run.exists()


def test_a_policy_fine_tuned_from_an_artefact_ships_behind_its_stack_and_its_checkpoint_keeps_it(tmp_path):
    """The stack a shipped artefact names (``metadata.json``'s ``"stack"``) is the stack of the
    policies a run started from it exports, and of the runs started from that run's checkpoint."""
    from curlnav.learner.artefact import export_policy
    from curlnav.learner.init_from import inherited_stack
    from curlnav.sim import EnvConfig

    shipped = json.loads((ROOT / "policies" / "namo-robust" / "metadata.json").read_text())["stack"]
    stack = inherited_stack(str(ROOT / "policies" / "namo-robust"))
    assert stack == shipped and inherited_stack(str(ARTEFACT)) is None and inherited_stack("") is None
    state = init_state(D4PGConfig(hidden=(32, 32)), ObservationLayout.from_env_config(EnvConfig()), "cpu")
    folder = export_policy(state, tmp_path / "policy", EnvConfig(), worlds=["open-room"], stack=stack)
    assert json.loads((folder / "metadata.json").read_text())["stack"] == shipped
    save_checkpoint(state, tmp_path / "ckpt.safetensors", extra={"stack": stack})
    assert inherited_stack(str(tmp_path / "ckpt.safetensors")) == shipped


@pytest.mark.slow
def test_a_serial_run_from_a_shipped_artefact_starts_from_its_actor_and_records_before_and_after(tmp_path, capsys):
    """... and trains inside the helpers it is given (``helpers.stack``): the share of control
    steps each part chose is in summary.json."""
    import subprocess

    run = tmp_path / "run"
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "train", "--serial", "--threads", "1", "--run-dir",
                             str(run), *TINY, "--set", "helpers.stack=+rescue+shield"],
                            capture_output=True, text=True, timeout=240, cwd=ROOT)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "a policy artefact ships no critic" in result.stdout and "[before]" in result.stdout
    summary = assert_records_its_start(run)
    assert summary["after"]["evaluation"] == summary["evals"][-1]["evaluation"]
    assert 0 < summary["updates"] < 1000
    steps = summary["sessions"][-1]["control_steps"]  # the session's control steps by chooser
    assert set(steps) <= {"network", "rescue", "shield"} and sum(steps.values()) == summary["env_steps"]
    # the critic's warm-up held the actor: the run's policy is still the artefact's, bit for bit
    assert same_tensors(run / "policy" / "policy.safetensors", ARTEFACT / "policy.safetensors")
    assert main(["status", str(run)]) == 0
    out = capsys.readouterr().out
    assert f"started from {ARTEFACT} (artefact" in out and "before any update: success" in out and "after: success" in out


@pytest.mark.slow
def test_a_distributed_run_from_a_shipped_artefact_starts_the_learner_from_its_actor(tmp_path, curlnav_proc):
    """... and its actors train inside the helpers they are given (``helpers.stack``): each
    episode's control steps by chooser reach the scheduler, metrics.csv and the progress line."""
    run = tmp_path / "run"
    proc = curlnav_proc("train", "--actors", "1", "--threads", "1", "--eval-every-s", "600", "--run-dir", str(run),
                        *TINY, "--set", "helpers.stack=+shield")
    first = run / "learner" / "artefacts" / "v0" / "policy.safetensors"  # the learner's weights before any update
    wait_for("the learner's first artefact", first.is_file, timeout=120, procs=[proc])
    time.sleep(0.5)  # written beside and renamed in: complete once it is there
    assert same_tensors(first, ARTEFACT / "policy.safetensors")
    wait_for("the run to end at its step budget", lambda: proc.poll() is not None, timeout=180)
    out = output_of(proc)
    assert proc.returncode == 0, out[-3000:]
    assert "a policy artefact ships no critic" in out and "[before]" in out, out[-3000:]
    assert "a policy artefact ships no critic" in (run / "logs" / "learner.log").read_text()
    assert_records_its_start(run)
    rows = [r for r in csv.DictReader((run / "metrics.csv").open()) if r.get("episodes") not in (None, "", "0")]
    assert rows and float(rows[0]["train_success_100"]) >= 0.5, "no random warm-up: actors drive from the first step"
    assert "| control steps: network " in out
    assert all(0.0 <= float(r["network_control_share_100"]) <= 1.0 for r in rows)
