"""A comparison's trials in worker processes, a line per trial as it finishes: ``curlnav eval --jobs N``.

The units of work are the comparison's (world, agent) pairs (``Comparison.run_unit``: one agent on
one world's pairs and seeds, in an environment of its own, so its outcomes depend on nothing run
before it). ``run_trials`` runs them in the calling process (one job, or one unit: ``Comparison.run``,
as always) or in the worker processes of a ``WorkerPool`` (``serve``, each in a Python of its own;
``worker_count`` of them), handing the next unit to whichever worker finishes one; it calls
``on_trial`` as each trial finishes and returns the finished trials in the order one process runs
them, also when SIGINT or a failed worker stopped the run. The pool starts before the caller builds
its worlds and agents, so that the workers load meanwhile.

Messages between the processes are JSON lines (nothing is pickled):

- parent -> worker, on its stdin: first the job, ``{"plan": "MODULE:FUNCTION", "options": {...},
  "parent": PID}``: the worker builds the comparison's plan (``ComparisonPlan``) with
  ``FUNCTION(options)``, the function the command built its own with, from the same options, and
  makes each agent once; then a unit at a time, ``{"unit": n, "world": SPEC, "agent": SPEC,
  "label": LABEL, "pairs": [...], "seeds": K, "mcap_agent": NAME}``.
- worker -> parent, on its stdout: ``{"unit": n, "index": i, "episode": {...}}`` per finished trial
  (``episode_message``), ``{"unit": n, "done": true}`` after the unit's last, or ``{"unit": n,
  "error": "..."}`` when it failed (the worker then exits).

A worker ends as soon as its stdin closes, even mid-episode (the parent is done with it, was
interrupted or died); on Linux it also dies with the parent. It ignores SIGINT: a Ctrl-C in a terminal
reaches the whole process group, and the parent decides. Its stderr is the parent's. Thread pools are
one thread in a worker (``OMP_NUM_THREADS=1`` and the like, read as the libraries load): N workers
share N cores instead of fighting over them; outcomes are the same as with one job (checked on the
BARN suite and on NAMO worlds under realistic senses).
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import itertools
import json
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from curlnav.evaluation.compare import Comparison, ComparisonPlan, Episode, mcap_agent_names
from curlnav.sim import StartGoal

#: a worker: SIGINT ignored before anything else loads (a Ctrl-C in a terminal reaches the whole group)
WORKER = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
          "from curlnav.evaluation.parallel import serve; sys.exit(serve())"]
ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
STOP_GRACE_S = 5.0  # a worker told to stop (stdin closed) is killed when still running after this


def default_jobs() -> int:
    """The CPUs this process may use (its affinity mask; every CPU where that is unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


# -- the pure part: units, order, the line per trial ------------------------------------------------
@dataclass(frozen=True)
class Unit:
    """One agent on one world: indices into the plan's ``worlds`` and ``agents``."""

    world: int
    agent: int


def units_of(worlds: int, agents: int) -> list[Unit]:
    """Every unit in the order one process runs them (``Comparison.run``): world by world, and on
    each world agent by agent; a unit's position in this list is its number."""
    return [Unit(w, a) for w in range(worlds) for a in range(agents)]


def in_run_order(finished: dict[tuple[int, int], Episode]) -> list[Episode]:
    """Finished trials keyed by (unit number, the trial's place in its unit: seed by seed, pair by
    pair) in the order one process runs them, whatever order they finished in."""
    return [finished[key] for key in sorted(finished)]


def outcome(episode: Episode, ends_on_collision: bool) -> str:
    """``success``, ``collision`` or ``timeout``. Where a collision ends the trial (the BARN suite)
    it outranks reaching the goal, as the challenge's ``run.py`` decides; elsewhere a collision is
    counted and the trial goes on, so a trial that fails ran out of time."""
    if ends_on_collision and episode.base_collisions > 0:
        return "collision"
    return "success" if episode.success else "timeout"


def time_left_s(done: int, total: int, elapsed_s: float) -> float:
    """Seconds until the last of ``total`` trials finishes at the rate so far (``done`` in
    ``elapsed_s`` s); nan before the first."""
    return elapsed_s / done * (total - done) if done > 0 else float("nan")


def duration_text(seconds: float) -> str:
    """``42s``, ``3m05s``, ``1h02m``; ``?`` for nan."""
    if not math.isfinite(seconds):
        return "?"
    s = max(0, round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def trial_line(done: int, total: int, left_s: float, episode: Episode, result: str) -> str:
    """The line printed as a trial finishes: ``trial 3/80, 2m10s left: AGENT on WORLD, pair P, seed
    S: OUTCOME, T s, N contact events``."""
    return (f"trial {done}/{total}, {duration_text(left_s)} left: {episode.agent} on {episode.world}, pair "
            f"{episode.pair}, seed {episode.seed}: {result}, {episode.time_s:.1f} s, "
            f"{episode.base_collision_events} contact events")


@dataclass
class Progress:
    """Counts finished trials and makes each one's line, with the time left at the rate so far
    (``clock``: seconds, monotonic; started when the progress is made)."""

    total: int
    ends_on_collision: bool = False
    clock: Callable[[], float] = time.monotonic
    done: int = 0
    start: float = field(default=float("nan"))

    def __post_init__(self) -> None:
        self.start = self.clock()

    def line(self, episode: Episode) -> str:
        self.done += 1
        left = time_left_s(self.done, self.total, self.clock() - self.start)
        return trial_line(self.done, self.total, left, episode, outcome(episode, self.ends_on_collision))


def _plain(value):
    """JSON for what ``json`` does not know: numpy scalars and arrays."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON: {type(value).__name__}")


def episode_message(episode: Episode) -> dict:
    """An ``Episode`` as JSON-able data (floats exact: JSON writes them as Python's ``repr``)."""
    return json.loads(json.dumps(dataclasses.asdict(episode), default=_plain))


def episode_of(message: dict) -> Episode:
    """The ``Episode`` of ``episode_message``."""
    return Episode(**{**message, "trajectory": tuple(tuple(point) for point in message["trajectory"])})


def unit_messages(comparison: Comparison, plan: ComparisonPlan) -> list[dict]:
    """Every unit as the message a worker runs it from, numbered as ``units_of``."""
    labels = list(comparison.agents)
    names = mcap_agent_names(labels)
    out = []
    for n, unit in enumerate(units_of(len(plan.worlds), len(plan.agents))):
        world = comparison.worlds[unit.world]
        out.append({"unit": n, "world": plan.worlds[unit.world], "agent": plan.agents[unit.agent],
                    "label": labels[unit.agent], "seeds": plan.seeds, "mcap_agent": names[labels[unit.agent]],
                    "pairs": [dataclasses.asdict(p) for p in comparison.pairs[world.name]]})
    return out


# -- the shell: running the trials, here or in workers -----------------------------------------------
@dataclass
class Trials:
    """A run's trials: ``episodes`` (those that finished, in the order one process runs them) of
    ``total``; ``stopped``: None when all finished, ``"interrupted"`` (SIGINT), else what failed."""

    episodes: list[Episode]
    total: int
    stopped: str | None = None


class WorkerFailed(Exception):
    """A worker failed or died in its unit (``unit``: its number)."""

    def __init__(self, unit: int, reason: str) -> None:
        super().__init__(reason)
        self.unit = unit
        self.reason = reason


def worker_count(jobs: int, plan: ComparisonPlan) -> int:
    """Worker processes for ``jobs`` jobs: none (the trials run in the calling process) for one job
    or one unit, else one per job up to one per unit."""
    units = len(plan.worlds) * len(plan.agents)
    return 0 if jobs <= 1 or units <= 1 else min(jobs, units)


def run_trials(comparison: Comparison, plan: ComparisonPlan, pool: WorkerPool | None = None,
               on_trial: Callable[[Episode], None] | None = None) -> Trials:
    """Every trial of ``comparison`` (made from ``plan``), ``on_trial(episode)`` as each finishes: in
    the workers of ``pool`` when it has any, else here (``Comparison.run``). SIGINT and a failed
    worker stop the run (every worker has ended when this returns): the trials that finished are
    returned, with why it stopped."""
    total = comparison.episode_count(plan.seeds)
    units = units_of(len(plan.worlds), len(plan.agents))
    finished: dict[tuple[int, int], Episode] = {}

    def keep(key: tuple[int, int], episode: Episode) -> None:
        finished[key] = episode
        if on_trial:
            on_trial(episode)

    # a Ctrl-C stops the run even where SIGINT came ignored (a script's background job inherits
    # SIG_IGN and Python then leaves it), as `curlnav train` installs its own handler
    interrupt = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        if pool is None or not pool.workers:
            comparison.run(plan.seeds, on_episode=lambda e: keep((0, len(finished)), e), mcap=plan.mcap,
                           recorder=plan.recorder)
        else:
            pool.run(unit_messages(comparison, plan),
                     lambda unit, index, message: keep((unit, index), episode_of(message)))
    except KeyboardInterrupt:
        return Trials(in_run_order(finished), total, "interrupted")
    except WorkerFailed as failed:
        which = "a worker"
        if 0 <= failed.unit < len(units):
            unit = units[failed.unit]
            which = f"the worker running {list(comparison.agents)[unit.agent]} on {comparison.worlds[unit.world].name}"
        return Trials(in_run_order(finished), total, f"{which} failed: {failed.reason}")
    finally:
        if threading.current_thread() is threading.main_thread() and interrupt is not None:
            signal.signal(signal.SIGINT, interrupt)
    return Trials(in_run_order(finished), total)


class _Worker:
    """One worker process: its pipes, the unit it runs (None when idle) and its last error."""

    def __init__(self, number: int, job: dict, events: queue.Queue) -> None:
        self.number = number
        self.unit: int | None = None
        self.error = ""
        self.proc = subprocess.Popen(WORKER, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     env={**os.environ, **ONE_THREAD})
        threading.Thread(target=self._read, args=(events,), daemon=True).start()
        try:
            self._send({**job, "parent": os.getpid()})
        except (BrokenPipeError, ValueError):
            pass  # it died at once: its stdout closes, and the unit it is given fails

    def _read(self, events: queue.Queue) -> None:
        for line in self.proc.stdout:
            events.put((self.number, line))
        events.put((self.number, None))

    def _send(self, message: dict) -> None:
        self.proc.stdin.write(json.dumps(message, default=_plain) + "\n")
        self.proc.stdin.flush()

    def give(self, message: dict) -> None:
        self.unit = message["unit"]
        try:
            self._send(message)
        except (BrokenPipeError, ValueError):  # it died (its stdin is gone)
            raise WorkerFailed(self.unit, f"its process ended (status {self.proc.wait()})") from None

    def close(self) -> None:
        """Tell it to end (it exits when its stdin closes)."""
        try:
            self.proc.stdin.close()
        except (BrokenPipeError, OSError):
            pass

    def stop(self) -> None:
        """End it: stdin closed, then SIGTERM and SIGKILL if it is still running."""
        self.close()
        try:
            self.proc.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            self.proc.terminate()
            try:
                self.proc.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class WorkerPool:
    """``size`` worker processes, started at once so that they load while the caller builds its
    comparison; each builds the plan with ``plan_function`` (``MODULE:FUNCTION``) from ``options``
    (JSON-able), as the caller built its own. ``run`` hands them units; every worker has ended when
    ``run`` returns or raises, or when the pool closes (a ``with`` block's end)."""

    def __init__(self, plan_function: str, options: dict, size: int) -> None:
        self.events: queue.Queue = queue.Queue()
        self.workers: list[_Worker] = []
        try:
            for number in range(size):
                self.workers.append(_Worker(number, {"plan": plan_function, "options": options}, self.events))
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End every worker (stdin closed, then SIGTERM and SIGKILL for one still running)."""
        for worker in self.workers:
            worker.close()
        for worker in self.workers:
            worker.stop()

    def run(self, units: list[dict], on_episode: Callable[[int, int, dict], None]) -> None:
        """Run every unit message of ``units``, the next to whichever worker finishes one;
        ``on_episode(unit, index, episode message)`` for each trial as it finishes. Raises
        ``WorkerFailed`` when a worker fails or dies; KeyboardInterrupt passes through."""
        todo = deque(units)
        try:
            busy = self.workers[:len(units)]
            for worker in self.workers[len(units):]:
                worker.close()  # more workers than units
            for worker in busy:
                worker.give(todo.popleft())
            running = len(self.workers)
            while running:
                try:
                    number, line = self.events.get(timeout=1.0)
                except queue.Empty:
                    continue
                worker = self.workers[number]
                if line is None:  # its stdout closed: it ended
                    running -= 1
                    status = worker.proc.wait()
                    if worker.unit is not None:
                        raise WorkerFailed(worker.unit, worker.error or f"its process ended (status {status})")
                    continue
                try:
                    message = json.loads(line)
                except ValueError:
                    raise WorkerFailed(worker.unit if worker.unit is not None else -1,
                                       f"it wrote a line that is not a message: {line[:200]!r}") from None
                if "episode" in message:
                    on_episode(message["unit"], message["index"], message["episode"])
                elif message.get("done"):
                    worker.unit = None
                    if todo:
                        worker.give(todo.popleft())
                    else:
                        worker.close()
                elif "error" in message:
                    worker.error = message["error"]
        finally:
            self.close()


def _die_with(parent: int) -> None:
    """On Linux, SIGKILL to this process when ``parent`` dies (``PR_SET_PDEATHSIG``); its end
    before this call is seen too. Elsewhere the closing stdin alone ends a worker."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(1)


class RowStream:
    """A CSV file a row is appended to as each trial finishes (header first, flushed per row), so
    a run stopped by any means leaves every finished trial's row. ``path`` None: writes nothing."""

    def __init__(self, path: str | Path | None, columns: list[str]) -> None:
        self.file = None
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self.file = open(path, "w", newline="")
            self.writer = csv.DictWriter(self.file, fieldnames=columns)
            self.writer.writeheader()
            self.file.flush()

    def write(self, row: dict) -> None:
        if self.file is not None:
            self.writer.writerow(row)
            self.file.flush()

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None

    def __enter__(self) -> RowStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# -- the worker ------------------------------------------------------------------------------------------
def _plan_function(name: str) -> Callable[[dict], ComparisonPlan]:
    """``MODULE:FUNCTION`` of curlnav's own."""
    module, _, function = name.partition(":")
    if not module.startswith("curlnav.") or not function:
        raise ValueError(f"not a curlnav plan function: {name!r}")
    return getattr(importlib.import_module(module), function)


def run_unit(plan: ComparisonPlan, message: dict, send: Callable[[dict], None]) -> None:
    """Run the unit ``message`` of ``plan``, ``send`` a message per finished trial."""
    world = plan.world_of(message["world"])
    label, agent = plan.agent_of(message["agent"])
    if label != message["label"]:
        raise ValueError(f"the worker made the agent {message['agent']} as {label!r}, the command as "
                         f"{message['label']!r}")
    pairs = [StartGoal(**p) for p in message["pairs"]]
    comparison = Comparison({label: agent}, [world], lambda w: pairs, plan.env_config)
    n = message["unit"]
    count = itertools.count()  # the trial's place in its unit: seed by seed, pair by pair
    comparison.run_unit(world, label, agent, message["seeds"],
                        on_episode=lambda e: send({"unit": n, "index": next(count), "episode": episode_message(e)}),
                        mcap=plan.mcap, recorder=plan.recorder, mcap_agent=message["mcap_agent"])


def _warm(job: dict) -> ComparisonPlan | None:
    """The job's plan, with each agent made once, while the parent still builds its comparison (a
    policy's first load in a process runs its checks); None where that fails: the first unit makes
    it again and reports what fails."""
    try:
        plan = _plan_function(job["plan"])(job["options"])
        for spec in plan.agents:
            plan.agent_of(spec)
    except Exception:  # noqa: BLE001 - reported by the unit that needs it
        return None
    return plan


def serve() -> int:
    """A worker's life: the job, then units until stdin closes (``os._exit`` there, mid-unit or not)."""
    channel = os.fdopen(os.dup(1), "w", buffering=1)  # the parent's pipe: messages only
    os.dup2(2, 1)  # anything else printed (a library's print, a C library's) goes to stderr
    sys.stdout = sys.stderr
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lines: queue.Queue = queue.Queue()

    def read() -> None:
        for line in sys.stdin:
            lines.put(line)
        os._exit(0)  # the parent closed our stdin, or died: stop now, whatever runs

    def send(message: dict) -> None:
        channel.write(json.dumps(message, default=_plain) + "\n")
        channel.flush()

    threading.Thread(target=read, daemon=True).start()
    job = json.loads(lines.get())
    _die_with(job["parent"])
    plan = _warm(job)
    while True:
        message = json.loads(lines.get())
        try:
            plan = plan or _plan_function(job["plan"])(job["options"])
            run_unit(plan, message, send)
        except Exception as exc:  # noqa: BLE001 - any failure is reported, with its traceback on stderr
            traceback.print_exc()
            text = " ".join(str(exc).split()) or type(exc).__name__
            send({"unit": message["unit"], "error": f"{type(exc).__name__}: {text}"[:1000]})
            return 1
        send({"unit": message["unit"], "done": True})


if __name__ == "__main__":
    sys.exit(serve())
