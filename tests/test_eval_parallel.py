"""``curlnav eval --jobs N``: the same trials in worker processes, a line per trial as it finishes,
its row in the CSV at once, and Ctrl-C (or a worker's death) that keeps the finished trials."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, assert_one_line_error, die_with_parent, run_curlnav, wait_for

from curlnav.evaluation.compare import Episode
from curlnav.evaluation.parallel import (
    Progress,
    duration_text,
    episode_message,
    episode_of,
    in_run_order,
    outcome,
    time_left_s,
    trial_line,
    units_of,
)

SMALL = ["dwa", "tare-l", "--world", "open-room", "--pairs", "2"]  # 2 agents x 1 world: 2 units
TRIAL = re.compile(r"^trial (\d+)/(\d+), (\S+) left: (.+) on (\S+), pair (\S+), seed (\d+): "
                   r"(success|collision|timeout), ([\d.]+) s, (\d+) contact events$")


def episode(**changes) -> Episode:
    fields = dict(agent="dwa", world="open-room", pair="eval-0", start_x=1.25, start_y=3.65, goal_x=6.55,
                  goal_y=1.65, seed=1_000_003, success=True, time_s=6.2, base_collisions=0, arm_collisions=0,
                  path_length_m=5.6989, shortest_path_m=4.9201, spl=0.8633, base_collision_events=0,
                  trajectory=((1.25, 3.65), (1.5, 3.5)))
    return Episode(**{**fields, **changes})


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# -- the pure part ---------------------------------------------------------------------------------------
def test_units_run_world_by_world_then_agent_by_agent():
    assert [(u.world, u.agent) for u in units_of(2, 3)] == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]


def test_trials_that_finish_in_any_order_come_back_in_the_order_one_process_runs_them():
    finished = {(1, 1): "d", (0, 1): "b", (1, 0): "c", (0, 0): "a"}
    assert in_run_order(finished) == ["a", "b", "c", "d"]


def test_the_time_left_is_the_rate_so_far_times_the_trials_left():
    assert time_left_s(4, 10, 20.0) == pytest.approx(30.0)
    assert np.isnan(time_left_s(0, 10, 5.0))
    assert [duration_text(s) for s in (float("nan"), 0.4, 42, 185, 3725)] == ["?", "0s", "42s", "3m05s", "1h02m"]
    clock = iter([100.0, 110.0, 120.0])
    progress = Progress(4, clock=lambda: next(clock))
    assert progress.line(episode()).startswith("trial 1/4, 30s left: ")
    assert progress.line(episode()).startswith("trial 2/4, 20s left: ")


def test_a_trials_line_names_agent_world_pair_seed_outcome_time_and_contacts():
    line = trial_line(3, 80, 130.0, episode(base_collision_events=2), "success")
    assert line == ("trial 3/80, 2m10s left: dwa on open-room, pair eval-0, seed 1000003: success, 6.2 s, "
                    "2 contact events")
    assert TRIAL.match(line)


def test_a_collision_outranks_the_goal_only_where_it_ends_the_trial():
    touched = episode(base_collisions=3)
    assert outcome(touched, ends_on_collision=True) == "collision"
    assert outcome(touched, ends_on_collision=False) == "success"
    assert outcome(episode(success=False), ends_on_collision=False) == "timeout"


def test_an_episode_crosses_the_pipe_unchanged():
    sent = episode(path_length_m=np.float64(1 / 3), time_s=0.1 * 3,
                   trajectory=tuple((np.float64(x), np.float64(x / 7)) for x in range(5)))
    back = episode_of(json.loads(json.dumps(episode_message(sent))))
    assert back == sent and back.row() == sent.row()


def test_fewer_than_one_job_is_a_one_line_error():
    assert_one_line_error(run_curlnav("eval", "dwa", "--jobs", "0"), "--jobs must be at least 1, got 0")


# -- real processes ----------------------------------------------------------------------------------------
def start(args: list[str], log: Path) -> subprocess.Popen:
    """``curlnav ARGS`` in a process group of its own (its workers join it), output to ``log``."""
    out = open(log, "w")
    proc = subprocess.Popen([sys.executable, "-m", "curlnav.cli", *args], cwd=ROOT, stdout=out,
                            stderr=subprocess.STDOUT, start_new_session=True, preexec_fn=die_with_parent)
    out.close()
    proc.log_path = log
    return proc


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


@pytest.fixture
def processes():
    """Processes started by ``start``; each one's whole group is killed when the test ends."""
    started: list[subprocess.Popen] = []
    yield started
    for proc in started:
        if group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def data_rows(path: Path) -> int:
    return max(0, len(path.read_text().splitlines()) - 1) if path.exists() else 0


@pytest.mark.slow
def test_two_jobs_give_every_trial_as_one_does_each_line_as_it_finishes(tmp_path, processes):
    one = run_curlnav("eval", *SMALL, "--seeds", "3", "--jobs", "1", "--out", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr[-2000:]
    proc = start(["eval", *SMALL, "--seeds", "3", "--jobs", "2", "--out", str(tmp_path / "two")], tmp_path / "two.log")
    processes.append(proc)
    rows = tmp_path / "two" / "episodes.csv"

    def first_line():
        return re.search(r"^trial 1/12, ", proc.log_path.read_text(), re.M)

    wait_for("the first trial's line", first_line, timeout=120, every=0.05)
    assert proc.poll() is None, "the line came only at the end"  # 11 trials still to run
    assert data_rows(rows) >= 1  # its row is in the CSV before its line is printed
    assert proc.wait(180) == 0, proc.log_path.read_text()[-2000:]
    printed = proc.log_path.read_text().splitlines()
    lines = [TRIAL.match(line) for line in printed if line.startswith("trial ")]
    assert all(lines) and [int(m[1]) for m in lines] == list(range(1, 13)), printed
    one_rows, two_rows = read_rows(tmp_path / "one" / "episodes.csv"), read_rows(rows)
    assert two_rows == one_rows  # every column (success, time, collisions, path), in the same order
    by_line = sorted((m[4], m[6], int(m[7]), m[8]) for m in lines)
    by_row = sorted((r["agent"], r["pair"], int(r["seed"]), "success" if r["success"] == "True" else "timeout")
                    for r in one_rows)
    assert by_line == by_row
    assert (tmp_path / "two" / "summary.csv").read_text() == (tmp_path / "one" / "summary.csv").read_text()
    summary = [line.replace("/one/", "/two/") for line in one.stdout.splitlines() if not line.startswith("trial ")]
    assert [line for line in printed if not line.startswith("trial ")][-len(summary):] == summary


@pytest.mark.slow
def test_the_barn_suite_in_two_jobs_scores_every_world_as_one_job(tmp_path):
    args = ["eval", "policies/barn-jackal", "--suite", "barn", "--worlds", "1-2"]  # a unit per world
    one = run_curlnav(*args, "--jobs", "1", "--out", str(tmp_path / "one"), timeout=300)
    two = run_curlnav(*args, "--jobs", "2", "--out", str(tmp_path / "two"), timeout=300)
    assert one.returncode == 0 and two.returncode == 0, (one.stderr[-1500:], two.stderr[-1500:])
    for name in ("barn-trials.csv", "barn-summary.csv"):
        assert (tmp_path / "two" / name).read_text() == (tmp_path / "one" / name).read_text(), name
    assert sum(line.startswith("trial ") for line in two.stdout.splitlines()) == 2
    ends = [line for line in two.stdout.splitlines() if line.startswith("barn: ")]
    assert ends == [line for line in one.stdout.splitlines() if line.startswith("barn: ")]


def run_until_first_row(tmp_path: Path, processes: list) -> tuple[subprocess.Popen, Path, list[int]]:
    """A long two-job eval with --out, once its first trial's row is in the CSV: (process, CSV, workers)."""
    out = tmp_path / "out"
    proc = start(["eval", *SMALL, "--seeds", "20", "--jobs", "2", "--out", str(out)], tmp_path / "run.log")
    processes.append(proc)
    rows = out / "episodes.csv"
    wait_for("the first trial's row", lambda: data_rows(rows) >= 1, timeout=120, procs=[proc], every=0.05)
    workers = children(proc.pid)
    assert len(workers) == 2, workers
    return proc, rows, workers


@pytest.mark.slow
def test_ctrl_c_keeps_the_finished_trials_and_leaves_no_worker(tmp_path, processes):
    proc, rows, workers = run_until_first_row(tmp_path, processes)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) == 130, proc.log_path.read_text()[-2000:]
    printed = proc.log_path.read_text()
    done = re.search(r"^interrupted: (\d+) of 80 trials finished; their rows and summary are in ", printed, re.M)
    assert done, printed[-2000:]
    kept = read_rows(rows)
    assert len(kept) == int(done[1]) >= 1 and "Traceback" not in printed
    assert len(re.findall(r"^trial \d+/80, ", printed, re.M)) == len(kept)
    order = [(r["agent"] != "dwa", int(r["seed"]), r["pair"]) for r in kept]
    assert order == sorted(order)  # rewritten in the order one process runs them
    summary = read_rows(rows.parent / "summary.csv")
    assert sum(int(s["episodes"]) for s in summary if s["world"] == "open-room") == len(kept)
    wait_for("every worker to end", lambda: not group_alive(proc.pid), timeout=10, every=0.1)
    assert not any(Path(f"/proc/{pid}").exists() for pid in workers)


@pytest.mark.slow
def test_a_worker_that_dies_is_named_and_the_finished_trials_are_kept(tmp_path, processes):
    proc, rows, workers = run_until_first_row(tmp_path, processes)
    os.kill(workers[0], signal.SIGKILL)
    assert proc.wait(60) == 2, proc.log_path.read_text()[-2000:]
    error = [line for line in proc.log_path.read_text().splitlines() if line.startswith("curlnav: error: ")]
    assert len(error) == 1, proc.log_path.read_text()[-2000:]
    assert re.search(r"the worker running (dwa|tare-l) on open-room failed: .*; (\d+) of 80 trials finished; "
                     r"their rows and summary are in ", error[0]), error[0]
    finished = int(re.search(r"(\d+) of 80 trials finished", error[0])[1])
    assert len(read_rows(rows)) == finished >= 1
    wait_for("every worker to end", lambda: not group_alive(proc.pid), timeout=10, every=0.1)
