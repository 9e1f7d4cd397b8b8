"""What a newcomer trips on, typed as printed: hints that run without an activated virtual
environment, a resume that goes on from its counts, the best policy that also avoids walls,
``curlnav status`` on a finished run, one form for every world argument, labelled config hashes."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import closed_port

ROOT = Path(__file__).resolve().parents[1]


def _first_word_runs(line: str) -> list[str]:
    words = shlex.split(line)
    program = words[0]
    assert os.path.isabs(program), f"{line!r}: {program} is looked up on PATH (no venv there)"
    assert os.path.isfile(program) and os.access(program, os.X_OK), f"{line!r}: {program} is not an executable"
    return words


@pytest.mark.slow
def test_the_launchers_hints_run_as_printed_without_an_activated_virtual_environment(tmp_path):
    from curlnav.run.supervise import start_hints

    lines = start_hints(tmp_path / "run", "http://127.0.0.1:1/status", "http://127.0.0.1:2")
    hints = [line.split("(", 1)[1].rsplit(")", 1)[0] if "(" in line else line.split(":", 1)[1] for line in lines]
    commands = [_first_word_runs(h) for h in hints]
    assert [Path(c[0]).name for c in commands] == ["curlnav", "curlnav", "tensorboard"]
    assert commands[0][1:] == ["status", str(tmp_path / "run")]
    assert commands[1][1:] == ["pull", "--from", "http://127.0.0.1:2"]
    assert commands[2][1:] == ["--logdir", str(tmp_path / "run" / "tensorboard")]
    # typed in a shell whose PATH has no venv: curlnav answers (not "command not found")
    bare = {"PATH": "/usr/bin:/bin", "HOME": os.environ.get("HOME", "/tmp")}
    status = subprocess.run([*commands[0][:1], "--version"], capture_output=True, text=True, env=bare, timeout=120)
    assert status.returncode == 0 and status.stdout.startswith("curlnav"), status.stderr
    assert shutil.which(commands[2][0]) == commands[2][0]


def test_hints_fall_back_to_python_dash_m_where_no_console_script_is_beside_the_interpreter(tmp_path, monkeypatch):
    from curlnav.run.launch import shell_command

    fake = tmp_path / "bin" / "python"
    fake.parent.mkdir()
    fake.symlink_to(os.path.realpath(sys.executable))
    monkeypatch.setattr(sys, "executable", str(fake))
    words = _first_word_runs(shell_command("curlnav", "status", "runs/x"))
    assert words[1:] == ["-m", "curlnav.cli", "status", "runs/x"]


def _row(success: float, collisions: float, world: str = "t-maze-0", pair: str = "p4", episodes: int = 50) -> dict:
    return {"world": world, "pair": pair, "success_rate": success, "collisions_per_episode": collisions,
            "episodes": episodes}


def test_policy_best_prefers_the_policy_that_avoids_walls_at_equal_success():
    from curlnav.run.evaluator import RANKING, best_rank, rank_beats
    from curlnav.scheduler.curriculum import load_curriculum

    curriculum = load_curriculum(ROOT / "scheduler" / "curricula" / "s1+s2.yaml")  # headline: T-Maze p4
    clean = best_rank(curriculum, [_row(0.98, 0.00)])
    bumping = best_rank(curriculum, [_row(1.00, 0.50)])
    # the case a user saw: 100 % with 0.50 contact steps per trial chosen over 98 % with none
    assert rank_beats(clean, bumping) and not rank_beats(bumping, clean)
    # at the same success, fewer collisions win; more success (beyond one episode) still comes first
    assert rank_beats(best_rank(curriculum, [_row(0.9, 0.1)]), best_rank(curriculum, [_row(0.9, 0.2)]))
    assert rank_beats(best_rank(curriculum, [_row(0.9, 3.0)]), best_rank(curriculum, [_row(0.8, 0.0)]))
    # the headline decides: success elsewhere never outranks it
    assert not rank_beats(best_rank(curriculum, [_row(1.0, 0.0, "barn-3x3-0", "held-out")]), clean)
    # a rank saved by an older curlnav (success, mean) is replaced at equal success
    assert rank_beats(clean, [0.98, 0.98]) and not rank_beats(best_rank(curriculum, [_row(0.5, 0.0)]), [0.98, 0.98])
    # without a curriculum the one held-out row is the headline
    assert rank_beats(best_rank(None, [_row(0.98, 0.0, "open-room", "held-out")]),
                      best_rank(None, [_row(1.0, 0.5, "open-room", "held-out")]))
    assert "success" in RANKING and "collisions" in RANKING


def test_selected_json_says_policy_best_ranks_by_success_then_collisions(tmp_path):
    import json

    from curlnav.config import resolve_config
    from curlnav.run.evaluator import RANKING, BesideEvaluator

    artefact = tmp_path / "artefact"
    artefact.mkdir()
    (artefact / "metadata.json").write_text("{}")
    evaluator = BesideEvaluator(tmp_path, resolve_config(), None)
    for version, (success, collisions) in enumerate([(1.0, 0.5), (0.98, 0.0), (1.0, 0.25)], start=1):
        evaluator.record([_row(success, collisions, "open-room", "held-out")], wall_s=60.0 * version,
                         version=version, env_steps=1000 * version, updates=10, artefact=artefact)
    selected = json.loads((tmp_path / "policy-best" / "selected.json").read_text())
    assert selected["policy_version"] == 2 and selected["ranked_by"] == RANKING
    assert selected["rows"][0]["collisions_per_episode"] == 0.0
    # a new evaluator on the folder (a resumed run) keeps that choice
    again = BesideEvaluator(tmp_path, resolve_config(), None)
    again.record([_row(1.0, 0.5, "open-room", "held-out")], wall_s=300.0, version=4, env_steps=4000, updates=10,
                 artefact=artefact)
    assert json.loads((tmp_path / "policy-best" / "selected.json").read_text())["policy_version"] == 2


FINISHED = {"stop_reason": "held-out success on t-maze-0/p4 90% >= 80%", "exit_code": 0, "elapsed_s": 1800.0,
            "env_steps": 123456, "updates": 7890, "run_dir": "x",
            "evals": [{"evaluation": 1, "wall_s": 600.0, "env_steps": 40000, "version": 12, "success_rate": 0.4,
                       "collisions_per_episode": 0.3},
                      {"evaluation": 2, "wall_s": 1700.0, "env_steps": 120000, "version": 40, "success_rate": 0.9,
                       "collisions_per_episode": 0.05}],
            "first_eval_reaching_80": {"wall_s": 1700.0, "env_steps": 120000},
            "sessions": [{"mode": "distributed", "wall_s": 1800.0, "stop_reason": "held-out success"}]}


@pytest.mark.net
def test_status_of_a_finished_run_reports_its_outcome_not_connection_refused(tmp_path, capsys):
    import json

    from curlnav.cli import main

    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"status_url": f"http://127.0.0.1:{closed_port()}/status"}))
    (run / "summary.json").write_text(json.dumps(FINISHED))
    assert main(["status", str(run)]) == 0
    out, err = capsys.readouterr()
    assert "connection refused" not in (out + err).lower() and "still going" not in out + err
    assert f"run {run} has finished: stopped (held-out success on t-maze-0/p4 90% >= 80%), exit code 0" in out
    assert "123456 env steps, 7890 updates" in out and "30.0 min" in out
    assert "last evaluation: success 90%, 0.05 base collisions/episode (policy v40)" in out
    assert main(["status", str(run), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["env_steps"] == 123456
    # a serial run (no scheduler, no run.json) that has finished: its outcome too
    serial = tmp_path / "serial"
    serial.mkdir()
    (serial / "summary.json").write_text(json.dumps({**FINISHED, "final_eval": {"success_rate": 1.0,
                                                                                  "collisions_per_episode": 0.0},
                                                     "sessions": [{"mode": "serial", "wall_s": 60.0}]}))
    assert main(["status", str(serial)]) == 0
    assert "last evaluation: success 100%, 0.00 base collisions/episode" in capsys.readouterr().out
    # still running (the launcher's summary says so) but its scheduler does not answer: the error stays
    (run / "summary.json").write_text(json.dumps({**FINISHED, "stop_reason": "running"}))
    assert main(["status", str(run)]) == 2
    assert "is the run still going?" in capsys.readouterr().err


def test_the_launcher_names_both_config_hashes_and_how_they_differ(tmp_path, capsys, monkeypatch):
    import json
    import re

    import curlnav.run.train as train
    from curlnav.bus.service import ConfigMismatch, check_agreement
    from curlnav.cli import main
    from curlnav.config import config_hash, config_to_dict, resolve_config, service_config_hash
    from curlnav.proto.messages import RunConfig

    monkeypatch.setattr(train, "_train_serial", lambda args, run_dir, experiment: 0)  # the first line is enough
    assert main(["train", "--serial", "--run-dir", str(tmp_path / "run"), "--minutes", "7"]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    experiment = resolve_config(overrides=["budget.minutes=7"], environ={})
    found = re.search(r"experiment config ([0-9a-f]{12}) \(config.yaml\); service-agreement hash ([0-9a-f]{12}) "
                      r"\(the services' logs: the same config without budget, evaluation and actor\)", line)
    assert found, line
    assert found.groups() == (config_hash(experiment)[:12], service_config_hash(experiment)[:12])
    assert not re.search(r"(?<!experiment )config [0-9a-f]{12}", line), f"an unlabelled hash in {line!r}"
    # config show names both as well
    assert main(["config", "show"]) == 0
    shown = capsys.readouterr().out
    assert "# experiment config hash " in shown and "# service-agreement hash " in shown
    # a service that disagrees names the service-agreement hash
    other = resolve_config(overrides=["d4pg.batch_size=64"], environ={})
    reply = RunConfig("learner", "0", service_config_hash(other), json.dumps(config_to_dict(other)))
    try:
        check_agreement(experiment, [reply])
    except ConfigMismatch as exc:
        assert f"runs service-agreement hash {service_config_hash(other)[:12]}" in str(exc)
    else:
        raise AssertionError("no mismatch")


def test_every_world_argument_takes_family_seed_like_eval(tmp_path, capsys, monkeypatch):
    import curlnav.run.train as train
    from curlnav.cli import build_parser, main
    from curlnav.run.launch import build_service
    from curlnav.sim import WorldError, get_world

    world = get_world("t-maze:0")  # the one resolver
    assert world.name == "t-maze-0" and {p.name for p in world.pairs} >= {"p1", "p4"}
    # train, both modes: the world is checked and the run starts (the training itself is not needed here)
    monkeypatch.setattr(train, "_train_serial", lambda args, run_dir, experiment: 0)
    monkeypatch.setattr(train, "_train_distributed", lambda args, run_dir, experiment, actors: 0)
    for mode in (["--serial"], []):
        run = tmp_path / f"run{len(mode)}"
        assert main(["train", *mode, "--world", "t-maze:0", "--run-dir", str(run), "--minutes", "1"]) == 0, \
            capsys.readouterr().err
        assert "world t-maze:0" in capsys.readouterr().out and "t-maze:0" in (run / "config.yaml").read_text()
    # serve: a service builds on it (no network yet)
    service = build_service(build_parser().parse_args(["serve", "replay", "--world", "t-maze:0", "--data-dir",
                                                       str(tmp_path / "svc")]))
    assert service.experiment.curriculum.world == "t-maze:0"
    # rollout and policy run drive in it; worlds show draws it
    assert main(["rollout", "--world", "t-maze:0", "--steps", "3", "--out", str(tmp_path / "roll")]) == 0
    assert "on t-maze-0/" in capsys.readouterr().out
    assert main(["policy", "run", str(ROOT / "policies" / "namo-s1s2"), "--world", "t-maze:0", "--pair", "p1",
                 "--out", str(tmp_path / "drive")]) == 0
    assert "on t-maze-0/p1" in capsys.readouterr().out
    assert main(["worlds", "show", "t-maze:0", "--out", str(tmp_path / "w.png")]) == 0
    # a family that does not exist: one line naming the families
    assert main(["train", "--serial", "--world", "t-mase:0", "--run-dir", str(tmp_path / "bad"), "--minutes", "1"]) == 2
    err = capsys.readouterr().err
    assert "unknown world family 't-mase'" in err and "t-maze" in err
    with pytest.raises(WorldError, match="FAMILY:SEED"):
        get_world("atlantis")


@pytest.mark.slow
def test_a_resumed_distributed_run_goes_on_from_its_counts_not_from_zero(tmp_path):
    import csv
    import re

    run = tmp_path / "run"
    fast = ["--set", "replay.min_size=200", "--set", "d4pg.batch_size=128", "--set", "replay.samples_per_insert=8",
            "--warmup-steps", "200", "--eval-every-s", "600", "--eval-episodes", "2", "--minutes", "6"]
    base = [sys.executable, "-m", "curlnav.cli", "train", "--run-dir", str(run), "--actors", "1"]
    first = subprocess.run(base + ["--max-env-steps", "300", *fast], capture_output=True, text=True, timeout=300,
                           cwd=ROOT)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-2000:]
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    before = rows[-1]
    assert int(before["env_steps"]) >= 300
    resumed = subprocess.run(base + ["--resume", "--max-env-steps", str(int(before["env_steps"]) + 200), "--minutes", "15"],
                             capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-2000:]
    new = list(csv.DictReader((run / "metrics.csv").open()))[len(rows):]
    assert new, "the resumed session wrote no metrics.csv row"
    def count(row: dict, key: str) -> float:
        return float(row.get(key) or 0)  # empty: that service had not reported yet

    keys = ("env_steps", "updates", "policy_version", "replay_size")
    assert count(before, "env_steps") > 0
    for key in keys:
        assert count(new[0], key) >= count(before, key), (key, before, new[0])
    progress = next(line for line in resumed.stdout.splitlines() if line.startswith("[") and "env steps" in line)
    counts = re.search(r"env steps (\d+) .* updates (\d+) .* policy v(\d+) \| replay (\d+)", progress)
    assert counts, progress
    assert all(int(c) >= count(before, k) for c, k in zip(counts.groups(), keys)), (progress, before)


FAKE_DOCKER = """#!/bin/bash
echo "$*" >> "$FAKE_LOG"
case "$1 $2" in
  "ps -aq") left=$(cat "$FAKE_STATE")
           if [ "$left" != 0 ]; then echo c0ffee; [ "$left" = always ] || echo $((left - 1)) > "$FAKE_STATE"; fi ;;
  "volume ls") printf 'curlnav_replay\\ncurlnav_old\\n' ;;
  "volume inspect") [ "$3" != curlnav_scheduler ] ;;
esac
"""


def _remove_stack(tmp_path: Path, containers: str, limit: int) -> tuple[subprocess.CompletedProcess, list[str]]:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "docker").write_text(FAKE_DOCKER)
    (bin_dir / "docker").chmod(0o755)
    (tmp_path / "state").write_text(containers)
    log = tmp_path / "docker.log"
    log.write_text("")
    env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "FAKE_LOG": str(log),
           "FAKE_STATE": str(tmp_path / "state")}
    command = f"set -euo pipefail; source scripts/stack-cleanup.sh; remove_stack curlnav {limit}"
    result = subprocess.run(["bash", "-c", command], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    return result, log.read_text().splitlines()


@pytest.mark.slow
def test_the_smoke_test_removes_the_stack_volumes_after_its_containers_are_gone(tmp_path):
    result, calls = _remove_stack(tmp_path, "1", 60)  # one look still finds a container
    assert result.returncode == 0, result.stdout + result.stderr
    assert calls[0] == "stack rm curlnav"
    removed = [c.split()[-1] for c in calls if c.startswith("volume rm")]
    assert sorted(removed) == ["curlnav_learner", "curlnav_old", "curlnav_replay"]  # scheduler: not there
    last_look = max(i for i, c in enumerate(calls) if c.startswith("ps -aq"))
    assert calls.index(next(c for c in calls if c.startswith("volume rm"))) > last_look
    assert sum(c.startswith("ps -aq") for c in calls) == 2  # waited for the container to go
    # containers that never go: the volumes stay (in use), and it says so with a failure
    result, calls = _remove_stack(tmp_path, "always", 1)
    assert result.returncode == 1 and "still there" in result.stdout
    assert not any(c.startswith("volume rm") for c in calls)
    # the smoke script removes them on its way (and on failure, in its EXIT trap)
    script = (ROOT / "scripts" / "compose-smoke.sh").read_text()
    trap = script[script.index("cleanup() {"):script.index("trap cleanup EXIT")]
    assert "remove_stack curlnav" in trap
    assert "docker stack rm curlnav\n" not in script.split("trap cleanup EXIT")[1]
