"""``curlnav train`` (distributed, the default): the launcher that owns a run's services.

It starts router, replay, learner, scheduler, the actors and the evaluator (``curlnav.run.evaluator``)
as one process group (``LocalCluster``), then supervises them every half second, never blocked by
anything else (the scheduler's status is polled in a thread, evaluations run in their own
process):

- a service that exits is noticed at once and its last log lines are printed; an actor (or the
  evaluator) is restarted, a crashed router, replay, learner or scheduler is restarted from its
  saved state (checkpoint, replay log, curriculum state), each within a restart budget
  (``RESTART_BUDGET``); a service that exits 2 (it refused its configuration) or one past its
  budget stops the run with exit code 1 and the reason;
- SIGINT, SIGTERM and SIGHUP stop every service in order (the learner checkpoints; the replay's log already
  holds everything accepted), exit 130;
- the budget (``budget.minutes`` of the run, earlier sessions included, each counted from the start
  of its command, start-up included; or ``budget.max_env_steps`` transitions accepted by the
  replay) or the held-out target ends it with exit 0. A run started from a policy (``init_from``)
  goes on past ``max_env_steps`` until the evaluator has evaluated that policy (``before.json``),
  never past ``budget.minutes``.

The run folder gets ``run.json`` (URLs, pids), ``metrics.csv``, ``eval.csv`` (written by the
evaluator), TensorBoard event files, ``learning_curve.png``, ``summary.json``, ``policy/`` (the
learner's newest artefact) and ``policy-best/`` (the evaluator's best).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from curlnav.bus.transport import STOP_SIGNALS, ignore_stop_signals, on_stop_signals, restore_signals
from curlnav.nav.roles import NETWORK
from curlnav.run import record
from curlnav.run.launch import LocalCluster, http_json, shell_command
from curlnav.run.record import EVAL_FIELDS, TRAIN_FIELDS, CsvLog, RunSummary, TensorBoardLog, copy_policy, now_iso, read_csv

#: restarts allowed per service name before the run stops (an actor, as RLlib restarts env runners)
RESTART_BUDGET = {"actor": 5, "evaluator": 3, "router": 3, "replay": 3, "learner": 3, "scheduler": 3}
EXIT_DONE, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130


def say(line: str) -> None:
    """Print for the person watching; a closed terminal (after SIGHUP) must not stop the shutdown."""
    try:
        print(line, flush=True)
    except (OSError, ValueError):
        pass


def detach_from_terminal() -> None:
    """After a hang-up the terminal is gone: send stdout and stderr to /dev/null so that the
    orderly stop (and the interpreter's last flush) cannot fail on it."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    if os.isatty(1) or os.isatty(2):
        null = os.open(os.devnull, os.O_WRONLY)
        for fd in (1, 2):
            if os.isatty(fd):
                os.dup2(null, fd)
        os.close(null)


def wait_for_earlier_services(group: int | None, timeout_s: float = 60.0) -> None:
    """The services of a launcher that was killed get SIGTERM and may take a few seconds to save
    and exit; its lock is already gone. Wait for its process group to empty before starting
    another set on the same folder (``RunFolderBusy`` if it does not)."""
    from curlnav.run.record import RunFolderBusy

    if not group:
        return
    deadline = time.monotonic() + timeout_s
    announced = False
    while time.monotonic() < deadline:
        try:
            os.killpg(int(group), 0)
        except (ProcessLookupError, PermissionError):
            return
        if not announced:
            say(f"waiting for the services of the previous launcher (process group {group}) to finish saving...")
            announced = True
        time.sleep(0.5)
    raise RunFolderBusy(f"services of an earlier launcher (process group {group}) are still running after "
                        f"{timeout_s:.0f} s: stop them (kill -TERM -{group}) before resuming")


def saved_counts(metrics_csv: Path) -> dict:
    """The counts of a run's last metrics.csv row (env steps, updates, policy version, replay
    size; those it has): where a resumed run's counts start."""
    counts = {}
    for row in read_csv(metrics_csv)[-1:]:
        for key in ("env_steps", "updates", "policy_version", "replay_size"):
            try:
                counts[key] = int(float(row[key]))
            except (KeyError, TypeError, ValueError):
                pass
    return counts


def port_is_free(port: int | None) -> bool:
    if not port:
        return False
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


class StatusPoller(threading.Thread):
    """The scheduler's ``/status`` every ``period_s`` in a thread: ``latest`` is never stale by
    more than a few seconds, and the supervisor never waits on HTTP."""

    def __init__(self, url: str, period_s: float = 2.0) -> None:
        super().__init__(daemon=True, name="status-poller")
        self.url, self.period_s = url, period_s
        self.latest: dict | None = None
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self.latest = http_json(self.url, timeout=2.0)
            except (OSError, ValueError):
                pass
            self.stop.wait(self.period_s)


def start_hints(run_dir: Path, status_url: str, learner_url: str) -> list[str]:
    """What the launcher prints at start: where to watch the run and take its policy, each as a
    command that works without activating the virtual environment (``shell_command``) and from any
    directory (the run folder by absolute path)."""
    run_dir = record.absolute(run_dir)
    return [f"status:  {status_url}   ({shell_command('curlnav', 'status', run_dir)})",
            f"policy:  {learner_url}/policy/latest   ({shell_command('curlnav', 'pull', '--from', learner_url)}); "
            f"newest copy in {run_dir / 'policy'}, best evaluated in {run_dir / 'policy-best'} "
            f"from the first evaluation on",
            f"curves:  {shell_command('tensorboard', '--logdir', run_dir / 'tensorboard')}"]


@dataclass
class RunOutcome:
    exit_code: int
    stop_reason: str
    summary: dict


def run_admin_token(path: Path) -> str:
    """The run's scheduler admin token (the evaluator sends held-out evaluations with it): made
    once (owner-only file), kept across ``--resume``."""
    try:
        return path.read_text().strip()
    except FileNotFoundError:
        import secrets

        token = secrets.token_urlsafe(24)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(token)
        return token


class DistributedRun:
    """One session of a distributed run in ``run_dir`` (see the module docstring)."""

    def __init__(self, run_dir: Path, experiment, actors: int, learner_threads: int = 1,
                 progress_every_s: float = 5.0, started: float | None = None) -> None:
        # the session's clock starts with its command (start-up counts against the budget)
        self.started = time.monotonic() if started is None else started
        self.run_dir = record.absolute(run_dir)
        self.experiment = experiment
        self.actors = actors
        self.progress_every_s = progress_every_s
        self.history = RunSummary(self.run_dir)
        self.elapsed_before_s = self.history.elapsed_before_s
        saved = self._saved_run_json()
        # the evaluator evaluates the newest artefact: export a few times per evaluation period
        export_every_s = min(60.0, max(10.0, experiment.evaluation.every_s / 4))
        self.admin_token_file = self.run_dir / "admin-token"
        self.cluster = LocalCluster(
            self.run_dir, experiment, actors=actors, learner_threads=learner_threads,
            admin_token=run_admin_token(self.admin_token_file),
            extra={"learner": ["--export-every-s", f"{export_every_s:g}"]},
            scheduler_port=saved.get("scheduler_port") if port_is_free(saved.get("scheduler_port")) else None,
            learner_port=saved.get("learner_port") if port_is_free(saved.get("learner_port")) else None)
        self.restarts: dict[str, int] = {}
        self.signal_received: int | None = None
        wait_for_earlier_services(saved.get("process_group"))
        CsvLog(self.run_dir / "eval.csv", EVAL_FIELDS).close()  # the header (an old one moves to .old) first
        self.eval_rows_seen = len(read_csv(self.run_dir / "eval.csv"))
        self.eval_bytes_read = -1  # eval.csv's size at the last read
        self.evals: list[dict] = []  # this session's, as read; summary.json lists the whole run's (eval.csv)
        self.policy_version = -1
        self.last_status: dict | None = None
        self.counts = saved_counts(self.run_dir / "metrics.csv")
        self.before_said = False  # the starting policy's evaluation (init_from) printed
        if experiment.init_from:
            record.record_init_from(self.run_dir, experiment.init_from)

    def _saved_run_json(self) -> dict:
        try:
            return json.loads((self.run_dir / "run.json").read_text())
        except (OSError, ValueError):
            return {}

    # -- bookkeeping -----------------------------------------------------------------------------
    def write_run_json(self) -> None:
        c = self.cluster
        info = {"pid": os.getpid(), "status_url": c.status_url, "learner_url": c.learner_url, "router": c.router,
                "scheduler_port": c.scheduler_port, "learner_port": c.learner_http_port, "process_group": c.pgid,
                "services": {name: p.pid for name, p in c.processes.items()}, "started": now_iso()}
        tmp = self.run_dir / "run.json.tmp"
        tmp.write_text(json.dumps(info, indent=2))
        tmp.replace(self.run_dir / "run.json")

    def wall_s(self) -> float:
        """The run's training wall clock (s), earlier sessions included."""
        return self.elapsed_before_s + time.monotonic() - self.started

    def _on_signal(self, signum, frame) -> None:
        self.signal_received = signum

    def start_evaluator(self) -> None:
        c = self.cluster
        c.spawn("evaluator", [sys.executable, "-m", "curlnav.run.evaluator", "--run-dir", str(self.run_dir),
                              "--config", str(c.config_path), "--learner-url", c.learner_url,
                              "--status-url", c.status_url, "--admin-token-file", str(self.admin_token_file),
                              "--run-started-unix", f"{time.time() - self.wall_s():.3f}"])

    # -- supervision -----------------------------------------------------------------------------
    def handle_exits(self) -> str | None:
        """Restart what exited, within budget; the reason to stop the run otherwise."""
        for name, code in self.cluster.reap():
            role = name.split("-")[0]
            tail = self.cluster.log_tail(name)
            say(f"!! {name} exited with code {code}; last lines of {self.run_dir / 'logs' / (name + '.log')}:")
            for line in tail:
                say(f"   | {line}")
            if code == 2:
                return f"{name} refused to run (exit 2): {tail[-1] if tail else 'see its log'}"
            used = self.restarts.get(name, 0)
            if used >= RESTART_BUDGET.get(role, 0):
                return f"{name} exited with code {code} after {used} restarts (restart budget {RESTART_BUDGET[role]})"
            self.restarts[name] = used + 1
            self.cluster.restart(name)
            self.write_run_json()
            saved = {"learner": "its checkpoint", "replay": "its log", "scheduler": "its curriculum state"}
            say(f"!! restarted {name} ({used + 1} of {RESTART_BUDGET[role]} restarts)"
                + (f", from {saved[role]}" if role in saved else ""))
        return None

    def sync_policy(self) -> None:
        """``policy/``: a copy of the learner's newest artefact, with its true step counts."""
        folder = self.run_dir / "learner" / "artefacts"
        versions = [int(p.name[1:]) for p in folder.glob("v*") if p.name[1:].isdigit() and (p / "metadata.json").exists()]
        if not versions or max(versions) <= self.policy_version:
            return
        version = max(versions)
        try:
            copy_policy(folder / f"v{version}", self.run_dir / "policy",
                        {"why": "the learner's newest artefact", "policy_version": version, "wall_s": self.wall_s()})
            self.policy_version = version
        except OSError:
            pass  # pruned by the learner while copying: the next one comes soon

    def update_counts(self, status: dict) -> dict:
        """The run's counts (env steps, updates, policy version, replay size) from ``status``,
        each carried over from the last known value while its service has not reported yet (a
        resumed run's services report a few seconds after start: its curve must not drop to 0).
        Env steps, updates and the version only grow."""
        learner, replay = status.get("learner") or {}, status.get("replay") or {}
        reported = {"env_steps": replay.get("inserted") or learner.get("env_steps"), "updates": learner.get("updates"),
                    "policy_version": learner.get("version"), "replay_size": replay.get("size")}
        for key, value in reported.items():
            if value is None:
                continue
            known = self.counts.get(key)
            self.counts[key] = int(value) if known is None or key == "replay_size" else max(int(value), known)
        return self.counts

    def record_progress(self, status: dict, rate: dict, metrics: CsvLog, board: TensorBoardLog) -> str | None:
        """One metrics.csv row, TensorBoard scalars, a progress line; a budget reason or None."""
        learner, replay = status.get("learner") or {}, status.get("replay") or {}
        counts = self.update_counts(status)
        env_steps = counts.get("env_steps") or 0
        wall = self.wall_s()
        row = {"wall_s": wall, "env_steps": env_steps, "updates": counts.get("updates"),
               "episodes": status.get("episodes"), "train_success_100": status.get("success_last_100"),
               "return_100": status.get("return_last_100"), "base_collisions_100": status.get("base_collisions_last_100"),
               "env_steps_per_s": replay.get("insert_rate"), "updates_per_s": learner.get("updates_per_s"),
               "losses/critic": learner.get("critic_loss"), "losses/actor": learner.get("actor_loss"),
               "values/q_mean": learner.get("q_mean"), "replay_size": counts.get("replay_size"),
               "policy_version": counts.get("policy_version"), "policy_lag": status.get("policy_lag"),
               "stage_index": status.get("stage_index"), "stage": status.get("stage"), "substep": status.get("substep"),
               "live_actors": status.get("live_actor_count", len(status.get("live_actors") or {})),
               "network_control_share_100": (status.get("control_steps_last_100") or {}).get(NETWORK, 0.0)
               if status.get("control_steps_last_100") else None}
        metrics.write(row)
        scalars = {"train/success_last_100": row["train_success_100"], "train/return_last_100": row["return_100"],
                   "train/base_collisions_last_100": row["base_collisions_100"],
                   "losses/critic": row["losses/critic"], "losses/actor": row["losses/actor"],
                   "values/q_mean": row["values/q_mean"], "speed/env_steps_per_s": row["env_steps_per_s"],
                   "speed/updates_per_s": row["updates_per_s"], "policy/lag_versions": row["policy_lag"],
                   "policy/version": row["policy_version"], "replay/size": row["replay_size"],
                   "curriculum/stage": row["stage_index"], "curriculum/substep": row["substep"],
                   "actors/live": row["live_actors"],
                   **{f"train/control_steps/{role}": share
                      for role, share in (status.get("control_steps_last_100") or {}).items()}}
        for key, value in (status.get("success_by_world_pair") or {}).items():
            world, _, pair = key.rpartition("/")
            done = value.get("episodes") or 0
            before = rate.get(key, (0, 0.0))
            successes = (value.get("success_rate") or 0.0) * done
            if done > before[0]:  # success over the episodes since the last row
                # a world file by its stem; a built-in, FAMILY:SEED or distribution key as it is (a
                # distribution's params hold decimal points, which Path.stem would cut at)
                name = Path(world).stem if world.endswith((".yaml", ".yml")) else world
                scalars[f"train/success/{name}/{pair or 'random'}"] = (successes - before[1]) / (done - before[0])
            rate[key] = (done, successes)
        board.scalars(scalars, env_steps)
        budget = self.experiment.budget
        left_s = budget.minutes * 60 - wall
        success = status.get("success_last_100")
        pair = status.get("substep_pair")
        say(f"[{wall / 60:5.1f} min, {max(left_s, 0) / 60:4.1f} left] stage {status.get('stage')}"
            + (f" sub-step {status.get('substep')} ({pair})" if pair else "")
            + f" | episodes {status.get('episodes')} success {'-' if success is None else f'{success:.0%}'}"
            + f" | env steps {env_steps} ({replay.get('insert_rate') or 0:.0f}/s) updates {row['updates'] or 0}"
            + f" ({learner.get('updates_per_s') or 0:.1f}/s) | policy v{row['policy_version'] or 0}"
            + f" | replay {row['replay_size'] or 0} | actors {row['live_actors']}"
            + (f" | control steps: {record.control_text(status.get('control_steps_last_100'))}"
               if self.experiment.helpers.stack and status.get("control_steps_last_100") else ""))
        if budget.max_env_steps is not None and env_steps >= budget.max_env_steps:
            if self.experiment.init_from and not (self.run_dir / record.BEFORE_FILE).exists():
                return None  # the run's record needs the starting policy's evaluation: the time budget still ends it
            return f"env step budget ({env_steps} >= {budget.max_env_steps})"
        return None

    def say_before(self) -> None:
        """Print the starting policy's evaluation (``before.json``) once it is there."""
        if self.before_said or not self.experiment.init_from:
            return
        try:
            before = json.loads((self.run_dir / record.BEFORE_FILE).read_text())
        except (OSError, ValueError):
            return
        from curlnav.run.evaluator import before_line

        self.before_said = True
        say(before_line(before))

    def read_evaluations(self, board: TensorBoardLog) -> str | None:
        """New eval.csv rows (written by the evaluator): console, TensorBoard, stopping target."""
        path = self.run_dir / "eval.csv"
        size = path.stat().st_size if path.exists() else 0
        if size == self.eval_bytes_read:
            return None  # nothing written since the last look (the supervisor looks twice a second)
        self.eval_bytes_read = size
        rows = read_csv(path)
        by_eval: dict[str, list[dict]] = {}
        for r in rows[self.eval_rows_seen:]:
            try:  # a row the evaluator is still writing is read again next time
                float(r["success_rate"]), float(r["collisions_per_episode"]), float(r["wall_s"])
                float(r["env_steps"]), float(r["policy_version"]), int(r["rows"])
            except (KeyError, TypeError, ValueError):
                break
            by_eval.setdefault(r["evaluation"], []).append(r)
        complete = {}
        numbers = list(by_eval)
        for i, number in enumerate(numbers):
            group = by_eval[number]
            if len(group) < int(group[0]["rows"]):
                if i == len(numbers) - 1:
                    break  # the rest of this evaluation is not written yet
                say(f"[eval {number}] incomplete ({len(group)} of {group[0]['rows']} rows: the evaluator "
                    f"stopped during it); skipped")
                self.eval_rows_seen += len(group)
                continue
            complete[number] = group
            self.eval_rows_seen += len(group)
        by_eval = complete
        reason = None
        for number, group in by_eval.items():
            # the last row is the headline target (the curriculum's last fixed target, e.g. T-Maze
            # p4, or the training world's held-out pairs): the stopping target follows it
            success = float(group[-1]["success_rate"])
            mean = sum(float(r["success_rate"]) for r in group) / len(group)
            first = group[0]
            env_steps = int(float(first.get("env_steps") or 0))
            scalars = {"eval/success_rate": success, "eval/mean_success_rate": mean}
            for r in group:
                scalars[f"eval/success/{r['world']}/{r['pair']}"] = float(r["success_rate"])
                scalars[f"eval/base_collisions_per_episode/{r['world']}/{r['pair']}"] = float(r["collisions_per_episode"])
            board.scalars(scalars, env_steps)
            self.evals.append({"evaluation": int(number), "success_rate": success, "mean_success_rate": mean})
            per_pair = ", ".join(f"{r['world']}/{r['pair']} {float(r['success_rate']):.0%}" for r in group)
            say(f"[eval {number} at {float(first['wall_s']) / 60:5.1f} min, policy v{first['policy_version']}, "
                f"stage {first['stage']}] {group[-1]['world']}/{group[-1]['pair']} {success:.0%}"
                + (f" (all: {per_pair})" if len(group) > 1 else ""))
            target = self.experiment.evaluation.stop_at_success
            if target is not None and success >= target:
                reason = f"held-out success on {group[-1]['world']}/{group[-1]['pair']} {success:.0%} >= {target:.0%}"
        return reason

    # -- the session -----------------------------------------------------------------------------
    def run(self) -> RunOutcome:
        from curlnav.evaluation.plots import plot_learning_curve

        budget = self.experiment.budget
        previous = on_stop_signals(self._on_signal)
        metrics = CsvLog(self.run_dir / "metrics.csv", TRAIN_FIELDS)
        board = TensorBoardLog(self.run_dir)
        session = {"started": now_iso(), "mode": "distributed", "actors": self.actors}
        c = self.cluster
        poller = StatusPoller(c.status_url)
        exit_code, stop_reason = EXIT_DONE, "time budget"
        try:
            c.start()
            self.start_evaluator()
            self.write_run_json()
            say(f"services started ({len(c.processes)} processes, process group {c.pgid}); logs in {self.run_dir / 'logs'}")
            for line in start_hints(self.run_dir, c.status_url, c.learner_url):
                say(line)
            poller.start()
            rate: dict = {}
            last_progress = last_sync = time.monotonic()
            while True:
                if self.signal_received is not None:
                    exit_code, stop_reason = EXIT_INTERRUPTED, f"interrupted by {STOP_SIGNALS[self.signal_received]}"
                    break
                failure = self.handle_exits()
                if failure:
                    exit_code, stop_reason = EXIT_FAILED, failure
                    break
                if self.wall_s() >= budget.minutes * 60:
                    stop_reason = f"time budget ({budget.minutes:g} min)"
                    break
                now = time.monotonic()
                if now - last_progress >= self.progress_every_s and poller.latest is not None:
                    last_progress = now
                    self.last_status = poller.latest
                    reason = self.record_progress(poller.latest, rate, metrics, board)
                    if reason:
                        stop_reason = reason
                        break
                reason = self.read_evaluations(board)
                if reason:
                    stop_reason = reason
                    break
                self.say_before()
                if now - last_sync >= 10.0:
                    self.sync_policy()
                    # the session so far: even a launcher killed outright leaves its history
                    self.history.write({**session, "stop_reason": "running (or the launcher was killed)",
                                        "wall_s": time.monotonic() - self.started}, stop_reason="running",
                                       run_dir=str(self.run_dir), last_status=self.last_status)
                    last_sync = now
                time.sleep(0.5)
        finally:
            say(f"stopping ({stop_reason}): services stop in order, the learner checkpoints...")
            poller.stop.set()
            # a second Ctrl-C must not cut the orderly stop short
            ignore_stop_signals()
            if self.signal_received == signal.SIGHUP:
                detach_from_terminal()
            stop_began = time.monotonic()
            c.stop()
            slowest = sorted(c.stop_report, key=lambda r: -r[1])[:3]
            killed = [name for name, _, was_killed in c.stop_report if was_killed]
            say(f"services stopped in {time.monotonic() - stop_began:.1f} s (slowest: "
                + ", ".join(f"{name} {seconds:.1f} s" for name, seconds, _ in slowest)
                + (f"; !! killed after not stopping in time: {', '.join(killed)}" if killed else "") + ")")
            self.read_evaluations(board)
            self.sync_policy()
            metrics.close()
            board.close()
            try:
                plot_learning_curve(self.run_dir)
            except Exception as exc:  # a picture must never hide the run's outcome
                say(f"learning curve not drawn: {exc}")
            restore_signals(previous)
        status = self.last_status or {}
        session.update({"stopped": now_iso(), "stop_reason": stop_reason, "exit_code": exit_code,
                        "wall_s": time.monotonic() - self.started, "restarts": dict(self.restarts),
                        "env_steps": int(self.update_counts(status).get("env_steps") or 0),
                        "updates": self.counts.get("updates"),
                        "policy_version": self.policy_version})
        summary = self.history.close_session(
            session, stop_reason=stop_reason, exit_code=exit_code, run_dir=str(self.run_dir),
            env_steps=session["env_steps"], updates=session["updates"], last_status=status,
            **record.outcome_fields(self.run_dir))  # every session's evaluations, the policies that exist
        return RunOutcome(exit_code, stop_reason, summary)


def train_distributed(run_dir: str | Path, experiment, actors: int, learner_threads: int = 1,
                      started: float | None = None) -> RunOutcome:
    """``curlnav train``: one supervised session of the distributed run in ``run_dir``; its clock
    starts at ``started`` (``time.monotonic()``; default now)."""
    return DistributedRun(Path(run_dir), experiment, actors, learner_threads, started=started).run()
