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
import sys
import time
from pathlib import Path
from typing import Any

#: metrics.csv columns (both modes; a mode leaves the ones it does not know empty)
TRAIN_FIELDS = ["wall_s", "env_steps", "updates", "episodes", "train_success_100", "return_100",
                "base_collisions_100", "env_steps_per_s", "updates_per_s", "losses/critic", "losses/actor",
                "values/q_mean", "replay_size", "policy_version", "policy_lag", "stage_index", "stage", "substep",
                "live_actors", "network_control_share_100"]


def control_text(shares: dict | None) -> str:
    """``network 87%, rescue 10%, shield 3%``: the share of control steps by chooser (the progress
    line's; "" for none)."""
    return ", ".join(f"{role} {share:.0%}" for role, share in (shares or {}).items())


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
    (a resumed run continues its history); a file whose header lacks only columns added since
    (at the end) is rewritten with them, empty in its rows; one with another header is kept as ``.old``."""

    def __init__(self, path: Path, fields: list[str]) -> None:
        self.path = path
        self.fields = fields
        if path.exists():
            with open(path, newline="") as f:
                header = next(csv.reader(f), None)
            if header and header != fields and header == fields[:len(header)]:
                rows = read_csv(path)  # a run written before the newer columns: its history kept
                tmp = path.with_suffix(path.suffix + ".tmp")
                with open(tmp, "w", newline="") as f:
                    writer = csv.DictWriter(f, fieldnames=fields)
                    writer.writeheader()
                    writer.writerows(rows)
                tmp.replace(path)
            elif header != fields:
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


def evaluations_of(eval_csv: Path) -> list[dict]:
    """Every evaluation of a run, from its eval.csv (all sessions, both modes): one entry per
    evaluation whose rows are all written, in order. ``success_rate`` and
    ``collisions_per_episode`` are the headline target's (the evaluation's last row: the
    curriculum's last fixed target, or the training world's held-out pairs), ``mean_success_rate``
    the mean over its rows, ``per_pair`` each row's success. ``summary.json`` and ``curlnav status``
    report these, so a resumed run reports the evaluations of its earlier sessions too."""
    groups: dict[str, list[dict]] = {}
    for row in read_csv(eval_csv):
        try:  # a row still being written ends what can be read
            float(row["success_rate"]), float(row["collisions_per_episode"]), float(row["wall_s"])
        except (KeyError, TypeError, ValueError):
            break
        groups.setdefault(row.get("evaluation") or str(len(groups) + 1), []).append(row)
    evaluations = []
    for number, rows in groups.items():
        expected = rows[0].get("rows") or ""
        if expected.isdigit() and len(rows) < int(expected):
            continue  # the evaluator stopped during it
        head, first = rows[-1], rows[0]
        evaluations.append({
            "evaluation": int(number) if number.isdigit() else number, "wall_s": float(first["wall_s"]),
            "env_steps": _whole(first.get("env_steps")), "updates": _whole(first.get("updates")),
            "version": _whole(first.get("policy_version")),
            "stage": rows[0].get("stage"), "target": f"{head.get('world')}/{head.get('pair')}",
            "success_rate": float(head["success_rate"]),
            "mean_success_rate": sum(float(r["success_rate"]) for r in rows) / len(rows),
            "collisions_per_episode": float(head["collisions_per_episode"]),
            "per_pair": {f"{r.get('world')}/{r.get('pair')}": float(r["success_rate"]) for r in rows}})
    return evaluations


def _whole(value: str | None) -> int | None:
    try:
        return int(float(value))
    except (TypeError, ValueError):
        return None


def first_reaching(evaluations: list[dict], success: float = 0.8) -> dict | None:
    """The first evaluation at or above ``success`` on its headline target, or None."""
    return next((e for e in evaluations if e["success_rate"] >= success), None)


def outcome_fields(run_dir: Path) -> dict:
    """What a closing ``summary.json`` says of evaluations and policies, in both modes: every
    evaluation of the run (``evals``, all sessions, from eval.csv), the first at >= 80 %, the
    policy folders (None for one that holds no artefact yet), and for a run started from a policy
    (``init_from``) where it started and how that policy and the newest one did (``start_fields``)."""
    evals = evaluations_of(run_dir / "eval.csv")
    newest, best = run_dir / "policy", run_dir / "policy-best"
    return {"evals": evals, "first_eval_reaching_80": first_reaching(evals),
            "policy": str(newest) if has_policy(newest) else None,
            "policy_best": str(best) if has_policy(best) else None, **start_fields(run_dir, evals)}


#: a run started from a policy (``init_from``): where from (path, kind, sha256 of each file), written
#: once by its trainer before anything is trained; and that policy's held-out evaluation as it came,
#: before any update (``curlnav.run.evaluator.evaluate_before``)
INIT_FROM_FILE, BEFORE_FILE = "init_from.json", "before.json"


def write_json(path: Path, data: dict) -> Path:
    """Strict JSON (no NaN), written beside ``path`` and renamed onto it."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(strict_json(data), indent=2, allow_nan=False))
    tmp.replace(path)
    return path


def record_init_from(run_dir: Path, init_from: str) -> dict:
    """``init_from.json`` of a run started from ``init_from``: its path, kind and the sha256 of each
    of its files (``curlnav.learner.init_from.StartingPoint.record``), written when the run starts;
    a resumed run keeps it. Returns the record."""
    path = Path(run_dir) / INIT_FROM_FILE
    saved = _read_json(path)
    if saved is not None:
        return saved
    from curlnav.learner.init_from import find_starting_point

    record = find_starting_point(init_from).record()
    write_json(path, record)
    return record


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return data if isinstance(data, dict) else None


def start_fields(run_dir: Path, evals: list[dict] | None = None) -> dict:
    """``init_from`` (``{"path", "kind", "sha256": {file: digest}}``), ``before`` (the starting
    policy's held-out success and base collisions per episode, before any update) and ``after``
    (the newest evaluation of the run, None before the first) of a run started from a policy;
    nothing for a run of fresh networks."""
    record = _read_json(run_dir / INIT_FROM_FILE)
    if record is None:
        return {}
    evals = evaluations_of(run_dir / "eval.csv") if evals is None else evals
    newest = evals[-1] if evals else None
    after = None if newest is None else {k: newest.get(k) for k in (
        "evaluation", "version", "wall_s", "env_steps", "updates", "target", "success_rate", "collisions_per_episode")}
    return {"init_from": record, "before": _read_json(run_dir / BEFORE_FILE), "after": after}


def absolute(path: str | Path) -> Path:
    """``path`` as an absolute path (not resolving links): what is printed for a person works from
    any directory."""
    return Path(os.path.abspath(path))


def has_policy(folder: Path) -> bool:
    return (Path(folder) / "metadata.json").is_file()


def policy_lines(run_dir: str | Path) -> str:
    """Where a run's policies are, by absolute path, naming only folders that hold an artefact
    (``policy-best`` appears with the first evaluation, ``policy`` with the first export)."""
    run_dir = absolute(run_dir)
    newest, best = run_dir / "policy", run_dir / "policy-best"
    return "; ".join([f"policy (newest): {newest}" if has_policy(newest) else
                      "policy (newest): no policy yet (the learner exported none)",
                      f"policy (best evaluation): {best}" if has_policy(best) else
                      "policy (best evaluation): no best policy yet (no evaluation finished)"])


def process_started() -> float | None:
    """When this process started, on ``time.monotonic()``'s clock (Linux ``/proc/self/stat``), or
    None where that cannot be read."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return time.monotonic() - age if 0.0 <= age < 300.0 else None


def command_started() -> float:
    """When this ``curlnav train`` started, on ``time.monotonic()``'s clock: the start of the
    process when the process is that command (the interpreter's start-up and imports count against
    the budget too), else now (``run_train`` called in-process: a test, a notebook)."""
    started = process_started() if sys.argv[1:2] == ["train"] else None
    return time.monotonic() if started is None else started


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
