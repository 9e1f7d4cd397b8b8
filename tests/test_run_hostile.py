"""Run bookkeeping, tried as a new user would (issue 35, deliverable 6): a resumed run's summary and
status cover every evaluation of the run, nothing printed names a folder that is not there or a
``None``, hints work from any directory, the budget counts from the start of the command (a resume
with less than a minute left is refused), the learning curve's legend covers no data, and the
README names every bench and every guide page."""

from __future__ import annotations

import csv
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--set", "replay.min_size=200", "--set", "d4pg.batch_size=64", "--set", "replay.samples_per_insert=8",
        "--warmup-steps", "200"]


def _evaluations_in(eval_csv: Path) -> list[int]:
    """The evaluation numbers eval.csv holds in full (every row of the evaluation written)."""
    if not eval_csv.exists():
        return []
    groups: dict[int, list[dict]] = {}
    for row in csv.DictReader(eval_csv.open()):
        groups.setdefault(int(row["evaluation"]), []).append(row)
    return sorted(n for n, rows in groups.items() if len(rows) == int(rows[0]["rows"]))


#: seconds a session's command sleeps before anything else (``delayed``): a clock that started after
#: the interpreter's start-up, as it did before issue 35, lags the command by more than this.
STARTUP_DELAY_S = 3.0
DELAYED = f"import runpy, time; time.sleep({STARTUP_DELAY_S}); runpy.run_module('curlnav.cli', run_name='__main__')"


def delayed(*args: str) -> list[str]:
    """``python -m curlnav.cli ARGS`` that sleeps ``STARTUP_DELAY_S`` first (``sys.argv[1:]`` is ARGS)."""
    return [sys.executable, "-c", DELAYED, *args]


def ctrl_c_heard() -> None:
    """In the launcher's child, before exec: SIGINT at its default. A test runner started in the
    background by a non-interactive shell ignores SIGINT, its children inherit that, and the
    launcher (rightly, as under nohup) keeps a signal it was started ignoring."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt_when(process: subprocess.Popen, done, deadline_s: float, what: str) -> None:
    """Poll ``done()`` until it holds (or the deadline passes, or the launcher exits), then Ctrl-C
    the launcher and wait for its orderly stop."""
    deadline = time.monotonic() + deadline_s
    try:
        while not done():
            if process.poll() is not None:
                raise AssertionError(f"the launcher exited ({process.returncode}) before {what}")
            if time.monotonic() > deadline:
                raise AssertionError(f"no {what} within {deadline_s:.0f} s")
            time.sleep(0.5)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            process.kill()  # its services die with it
            process.wait(timeout=30)


@pytest.fixture(scope="module")
def resumed_run(tmp_path_factory):
    """A distributed run started from another directory with a relative ``--run-dir``: an
    evaluation, Ctrl-C, ``--resume`` (its command sleeping ``STARTUP_DELAY_S`` first), one more
    evaluation than session 1 left (its orderly stop may finish one), Ctrl-C. Returns (cwd, run
    folder, the two sessions' output, the time.time() each session's command was started)."""
    cwd = tmp_path_factory.mktemp("elsewhere")
    args = ["train", "--run-dir", "run", "--actors", "1", *FAST, "--eval-every-s", "5", "--eval-episodes", "2",
            "--minutes", "10"]
    run_dir = cwd / "run"
    outputs, launched = [], []
    for session in (1, 2):
        wanted = 1 if session == 1 else len(_evaluations_in(run_dir / "eval.csv")) + 1
        log = cwd / f"session-{session}.txt"
        with log.open("w") as out:
            launched.append(time.time())
            command = [sys.executable, "-m", "curlnav.cli", *args] if session == 1 else delayed(*args, "--resume")
            process = subprocess.Popen(command, cwd=cwd, stdout=out, stderr=subprocess.STDOUT, preexec_fn=ctrl_c_heard)
            _interrupt_when(process, lambda: len(_evaluations_in(run_dir / "eval.csv")) >= wanted, 300,
                            f"{wanted} evaluations in session {session}")
        outputs.append(log.read_text())
        assert process.returncode == 130, outputs[-1][-3000:]
    return cwd, run_dir, outputs, launched


# -- 1. after --resume, summary.json and status cover every evaluation ------------------------------
@pytest.mark.slow
def test_summary_and_status_after_a_resume_cover_every_evaluation_of_the_run(resumed_run, capsys):
    from curlnav.run.status import finished_summary, format_outcome

    _, run_dir, _, _ = resumed_run
    numbers = _evaluations_in(run_dir / "eval.csv")
    assert len(numbers) >= 2  # at least one of each session
    summary = json.loads((run_dir / "summary.json").read_text())
    assert len(summary["sessions"]) == 2
    assert [e["evaluation"] for e in summary["evals"]] == numbers, (summary["evals"], numbers)
    outcome = format_outcome(run_dir, finished_summary(run_dir))
    assert f"{len(numbers)} evaluations in eval.csv" in outcome, outcome


# -- 2. Ctrl-C before the first evaluation: no policy-best printed ---------------------------------
def _finished(run_dir: Path, **extra) -> dict:
    return {"stop_reason": "interrupted by SIGINT (Ctrl-C)", "exit_code": 130, "elapsed_s": 40.0, "env_steps": 900,
            "updates": 12, "run_dir": str(run_dir), "evals": [], "first_eval_reaching_80": None,
            "sessions": [{"mode": "distributed", "wall_s": 40.0, "stop_reason": "interrupted by SIGINT (Ctrl-C)"}],
            **extra}


def test_ctrl_c_before_the_first_evaluation_names_no_best_policy_that_does_not_exist(tmp_path, capsys):
    from curlnav.run.status import format_outcome
    from curlnav.run.train import _print_evaluations

    run_dir = tmp_path / "run"
    (run_dir / "policy").mkdir(parents=True)
    (run_dir / "policy" / "metadata.json").write_text("{}")
    summary = _finished(run_dir)
    _print_evaluations(summary, run_dir)
    printed = capsys.readouterr().out + "\n" + format_outcome(run_dir, summary)
    assert not (run_dir / "policy-best").exists()
    assert "policy-best" not in printed, printed
    assert printed.count("no best policy yet") == 2, printed
    assert str(run_dir / "policy") in printed  # what exists is still named
    # neither the newest: a run stopped before the learner exported anything
    bare = tmp_path / "bare"
    bare.mkdir()
    _print_evaluations(_finished(bare), bare)
    printed = capsys.readouterr().out
    assert str(bare / "policy") not in printed and "no policy yet" in printed, printed


# -- 3. status never prints None ----------------------------------------------------------------------
def test_status_says_no_policy_yet_instead_of_version_none(tmp_path):
    from curlnav.run.status import format_outcome, format_status

    # the scheduler's /status before the learner and the replay have reported (their keys are None)
    status = {"curriculum": "default", "stage": "train", "stage_index": 0, "substep": 0, "substep_pair": None,
              "epoch": 0, "episodes": 0, "window_success_rate": None, "success_last_100": None, "window_size": 0,
              "criterion": None, "success_by_world_pair": {}, "advances": [], "live_actor_count": 0,
              "live_actors": {},
              "learner": dict.fromkeys(("version", "updates", "updates_per_s", "env_steps", "critic_loss",
                                        "actor_loss", "q_mean", "uptime_s")),
              "replay": dict.fromkeys(("size", "inserted", "accepted", "restored", "insert_rate", "sample_rate",
                                       "rejected", "uptime_s"))}
    text = format_status(status)
    assert "None" not in text, text
    assert "learner: no policy yet" in text, text
    # a finished run whose learner never reported: no "None updates"
    outcome = format_outcome(tmp_path, _finished(tmp_path, updates=None, env_steps=None))
    assert "None" not in outcome, outcome


# -- 4. the hints name the run folder by absolute path ---------------------------------------------
#: the folder ``run`` named relatively: ``run/logs``, ``run;``, ``status run)`` (not ``run folder``, ``--run-dir``,
#: ``in the run``)
RELATIVE_RUN = re.compile(r"(?<![\w/.-])run(?=/|;|\))")


@pytest.mark.slow
def test_printed_hints_name_the_run_folder_by_absolute_path(resumed_run, tmp_path, monkeypatch, capsys):
    from curlnav.run.status import format_outcome
    from curlnav.run.supervise import start_hints
    from curlnav.run.train import _print_evaluations

    _, run_dir, outputs, _ = resumed_run
    # what the launcher printed, started from another directory with --run-dir run
    for output in outputs:
        assert not RELATIVE_RUN.findall(output), output[-3000:]
        assert str(run_dir) in output
    # and the functions behind them, given a relative folder
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run" / "policy-best").mkdir(parents=True)
    (tmp_path / "run" / "policy-best" / "metadata.json").write_text("{}")
    absolute = str(tmp_path / "run")
    lines = start_hints(Path("run"), "http://127.0.0.1:1/status", "http://127.0.0.1:2")
    _print_evaluations(_finished(Path("run")), Path("run"))
    text = "\n".join(lines) + "\n" + capsys.readouterr().out + "\n" + format_outcome(Path("run"), _finished(Path("run")))
    assert absolute in text
    assert not RELATIVE_RUN.findall(text), text


# -- 5. the budget counts from the start of the command ------------------------------------------------
def test_a_resume_with_less_than_a_minute_of_budget_left_is_refused_in_one_line(tmp_path, capsys):
    from curlnav.cli import main

    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "latest.safetensors").write_bytes(b"saved state")
    (run_dir / "summary.json").write_text(json.dumps({"sessions": [{"mode": "serial", "wall_s": 250.0}]}))
    started = time.monotonic()
    assert main(["train", "--serial", "--run-dir", str(run_dir), "--resume", "--minutes", "5"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("curlnav: error: --resume:") and err.count("\n") == 1, err
    assert "0.8 min of its 5 min budget left" in err and "--minutes" in err, err
    assert time.monotonic() - started < 10
    assert not (run_dir / "metrics.csv").exists()  # nothing started


def _session_clock_lag(run_dir: Path, launched: float) -> float:
    """Seconds between a session's command being launched and the session's clock starting: the
    closing summary.json is written as the session's ``wall_s`` is taken."""
    summary = run_dir / "summary.json"
    return (summary.stat().st_mtime - launched) - json.loads(summary.read_text())["sessions"][-1]["wall_s"]


@pytest.mark.slow
def test_the_budget_counts_from_the_start_of_the_command_start_up_included(resumed_run, tmp_path):
    """Each command sleeps ``STARTUP_DELAY_S`` before its imports: the session's clock starts at the
    process's start (``/proc``), so the lag between launching the command and the clock's start is
    only the process's creation, far below 2 s even on a loaded machine; a clock started after the
    start-up (before issue 35) lags by more than ``STARTUP_DELAY_S``."""
    # serial: the interpreter's start-up, imports, the environment, all count
    serial = tmp_path / "serial"
    launched = time.time()
    done = subprocess.run(delayed("train", "--serial", "--run-dir", str(serial), *FAST, "--eval-episodes", "2",
                                  "--threads", "1", "--minutes", "10", "--max-env-steps", "250"),
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    # distributed: the resumed session of the run above (loading, waiting, starting services)
    _, run_dir, _, sessions_launched = resumed_run
    lags = {"serial": _session_clock_lag(serial, launched),
            "distributed, resumed": _session_clock_lag(run_dir, sessions_launched[-1])}
    assert max(lags.values()) < 2.0 < STARTUP_DELAY_S, f"seconds of the command before the session's clock started: {lags}"


# -- 6. the learning curve's legends cover no data ------------------------------------------------------
def test_the_learning_curve_legend_covers_none_of_the_plotted_points(tmp_path, monkeypatch):
    import matplotlib.figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from curlnav.evaluation.plots import plot_learning_curve

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    with (run_dir / "metrics.csv").open("w", newline="") as f:  # success creeping up along the bottom right
        w = csv.DictWriter(f, ["wall_s", "env_steps", "train_success_100", "return_100", "losses/critic"])
        w.writeheader()
        for i in range(60):
            w.writerow({"wall_s": 10.0 * i, "env_steps": 1000 * i, "train_success_100": 0.004 * i,
                        "return_100": -5.0 + 0.2 * i, "losses/critic": 3.0 - 0.04 * i})
    with (run_dir / "eval.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, ["evaluation", "wall_s", "env_steps", "world", "pair", "success_rate", "rows"])
        w.writeheader()
        for n in range(1, 6):
            for pair, rate in (("p1", 0.9), ("p4", 0.05 * n)):
                w.writerow({"evaluation": n, "wall_s": 120.0 * n, "env_steps": 12000 * n, "world": "t-maze-0",
                            "pair": pair, "success_rate": rate, "rows": 2})
    figures = []
    real_savefig = matplotlib.figure.Figure.savefig

    def keep(self, *args, **kwargs):
        figures.append(self)
        return real_savefig(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    out = plot_learning_curve(run_dir)
    assert out.exists() and len(figures) == 1
    fig = figures[0]
    canvas = FigureCanvasAgg(fig)  # drawn again as saved (the crop of bbox_inches moves both alike)
    canvas.draw()
    renderer = canvas.get_renderer()
    legends = [a.get_legend() for a in fig.axes if a.get_legend() is not None] + list(fig.legends)
    assert legends
    lines = [line for a in fig.axes for line in a.get_lines() if not line.get_label().startswith("_")]
    assert any("training success" in line.get_label() for line in lines)
    for legend in legends:
        box = legend.get_window_extent(renderer)
        for line in lines:
            points = line.get_transform().transform(line.get_xydata())
            covered = [p for p in points if box.contains(*p)]
            assert not covered, f"the legend covers {len(covered)} points of {line.get_label()!r}"


# -- 7. the README names every bench and every guide page ------------------------------------------------
def _section(text: str, title: str) -> str:
    return text.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]


def _bench_commands() -> set[str]:
    import argparse

    from curlnav.cli import build_parser

    def subcommands(parser: argparse.ArgumentParser) -> dict:
        return next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    return set(subcommands(subcommands(build_parser())["bench"]))


def test_the_readme_names_every_bench_subcommand_and_links_every_guide_page():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) < 300
    documented = set()
    for row in _section(readme, "Commands").splitlines():
        cell = row.split(" | ", 1)[0]
        for match in re.finditer(r"`curlnav bench ([^`\s]+)", cell):
            documented |= set(match.group(1).split("\\|"))
    benches = _bench_commands()
    assert {"chaos", "actor"} <= benches
    assert not benches - documented, f"curlnav bench {sorted(benches - documented)} missing from the command table"
    read_on = _section(readme, "Read on")
    linked = set(re.findall(r"\(docs/guide/([\w.-]+\.md)[)#]", read_on))
    pages = {p.name for p in (ROOT / "docs" / "guide").glob("*.md")}
    assert "robot.md" in pages
    assert not pages - linked, f"docs/guide pages {sorted(pages - linked)} not linked from README's Read on"


def test_run_dir_help_gives_the_default_the_trainer_uses(monkeypatch):
    from curlnav.cli import build_parser

    train = next(a.choices for a in build_parser()._actions if hasattr(a, "choices") and a.choices
                 and "train" in a.choices)["train"]
    help_text = next(a.help for a in train._actions if "--run-dir" in a.option_strings)
    assert "runs/<date>-<time>-<world>-x<actors>" in help_text, help_text
    from curlnav.run.train import default_run_dir

    assert re.fullmatch(r"runs/\d{8}-\d{6}-open-room-x2", str(default_run_dir("open-room", 2, serial=False)))
    assert re.fullmatch(r"runs/\d{8}-\d{6}-t-maze-0", str(default_run_dir("t-maze:0", 1, serial=True)))
    assert "--serial: runs/<date>-<time>-<world>" in help_text, help_text
