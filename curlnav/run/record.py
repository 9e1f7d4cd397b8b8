"""What a run folder records, in both modes: ``metrics.csv`` (training, a row every few
seconds), ``eval.csv`` (held-out evaluations, a row per world and pair), TensorBoard event files
in ``tensorboard/``, ``learning_curve.png``, and ``summary.json`` (strict JSON, one entry per
session so a resume keeps the history). Also the run folder's lock: one launcher per folder.
"""

from __future__ import annotations

import csv
import fcntl
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any

#: metrics.csv columns (both modes; a mode leaves the ones it does not know empty)
TRAIN_FIELDS = ["wall_s", "env_steps", "updates", "episodes", "train_success_100", "return_100",
                "base_collisions_100", "env_steps_per_s", "updates_per_s", "losses/critic", "losses/actor",
                "values/q_mean", "replay_size", "policy_version", "policy_lag", "stage_index", "stage", "substep",
                "live_actors"]
#: eval.csv columns: one row per (evaluation, world, pair); pair "held-out" is the held-out draw
EVAL_FIELDS = ["evaluation", "wall_s", "env_steps", "updates", "policy_version", "stage_index", "stage", "substep",
               "world", "pair", "episodes", "success_rate", "collisions_per_episode",
               "end_effector_collisions_per_episode", "mean_time_to_goal_s", "rows"]  # rows: of this evaluation


class RunFolderBusy(ValueError):
    """Another launcher holds the run folder (exit 2, one line)."""


class RunLock:
    """An exclusive ``flock`` on ``<run_dir>/.lock`` for as long as this process runs: a second
    launcher on the same folder is refused. The kernel drops the lock when the process dies, so
    a crashed launcher never leaves a stale lock."""

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / ".lock"
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise RunFolderBusy(f"run folder {self.path.parent} is in use by another launcher (pid {holder}): "
                                f"stop it first, or choose another --run-dir") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        self._fd = fd
        return self

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


class CsvLog:
    """Append-only CSV with a fixed header, flushed at every row. Appends to an existing file
    (a resumed run continues its history); a file with another header is kept as ``.old``."""

    def __init__(self, path: Path, fields: list[str]) -> None:
        self.path = path
        self.fields = fields
        if path.exists():
            with open(path, newline="") as f:
                header = next(csv.reader(f), None)
            if header != fields:
                path.replace(path.with_suffix(path.suffix + ".old"))
        new = not path.exists()
        self._file = open(path, "a", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=fields, extrasaction="ignore")
        if new:
            self._writer.writeheader()

    def write(self, row: dict) -> None:
        self._writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()
                               if v is not None})
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def last_evaluation_number(eval_csv: Path) -> int:
    """The highest ``evaluation`` number in an eval.csv (0 when there is none): a resumed run's
    evaluations continue after it, whichever process writes them."""
    return max((int(r["evaluation"]) for r in read_csv(eval_csv) if r.get("evaluation", "").isdigit()), default=0)


class TensorBoardLog:
    """Scalars in TensorBoard event files under ``<run_dir>/tensorboard`` (step: environment
    steps). Without the ``tensorboard`` package it says so once and records nothing."""

    def __init__(self, run_dir: Path) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # the package is a dependency; a stripped install still trains
            print("tensorboard is not installed: no TensorBoard event files (pip install tensorboard)")
            self._writer = None
            return
        self._writer = SummaryWriter(str(run_dir / "tensorboard"), flush_secs=10)

    def scalars(self, values: dict[str, Any], step: int, wall_time: float | None = None) -> None:
        if self._writer is None:
            return
        for tag, value in values.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                self._writer.add_scalar(tag, float(value), global_step=int(step), walltime=wall_time)

    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


def strict_json(value: Any) -> Any:
    """``value`` with every NaN or infinity replaced by ``None`` (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


class RunSummary:
    """``summary.json``: the latest session's figures at the top level, and ``sessions``, one
    entry per start of the run (a resume appends). ``elapsed_s`` and ``env_steps`` are the
    run's totals, which the budget counts against."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_dir / "summary.json"
        self.sessions: list[dict] = []
        if self.path.exists():
            try:
                saved = json.loads(self.path.read_text())
                self.sessions = list(saved.get("sessions", []))
            except (json.JSONDecodeError, AttributeError):
                self.path.replace(self.path.with_suffix(".json.bad"))

    @property
    def elapsed_before_s(self) -> float:
        """Training wall time of the earlier sessions (s)."""
        return float(sum(s.get("wall_s") or 0.0 for s in self.sessions))

    def write(self, session: dict, **latest: Any) -> dict:
        summary = {**latest, "elapsed_s": self.elapsed_before_s + (session.get("wall_s") or 0.0),
                   "sessions": [*self.sessions, session]}
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(strict_json(summary), indent=2, allow_nan=False))
        tmp.replace(self.path)
        return summary

    def close_session(self, session: dict, **latest: Any) -> dict:
        summary = self.write(session, **latest)
        self.sessions.append(session)
        return summary


def copy_policy(source: Path, target: Path, note: dict | None = None) -> Path:
    """Replace the artefact folder ``target`` by a copy of ``source`` (built beside it, then
    swapped in), with ``note`` written as ``selected.json`` (why this version is here)."""
    tmp = target.with_name(f".{target.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(source, tmp)
    if note is not None:
        (tmp / "selected.json").write_text(json.dumps(strict_json(note), indent=2, allow_nan=False))
    old = target.with_name(f".{target.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if target.exists():
        target.replace(old)
    tmp.replace(target)
    shutil.rmtree(old, ignore_errors=True)
    return target


def now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")
