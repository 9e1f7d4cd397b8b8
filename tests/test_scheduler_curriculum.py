"""The curriculum file's options beyond the paper: replay of earlier stages, the
learning-progress sampler and fixed evaluation targets; and a curriculum run by the serial
trainer (the ablation instrument)."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from curlnav.scheduler.curriculum import CurriculumError, CurriculumState, load_curriculum

REPLAY = """
name: replay
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.5, window: 2}
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door, p2]
    substep_advance: {success_rate: 0.5, window: 2}
    replay_earlier: 0.25
evaluate:
  - {world: door-corridor, pairs: [p2]}
  - {world: open-room}
"""


def _state(tmp_path, text) -> CurriculumState:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    return CurriculumState(load_curriculum(path))


def test_replay_earlier_sends_its_share_back_to_earlier_tasks_and_they_never_fill_the_window(tmp_path):
    state = _state(tmp_path, REPLAY)
    assert state.curriculum.evaluation_targets() == (("door-corridor", "p2"), ("open-room", ""))
    state.record("open-room", "", True, 0)
    assert state.record("open-room", "", True, 0) and state.current.name == "S2"
    draws = Counter(state.assign() for _ in range(2000))
    assert set(draws) == {("door-corridor", "through-door"), ("open-room", "")}
    assert 0.2 < draws[("open-room", "")] / 2000 < 0.3
    for _ in range(5):  # successes on the replayed S1 task never advance S2
        assert not state.record("open-room", "", True, state.epoch)
    assert state.substep == 0 and not state.window
    state.record("door-corridor", "through-door", True, state.epoch)
    assert state.record("door-corridor", "through-door", True, state.epoch) and state.substep == 1
    draws = Counter(state.assign() for _ in range(2000))  # now S1 and sub-step 1 are the earlier tasks
    assert set(draws) == {("door-corridor", "p2"), ("door-corridor", "through-door"), ("open-room", "")}
    restored = CurriculumState.from_dict(state.curriculum, json.loads(json.dumps(state.to_dict())))
    assert restored.replays == state.replays > 0


def test_replay_draws_follow_the_experiment_seed(tmp_path):
    def draws(seed: int) -> list:
        state = CurriculumState(_state(tmp_path, REPLAY).curriculum, seed=seed)
        state.advance()
        return [state.assign() for _ in range(200)]

    assert draws(0) == draws(0), "the same seed draws the same replays"
    assert draws(0) != draws(1), "two seeds of an ablation must not share their replay draws"


LP = """
name: lp
stages:
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door, p2]
    advance: {success_rate: 0.5, window: 4}
    sampler: learning-progress
"""


def test_learning_progress_favours_the_task_whose_success_is_changing(tmp_path):
    state = _state(tmp_path, LP)
    assert {state.assign() for _ in range(200)} == {("door-corridor", "through-door"), ("door-corridor", "p2")}
    for _ in range(30):  # through-door is being learnt; p2 stays at 0
        state.record("door-corridor", "through-door", True, 0)
        state.record("door-corridor", "p2", False, 0)
    progress = state.task_progress()
    assert progress["door-corridor/through-door"] > 0.3 and progress["door-corridor/p2"] == 0
    draws = Counter(state.assign() for _ in range(2000))
    assert draws[("door-corridor", "through-door")] > 0.8 * 2000  # all but the uniform share's half
    # the stage's criterion watches the last pair (the hardest) alone
    assert state.stage == 0 and list(state.window) == [False] * 4
    restored = CurriculumState.from_dict(state.curriculum, json.loads(json.dumps(state.to_dict())))
    assert restored.task_progress() == pytest.approx(progress)


@pytest.mark.parametrize("body, message", [
    ("stages: [{worlds: [open-room], replay_earlier: 0.3}]", "nothing earlier to replay"),
    ("stages: [{worlds: [open-room]}, {worlds: [open-room], replay_earlier: 1.5}]", "share in [0, 1)"),
    ("stages: [{worlds: [open-room], sampler: bandit}]", "sampler must be one of"),
    ("stages: [{worlds: [open-room], substeps: [a], sampler: learning-progress}]", "at least two tasks"),
    ("stages: [{worlds: [open-room]}]\nevaluate: [{pairs: [p1]}]", "evaluate[0]"),
])
def test_malformed_options_are_refused_naming_the_field(tmp_path, body, message):
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    with pytest.raises(CurriculumError, match=message.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        load_curriculum(path)


def test_an_evaluate_target_naming_a_missing_pair_is_refused_before_the_run(tmp_path):
    from curlnav.scheduler.curriculum import check_curriculum

    path = tmp_path / "c.yaml"
    path.write_text("stages: [{worlds: [open-room]}]\nevaluate: [{world: door-corridor, pairs: [p9]}]\n")
    with pytest.raises(CurriculumError, match="p9"):
        check_curriculum(load_curriculum(path), path)


SERIAL = """
name: tiny
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.0, window: 1}
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door]
evaluate:
  - {world: door-corridor, pairs: [through-door]}
"""


@pytest.mark.slow
def test_serial_trainer_runs_a_curriculum_advances_evaluates_each_target_and_resumes_at_its_stage(tmp_path):
    import csv
    import subprocess
    import sys

    curriculum = tmp_path / "tiny.yaml"
    curriculum.write_text(SERIAL)  # S1 ends after its first episode (>= 0 % over 1)
    run = tmp_path / "run"
    base = [sys.executable, "-m", "curlnav.cli", "train", "--serial", "--run-dir", str(run), "--curriculum",
            str(curriculum), "--warmup-steps", "300", "--eval-episodes", "2", "--threads", "1",
            "--set", "replay.min_size=300", "--minutes", "3"]
    result = subprocess.run(base + ["--max-env-steps", "400"], capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "[curriculum] advanced to S2 sub-step 0" in result.stdout
    rows = list(csv.DictReader((run / "eval.csv").open()))
    assert [(r["stage"], r["world"], r["pair"]) for r in rows] == [("S2", "door-corridor", "through-door")]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["curriculum"]["stage"] == "S2" and summary["curriculum"]["advances"][0]["env_steps"] <= 400
    selected = json.loads((run / "policy-best" / "selected.json").read_text())
    assert selected["target"] == "door-corridor/through-door"
    # the artefact names what it trained on: the curriculum's worlds and stage, not the fallback world
    training = json.loads((run / "policy" / "metadata.json").read_text())["training"]
    assert training["worlds"] == ["open-room", "door-corridor"] and training["curriculum"] == "tiny"
    assert training["curriculum_stage"] == "S2"
    assert json.loads((run / "policy-best" / "metadata.json").read_text())["training"]["worlds"] == training["worlds"]
    # a run killed between an evaluation and its next checkpoint: eval.csv holds an evaluation the
    # checkpoint does not know; the resumed run's evaluations must not reuse its number
    after_checkpoint = {**rows[0], "evaluation": "2"}
    with (run / "eval.csv").open("a", newline="") as f:
        csv.DictWriter(f, fieldnames=list(rows[0])).writerow(after_checkpoint)
    result = subprocess.run(base + ["--max-env-steps", "500", "--resume"], capture_output=True, text=True, timeout=400)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "[curriculum] advanced" not in result.stdout, "a resumed run stays at its stage"
    assert json.loads((run / "summary.json").read_text())["curriculum"]["stage"] == "S2"
    # two-stage fine-tuning: a new run starts from this run's networks; a wrong source is one line, exit 2
    # with another n-step length (a training setting); another width is refused, naming the field
    tuned = subprocess.run(base[:6] + [str(tmp_path / "tuned"), "--world", "door-corridor", "--init-from", str(run),
                                       "--max-env-steps", "300", "--set", "d4pg.n_step=1"] + base[9:],
                           capture_output=True, text=True, timeout=400)
    assert tuned.returncode == 0, tuned.stderr[-2000:]
    assert f"networks from {run / 'checkpoints' / 'latest.safetensors'}" in tuned.stdout
    assert "fine-tuning with d4pg.n_step 5 -> 1" in tuned.stdout
    wider = subprocess.run(base[:6] + [str(tmp_path / "wider"), "--init-from", str(run), "--set", "d4pg.hidden=[64]"]
                           + base[9:], capture_output=True, text=True, timeout=120)
    assert wider.returncode == 2 and "d4pg.hidden (256, 256) vs (64,)" in wider.stderr, wider.stderr[-2000:]
    assert len(wider.stderr.strip().splitlines()) == 1
    bad = subprocess.run(base[:6] + [str(tmp_path / "bad"), "--init-from", str(tmp_path / "nowhere")] + base[9:],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no such file or folder" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    rows = list(csv.DictReader((run / "eval.csv").open()))
    assert len(rows) == 3 and rows[-1]["stage"] == "S2"
    assert [r["evaluation"] for r in rows] == ["1", "2", "3"], "each evaluation keeps a number of its own"


@pytest.mark.slow
def test_ablation_run_trains_each_condition_skips_finished_runs_and_writes_the_report(tmp_path):
    import csv
    import subprocess
    import sys

    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(SERIAL)
    direct = tmp_path / "direct.yaml"
    direct.write_text("name: direct\nstages: [{worlds: [door-corridor], substeps: [through-door]}]\n")
    out = tmp_path / "ablation"
    cmd = [sys.executable, "-m", "curlnav.cli", "ablation", "run", "--out", str(out), "--conditions", str(tiny),
           str(direct), "--seeds", "3", "--max-env-steps", "300", "--parallel", "2",
           "--set", "exploration.warmup_steps=250", "--set", "replay.min_size=256", "--set", "evaluation.episodes=2"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert result.stdout.count(": started (new") == 2 and result.stdout.count(": finished at 300 env steps") == 2
    rows = list(csv.DictReader((out / "ablation.csv").open()))
    assert {(r["condition"], r["seed"], r["env_steps"]) for r in rows} == {("tiny", "3", "300"), ("direct", "3", "300")}
    tiny_row = next(r for r in rows if r["condition"] == "tiny")
    assert tiny_row["stage switches (env steps)"].startswith("S2.0@")
    assert (out / "ablation.png").stat().st_size > 10_000
    assert "held-out success on door-corridor/through-door" in (out / "ablation.md").read_text()
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)  # resumable: nothing left to do
    assert again.returncode == 0 and again.stdout.count("skipped") == 2, again.stdout[-2000:]


@pytest.mark.slow
def test_stopping_ablation_run_with_sigterm_stops_its_training_runs_in_order_and_leaves_none_behind(tmp_path):
    import signal
    import subprocess
    import sys

    from conftest import wait_for

    direct = tmp_path / "direct.yaml"
    direct.write_text("name: direct\nstages: [{worlds: [door-corridor], substeps: [through-door]}]\n")
    out = tmp_path / "ablation"
    cmd = [sys.executable, "-m", "curlnav.cli", "ablation", "run", "--out", str(out), "--conditions", str(direct),
           "--seeds", "0", "--max-env-steps", "100000", "--parallel", "1",
           "--set", "exploration.warmup_steps=250", "--set", "replay.min_size=256", "--set", "evaluation.episodes=2"]
    ablation = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    run = out / "direct-s0"
    try:
        wait_for("the training run's first metrics row", lambda: ablation.poll() is not None or (
            (run / "metrics.csv").exists() and len((run / "metrics.csv").read_text().splitlines()) >= 2), timeout=300)
        assert ablation.poll() is None, "ablation run exited before its training run reported"
        ablation.send_signal(signal.SIGTERM)
        output, _ = ablation.communicate(timeout=180)
    finally:
        if ablation.poll() is None:
            ablation.kill()
            ablation.wait()
    assert ablation.returncode == 130, output[-2000:]
    summary = json.loads((run / "summary.json").read_text())  # the run stopped in order and saved itself
    assert "SIGTERM" in summary["stop_reason"] and (run / "checkpoints" / "latest.safetensors").exists(), summary
    leftovers = subprocess.run(["pgrep", "-f", str(run)], capture_output=True, text=True).stdout.split()
    assert not leftovers, f"training processes left running: {leftovers}"


def test_a_criterion_on_evaluation_ignores_training_episodes_and_advances_on_a_held_out_evaluation(tmp_path):
    state = _state(tmp_path, """
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.7, window: 10, source: evaluation}
  - name: S2
    worlds: [door-corridor]
""")
    for _ in range(50):
        assert not state.record("open-room", "", True, 0), "training episodes never advance it"
    assert not state.record_evaluation(0.9, 5, 0), "fewer held-out episodes than the window"
    assert not state.record_evaluation(0.6, 20, 0)
    assert not state.record_evaluation(0.9, 20, epoch=7), "a policy evaluated under another epoch"
    assert state.record_evaluation(0.7, 20, 0) and state.current.name == "S2"
    assert "held-out success 70% over 20 episodes" in state.history[-1]["reason"]
    assert state.curriculum.to_dict()["stages"][0]["advance"]["source"] == "evaluation"


def test_the_current_steps_rate_counts_only_its_own_rows_weighted_by_episodes(tmp_path):
    from curlnav.config import ExperimentConfig
    from curlnav.run.evaluator import Target, current_step_rate, targets_for

    state = _state(tmp_path, REPLAY)
    state.advance()  # S2, sub-step through-door
    targets = targets_for(ExperimentConfig(), state.curriculum, {"stage_index": 1, "substep": 0})
    targets.append(Target(1, "S2", 0, "open-room", "held-out"))  # a fixed target of another stage
    rows = [{"episodes": 4, "success_rate": 0.5}, {"episodes": 4, "success_rate": 0.0},
            {"episodes": 6, "success_rate": 1.0}]
    assert [t.pair for t in targets] == ["through-door", "p2", "held-out"]
    assert current_step_rate(state.curriculum, targets, rows) == (0.5, 4)


def test_a_learning_progress_stage_ends_at_once_when_its_criterion_holds(tmp_path):
    state = _state(tmp_path, """
stages:
  - name: A
    worlds: [door-corridor]
    substeps: [through-door, p2, p3]
    advance: {success_rate: 0.5, window: 2}
    sampler: learning-progress
  - name: B
    worlds: [open-room]
""")
    state.record("door-corridor", "p3", True, 0)
    assert state.record("door-corridor", "p3", True, 0)
    assert state.current.name == "B" and len(state.history) == 1


def test_a_step_budget_ends_a_stage_whose_success_criterion_never_holds_and_survives_a_resume(tmp_path):
    state = _state(tmp_path, """
stages:
  - name: S1
    worlds: [open-room]
    advance: {success_rate: 0.7, window: 100, max_env_steps: 1000}
  - name: S2
    worlds: [door-corridor]
    substeps: [through-door, p2]
    substep_advance: {success_rate: 0.5, window: 50, compare: ">", max_env_steps: 300}
""")
    assert not state.record("open-room", "", False, 0, steps=200)
    assert not state.record("open-room", "", False, epoch=5, steps=5000), "another epoch's steps never count"
    for _ in range(3):
        assert not state.record("open-room", "", False, 0, steps=200)
    restored = CurriculumState.from_dict(state.curriculum, json.loads(json.dumps(state.to_dict())))
    assert restored.step_env_steps == 800
    assert restored.record("open-room", "", False, 0, steps=200) and restored.current.name == "S2"
    assert "1000 environment steps, the step's budget of 1000" in restored.history[-1]["reason"]
    assert restored.step_env_steps == 0, "the next step's budget starts from zero"
    # sub-steps: the budget of the sub-step criterion; the success criterion still ends one first
    for _ in range(50):
        restored.record("door-corridor", "through-door", True, restored.epoch, steps=1)
    assert restored.substep == 1 and restored.step_env_steps == 0
    # the last sub-step of the last stage has the stage's criterion (none): it never ends
    assert not restored.record("door-corridor", "p2", False, restored.epoch, steps=299)
    assert not restored.record("door-corridor", "p2", False, restored.epoch, steps=1)
    assert state.curriculum.to_dict()["stages"][0]["advance"]["max_env_steps"] == 1000


def test_the_shipped_budget_curriculum_is_the_papers_with_a_250k_step_cap_on_s1():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "scheduler" / "curricula"
    budget, paper = load_curriculum(root / "s1+s2-budget.yaml"), load_curriculum(root / "s1+s2.yaml")
    assert budget.stages[0].advance.max_env_steps == 250_000
    assert budget.stages[0].advance.success_rate == paper.stages[0].advance.success_rate == 0.7
    assert budget.stages[1] == paper.stages[1] and budget.evaluate == paper.evaluate


def test_the_budget_s1_only_differs_from_the_budget_s1_s2_only_in_its_sub_steps():
    """The ablation's "S1 only" at equal budgets: same S1 (250k-step cap), same held-out targets,
    then T-Maze p4 at once instead of p1..p4."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "scheduler" / "curricula"
    s1_only, s1_s2 = load_curriculum(root / "s1-only-budget.yaml"), load_curriculum(root / "s1+s2-budget.yaml")
    assert s1_only.stages[0] == s1_s2.stages[0] and s1_only.evaluate == s1_s2.evaluate
    assert s1_only.stages[1].worlds == s1_s2.stages[1].worlds
    assert list(s1_only.stages[1].substeps) == ["p4"] and list(s1_s2.stages[1].substeps) == ["p1", "p2", "p3", "p4"]


def test_the_budget_replay_curriculum_differs_from_the_budget_s1_s2_only_in_its_s2_replay_share():
    """s1+s2-budget-replay trains S1 exactly as s1+s2-budget (so a run can fork from it at the
    switch) and sends a fifth of S2's assignments back to earlier tasks."""
    import dataclasses
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "scheduler" / "curricula"
    replay, plain = load_curriculum(root / "s1+s2-budget-replay.yaml"), load_curriculum(root / "s1+s2-budget.yaml")
    assert len(replay.stages) == len(plain.stages) == 2
    assert replay.stages[0] == plain.stages[0] and replay.evaluate == plain.evaluate
    assert replay.stages[1].replay_earlier == 0.2 and plain.stages[1].replay_earlier == 0.0
    assert dataclasses.replace(replay.stages[1], replay_earlier=0.0) == plain.stages[1]


@pytest.mark.parametrize("value", ["-5", "1.5", "many", "true"])
def test_a_malformed_step_budget_is_refused_naming_the_field(tmp_path, value):
    path = tmp_path / "bad.yaml"
    path.write_text(f"stages: [{{worlds: [open-room], advance: {{success_rate: 0.7, window: 10, max_env_steps: {value}}}}}]")
    with pytest.raises(CurriculumError, match=r"stages\[0\].advance.max_env_steps must be a whole number"):
        load_curriculum(path)


def test_the_distributed_learners_artefacts_name_the_curriculums_worlds_read_once_at_start(tmp_path):
    """A user pulling a learner artefact sees what it was trained on: the curriculum's stage worlds
    and its name, not the actors' fallback world. The file is read when the learner starts: an
    artefact exported after the file went away still names it."""
    from curlnav.builder import D4PGBuilder
    from curlnav.bus.service import Deployment
    from curlnav.config import resolve_config
    from curlnav.learner.service import LearnerServiceConfig
    from curlnav.run.ablation import CURRICULA

    curriculum = tmp_path / "budget.yaml"
    curriculum.write_text((CURRICULA / "s1+s2-budget.yaml").read_text())
    (tmp_path / "worlds").symlink_to(CURRICULA / "worlds")
    experiment = resolve_config(overrides=["d4pg.batch_size=8", "replay.min_size=8", f"curriculum.file={curriculum}"])
    service = D4PGBuilder(experiment).make_learner_service(LearnerServiceConfig(Deployment(data_dir=str(tmp_path / "learner"))))
    curriculum.unlink()
    training = json.loads((service.export() / "metadata.json").read_text())["training"]
    assert training["worlds"] == ["barn-3x3-0", "t-maze-0"] and training["curriculum"] == "s1+s2-budget"
