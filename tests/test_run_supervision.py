"""A training run as a user starts, watches, stops and resumes it: nothing starts on a broken
curriculum, one launcher per run folder, crashed services come back, a hang-up leaves no process
behind, and the run folder holds the curves (CSV, TensorBoard, summary) and the policies."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import wait_for

from curlnav.cli import main
from curlnav.run.launch import http_json

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--set", "replay.min_size=200", "--set", "d4pg.batch_size=128", "--set", "replay.samples_per_insert=8",
        "--warmup-steps", "200"]



def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is not alive
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def strict_load(path: Path) -> dict:
    def refuse(name):
        raise ValueError(f"{path} holds {name}, which is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def tensorboard_tags(run_dir: Path) -> set[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tensorboard"))
    acc.Reload()
    return set(acc.Tags()["scalars"])


# -- checked before anything starts ---------------------------------------------------------------
CURRICULA = {
    "unknown key": "name: bad\nstages:\n  - name: S1\n    worlds: [open-room]\n    advence: {success_rate: 0.5, window: 10}\n",
    "wrong world path": "name: bad\nstages:\n  - name: S1\n    worlds: [worlds/no-such-world.yaml]\n",
    "YAML error": "name: bad\nstages:\n  - name: S1\n    worlds: [open-room\n",
    "missing pair": ("name: bad\nstages:\n  - name: S2\n    worlds: [t-maze-0.yaml]\n    substeps: [p1, p5]\n"
                     "    substep_advance: {success_rate: 0.5, window: 50}\n"),
    "top-level typo": "name: bad\nstage:\n  - name: S1\n    worlds: [open-room]\n",
}
EXPECTED = {"unknown key": "unknown keys ['advence']", "wrong world path": "does not load",
            "YAML error": "not valid YAML", "missing pair": "p5 do not exist in world t-maze-0",
            "top-level typo": "non-empty 'stages' list", "missing file": "cannot read curriculum"}


@pytest.mark.parametrize("mistake", [*CURRICULA, "missing file"])
def test_a_curriculum_mistake_ends_with_one_line_and_exit_2_before_any_service_starts(tmp_path, capsys, mistake):
    import shutil

    for suffix in (".yaml", ".pgm"):
        shutil.copy(ROOT / "scheduler" / "curricula" / "worlds" / f"t-maze-0{suffix}", tmp_path / f"t-maze-0{suffix}")
    curriculum = tmp_path / "curriculum.yaml"
    if mistake in CURRICULA:
        curriculum.write_text(CURRICULA[mistake])
    run_dir = tmp_path / "run"
    assert main(["train", "--curriculum", str(curriculum), "--run-dir", str(run_dir), "--minutes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("curlnav: error:") and err.count("\n") == 1, err
    assert EXPECTED[mistake] in err
    assert not run_dir.exists()  # nothing written, nothing started


def test_numbers_out_of_range_are_refused_before_start(tmp_path, capsys):
    assert main(["train", "--minutes", "-1", "--run-dir", str(tmp_path / "run")]) == 2
    assert "budget.minutes must be a positive number" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


# -- the distributed run, supervised -------------------------------------------------------------
@pytest.mark.net
@pytest.mark.slow
def test_distributed_run_restarts_crashed_services_stops_whole_on_sighup_and_resumes_with_its_history(tmp_path):
    run_dir = tmp_path / "run"
    env = {**os.environ, "CURLNAV_CHECKPOINT_EVERY_S": "3"}
    cmd = [sys.executable, "-m", "curlnav.cli", "train", "--world", "open-room", "--run-dir", str(run_dir),
           "--minutes", "20", "--eval-every-s", "15", "--eval-episodes", "3", *FAST]
    log = open(tmp_path / "launcher.log", "wb")
    # as started from a terminal: SIGHUP at its default even when pytest itself runs under nohup (a launcher
    # that inherits an ignored hang-up keeps ignoring it, by design)
    launcher = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
    pids: set[int] = set()
    try:
        info = wait_for("run.json", lambda: (run_dir / "run.json").exists() and json.loads(
            (run_dir / "run.json").read_text()), timeout=60)
        assert info["pid"] == launcher.pid
        pids |= set(info["services"].values())
        status = lambda: http_json(info["status_url"], timeout=3) if True else None  # noqa: E731

        def learning():
            try:
                s = status()
            except OSError:
                return None
            return s if (s["learner"]["version"] or 0) >= 1 and len(s["live_actors"]) == 2 and s["episodes"] > 0 else None

        wait_for("two actors reporting, learner version >= 1", learning, timeout=240)

        # a second launcher on the same folder is refused, before it reads anything
        second = subprocess.run([sys.executable, "-m", "curlnav.cli", "train", "--run-dir", str(run_dir), "--resume"],
                                capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert second.returncode == 2 and "in use by another launcher" in second.stderr, second.stderr
        assert second.stderr.count("\n") == 1

        # a killed actor is restarted
        def services():
            return json.loads((run_dir / "run.json").read_text())["services"]

        old_actor = services()["actor-0"]
        os.kill(old_actor, signal.SIGKILL)
        new_actor = wait_for("actor-0 restarted", lambda: (p := services()["actor-0"]) != old_actor and alive(p) and p,
                             timeout=60)
        pids.add(new_actor)
        wait_for("actor-0 back in /status", lambda: "actor-0" in status()["live_actors"], timeout=120)

        # a killed learner is restarted from its checkpoint
        wait_for("a learner checkpoint", lambda: (run_dir / "learner" / "latest.safetensors").exists(), timeout=60)
        old_learner = services()["learner"]
        os.kill(old_learner, signal.SIGKILL)
        new_learner = wait_for("learner restarted", lambda: (p := services()["learner"]) != old_learner and alive(p)
                               and p, timeout=60)
        pids.add(new_learner)
        learner_log = run_dir / "logs" / "learner.log"
        wait_for("the restarted learner resumed from its checkpoint",
                 lambda: "resumed from" in learner_log.read_text(errors="replace").split("start:")[-1], timeout=120)
        wait_for("an evaluation recorded", lambda: len((run_dir / "eval.csv").read_text().splitlines()) >= 2,
                 timeout=240)
        pids |= set(services().values())
        group = json.loads((run_dir / "run.json").read_text())["process_group"]

        # the terminal closes: every process of the run stops, checkpoint and replay saved, exit 130
        launcher.send_signal(signal.SIGHUP)
        try:  # the stop is bounded by 30 s per role (6 roles, SIGKILL after that), then the curve
            code = launcher.wait(timeout=240)
        except subprocess.TimeoutExpired:
            logs = "".join(f"\n--- {p.name}: " + "\n".join(p.read_text(errors="replace").splitlines()[-8:])
                           for p in sorted((run_dir / "logs").glob("*.log")))
            pytest.fail("the launcher did not exit within 240 s of SIGHUP; its output:\n"
                        + (tmp_path / "launcher.log").read_text(errors="replace")[-3000:] + logs)
        assert code == 130
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)
            launcher.wait()
        log.close()
    output = (tmp_path / "launcher.log").read_text()
    assert "!! actor-0 exited" in output and "!! restarted learner" in output, output[-3000:]
    assert "services stopped in" in output and "killed after not stopping" not in output, output[-3000:]
    wait_for("every process of the run gone", lambda: not any(alive(p) for p in pids), timeout=30)
    with pytest.raises(ProcessLookupError):
        os.killpg(group, 0)
    assert list((run_dir / "replay" / "wal").glob("seg-*.log")) and (run_dir / "learner" / "latest.safetensors").exists()

    summary = strict_load(run_dir / "summary.json")
    assert summary["exit_code"] == 130 and "SIGHUP" in summary["stop_reason"]
    assert summary["sessions"][0]["restarts"] == {"actor-0": 1, "learner": 1}
    tags = tensorboard_tags(run_dir)
    for tag in ("train/success_last_100", "train/return_last_100", "losses/critic", "losses/actor",
                "speed/env_steps_per_s", "speed/updates_per_s", "policy/lag_versions", "replay/size",
                "curriculum/stage", "train/success/open-room/random", "eval/success_rate",
                "eval/success/open-room/held-out"):
        assert tag in tags, f"{tag} not in TensorBoard's tags {sorted(tags)}"
    policy = json.loads((run_dir / "policy" / "metadata.json").read_text())
    assert policy["training"]["env_steps"] > 0 and policy["training"]["learner_steps"] > 0
    assert (run_dir / "policy-best" / "selected.json").exists() and (run_dir / "learning_curve.png").exists()
    rows_before = (run_dir / "metrics.csv").read_text().splitlines()

    # resume: the history goes on, the budget counts the first session
    inserted = summary["env_steps"]
    resumed = subprocess.run([sys.executable, "-m", "curlnav.cli", "train", "--run-dir", str(run_dir), "--resume",
                              "--max-env-steps", str(inserted + 400)],
                             capture_output=True, text=True, timeout=400, cwd=ROOT)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-2000:]
    assert "used before" in resumed.stdout
    summary = strict_load(run_dir / "summary.json")
    assert len(summary["sessions"]) == 2 and summary["sessions"][1]["stop_reason"].startswith("env step budget")
    assert summary["elapsed_s"] > summary["sessions"][0]["wall_s"]
    rows_after = (run_dir / "metrics.csv").read_text().splitlines()
    assert rows_after[:len(rows_before)] == rows_before and len(rows_after) > len(rows_before)
    wall = [float(r.split(",")[0]) for r in rows_after[1:]]
    assert wall == sorted(wall), "the resumed run's clock goes on from the first session's"


@pytest.mark.slow
def test_a_service_that_refuses_its_config_stops_the_run_with_a_nonzero_exit(tmp_path):
    """The learner finds a checkpoint of another network: it exits 2, the run stops (exit 1)
    and the reason is on the console, instead of restarting it forever."""
    from curlnav.builder import D4PGBuilder
    from curlnav.config import resolve_config
    from curlnav.learner.d4pg import save_checkpoint

    run_dir = tmp_path / "run"
    other = resolve_config(overrides=["d4pg.hidden=[64, 64]"])
    (run_dir / "learner").mkdir(parents=True)
    save_checkpoint(D4PGBuilder(other).make_learner_state(), run_dir / "learner" / "latest.safetensors",
                    extra={"version": 3})
    result = subprocess.run([sys.executable, "-m", "curlnav.cli", "train", "--world", "open-room", "--run-dir",
                             str(run_dir), "--resume", "--minutes", "5", *FAST],
                            capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert result.returncode == 1, result.stdout[-3000:] + result.stderr[-2000:]
    assert "learner refused to run (exit 2)" in result.stdout and "another d4pg config" in result.stdout
    summary = strict_load(run_dir / "summary.json")
    assert summary["exit_code"] == 1


# -- the serial run ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_serial_run_stops_on_sigterm_with_exit_130_and_resumes_with_curves_and_policies(tmp_path):
    run_dir = tmp_path / "serial"
    cmd = [sys.executable, "-m", "curlnav.cli", "train", "--serial", "--world", "open-room", "--run-dir", str(run_dir),
           "--eval-episodes", "2", "--eval-every-s", "5", "--minutes", "10", *FAST]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)
    try:
        wait_for("two metrics rows", lambda: (run_dir / "metrics.csv").exists()
                 and len((run_dir / "metrics.csv").read_text().splitlines()) >= 3, timeout=180)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, out.decode()[-3000:]
    summary = strict_load(run_dir / "summary.json")
    assert "SIGTERM" in summary["stop_reason"] and summary["exit_code"] == 130
    steps = summary["env_steps"]
    assert (run_dir / "checkpoints" / "latest.safetensors").exists()
    resumed = subprocess.run(cmd[:-len(FAST)] + ["--resume", "--max-env-steps", str(steps + 300)],
                             capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-2000:]
    summary = strict_load(run_dir / "summary.json")
    assert len(summary["sessions"]) == 2 and summary["env_steps"] >= steps + 300
    assert math.isfinite(summary["elapsed_s"])
    tags = tensorboard_tags(run_dir)
    for tag in ("train/success_last_100", "losses/critic", "speed/env_steps_per_s", "speed/updates_per_s",
                "replay/size", "eval/success_rate", "eval/success/open-room/held-out", "curriculum/stage"):
        assert tag in tags, f"{tag} not in {sorted(tags)}"
    for folder in ("policy", "policy-best"):
        meta = json.loads((run_dir / folder / "metadata.json").read_text())
        assert meta["training"]["env_steps"] > 0
    assert (run_dir / "learning_curve.png").exists() and (run_dir / "eval.csv").exists()


# -- evaluation beside a curriculum ----------------------------------------------------------------
def test_the_evaluator_follows_the_curriculum_evaluates_the_fixed_targets_and_keeps_the_best_on_the_headline(tmp_path):
    from curlnav.builder import D4PGBuilder
    from curlnav.config import resolve_config
    from curlnav.learner.artefact import export_policy
    from curlnav.policy import PolicyArtefact
    from curlnav.run.evaluator import BesideEvaluator, evaluation_plan, targets_for
    from curlnav.run.record import read_csv
    from curlnav.scheduler.curriculum import load_curriculum

    file = ROOT / "scheduler" / "curricula" / "s1+s2.yaml"
    experiment = resolve_config(overrides=[f"curriculum.file={file}", "evaluation.episodes=8",
                                           "evaluation.max_episode_steps=40"])
    curriculum = load_curriculum(file)
    assert [t.pair for t in targets_for(experiment, curriculum, {"stage_index": 0})] == ["held-out"]
    # in S1 the distributed evaluator also measures the curriculum's fixed targets, T-Maze p1..p4
    s1_plan = evaluation_plan(experiment, curriculum, {"stage_index": 0})
    assert [(t.stage, Path(t.world).stem, t.pair) for t in s1_plan] == [
        ("S1", "barn-3x3-0", "held-out"), *[("S1", "t-maze-0", p) for p in ("p1", "p2", "p3", "p4")]]
    targets = evaluation_plan(experiment, curriculum, {"stage_index": 1, "substep": 2})
    assert [(t.stage, t.pair) for t in targets] == [("S2", "p1"), ("S2", "p2"), ("S2", "p3"), ("S2", "p4")]
    # training on p4 alone: p4 is evaluated once, last (the headline), not first
    alone = load_curriculum(ROOT / "scheduler" / "curricula" / "no-curriculum.yaml")
    assert [t.pair for t in evaluation_plan(experiment, alone, {"stage_index": 0})] == ["p1", "p2", "p3", "p4"]
    artefact = export_policy(D4PGBuilder(experiment).make_learner_state(), tmp_path / "v7", experiment.env,
                             worlds=["t-maze-0"], version=7, env_steps=1234)
    evaluator = BesideEvaluator(tmp_path, experiment, curriculum)
    try:
        rows = evaluator.evaluate(PolicyArtefact(artefact), targets)
        evaluator.record(rows, wall_s=60.0, version=7, env_steps=1234, updates=99, artefact=artefact)
        # an evaluation without the headline target (T-Maze p4) never replaces one with it
        s1 = evaluator.evaluate(PolicyArtefact(artefact), targets_for(experiment, curriculum, {"stage_index": 0}))
        evaluator.record([{**s1[0], "success_rate": 1.0}], wall_s=90.0, version=8, env_steps=2000, updates=150,
                         artefact=artefact)
        # a better success on the headline replaces it, whatever the stage
        better = [dict(r) for r in rows]
        better[-1]["success_rate"] = 1.0
        evaluator.record(better, wall_s=120.0, version=9, env_steps=3000, updates=200, artefact=artefact)
    finally:
        evaluator.close()
    written = read_csv(tmp_path / "eval.csv")
    assert [(r["evaluation"], r["pair"]) for r in written[:5]] == [("1", "p1"), ("1", "p2"), ("1", "p3"),
                                                                  ("1", "p4"), ("2", "held-out")]
    assert all(r["episodes"] == "5" and r["env_steps"] == "1234" for r in written[:4])
    selected = json.loads((tmp_path / "policy-best" / "selected.json").read_text())
    assert selected["evaluation"] == 3 and selected["rank"][0] == 1.0 and "t-maze-0/p4" in selected["why"]
    assert (tmp_path / "policy-best" / "actor.onnx").exists()


def test_an_evaluation_cut_short_does_not_hold_back_the_ones_after_it(tmp_path):
    from curlnav.config import resolve_config
    from curlnav.run.record import EVAL_FIELDS, CsvLog, TensorBoardLog
    from curlnav.run.supervise import DistributedRun

    run = DistributedRun(tmp_path / "run", resolve_config(overrides=["evaluation.stop_at_success=0.8"]), actors=1)
    rows = CsvLog(run.run_dir / "eval.csv", EVAL_FIELDS)
    common = {"wall_s": 60.0, "env_steps": 100, "updates": 10, "policy_version": 3, "stage_index": 1, "stage": "S2",
              "substep": 0, "world": "t-maze-0", "episodes": 5, "collisions_per_episode": 0.0,
              "end_effector_collisions_per_episode": 0.0, "mean_time_to_goal_s": 9.0, "rows": 2}
    rows.write({**common, "evaluation": 1, "pair": "p1", "success_rate": 0.2})  # the evaluator died here
    rows.write({**common, "evaluation": 2, "pair": "p1", "success_rate": 0.8})
    board = TensorBoardLog(run.run_dir)
    assert run.read_evaluations(board) is None  # evaluation 2 is not complete yet
    rows.write({**common, "evaluation": 2, "pair": "p2", "success_rate": 1.0})
    rows.close()
    # the stopping target follows the headline target, the evaluation's last row
    assert run.read_evaluations(board) == "held-out success on t-maze-0/p2 100% >= 80%"
    board.close()
    assert [e["evaluation"] for e in run.evals] == [2]
