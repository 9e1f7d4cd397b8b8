"""The curriculum ablation (the paper's Fig. 5): conditions x seeds at one environment-step
budget, each a serial run (``curlnav train --serial --curriculum FILE``) on one core, and the
report that compares them.

``curlnav ablation run --out DIR``: launches the runs ``DIR/<condition>-s<seed>``, ``--parallel``
at a time (default: one per core), each with ``--threads 1``. It is resumable: a run that has
used its step budget is skipped, a run cut short is resumed (``--resume``), and a changed
budget only raises the budget. Progress: one line per run as it starts, every minute the step
count of each running run, and one line as it ends.

``curlnav ablation report DIR``: from the saved runs only (no training), ``ablation.png`` (held-out
success per evaluation target, e.g. T-Maze p1..p4, over environment steps: one panel per target,
one colour per condition, the mean over seeds bold and each seed thin, stage switches marked),
``ablation.csv`` (one row per run) and ``ablation.md`` (the table). Conditions are the run's
curriculum name (``name:`` of its file), seeds its ``seed``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

import curlnav.scheduler
from curlnav.bus.transport import on_stop_signals, restore_signals
from curlnav.run.record import read_csv

#: the shipped curricula, wherever the scheduler package is installed (the scheduler/ folder in a checkout)
CURRICULA = Path(curlnav.scheduler.__file__).resolve().parent / "curricula"
#: the paper's four conditions (Fig. 5), as shipped curriculum files
PAPER_CONDITIONS = ("s1+s2", "s1-only", "s2-only", "no-curriculum")


def say(line: str) -> None:
    """Progress lines, flushed at once (they are often read from a log file)."""
    print(line, flush=True)


class AblationError(ValueError):
    """A bad condition, budget or run folder (one line)."""


def condition_file(name: str) -> Path:
    """A shipped condition's curriculum file, or the curriculum file ``name`` itself."""
    path = Path(name)
    if path.suffix in (".yaml", ".yml"):
        if not path.exists():
            raise AblationError(f"no curriculum file {path}")
        return path
    shipped = CURRICULA / f"{name}.yaml"
    if not shipped.exists():
        choices = ", ".join(sorted(p.stem for p in CURRICULA.glob("*.yaml")))
        raise AblationError(f"unknown condition {name!r}: give a curriculum file or one of {choices}")
    return shipped


@dataclass
class RunSpec:
    """One serial run: its folder, its environment-step budget and the ``curlnav train`` options
    of a new run (world or curriculum, seed, overrides); an existing run is resumed instead."""

    run_dir: Path
    max_env_steps: int
    new_args: list[str]
    condition: str = ""
    seed: int = 0

    def steps_done(self) -> int:
        try:
            return int(json.loads((self.run_dir / "summary.json").read_text()).get("env_steps", 0))
        except (OSError, ValueError):
            return 0

    def command(self) -> list[str]:
        cmd = [sys.executable, "-m", "curlnav.cli", "train", "--serial", "--threads", "1", "--run-dir",
               str(self.run_dir), "--max-env-steps", str(self.max_env_steps), "--minutes", "100000"]
        if (self.run_dir / "checkpoints" / "latest.safetensors").exists():
            return cmd + ["--resume"]  # its saved config (curriculum, seed) continues
        return cmd + self.new_args


def plan_runs(out: Path, conditions: list[str], seeds: list[int], max_env_steps: int,
              extra: list[str] | None = None) -> list[RunSpec]:
    """The ablation's runs: ``out/<condition>-s<seed>`` for each curriculum and seed."""
    if max_env_steps <= 0:
        raise AblationError(f"--max-env-steps must be positive, got {max_env_steps}")
    specs = []
    for condition in conditions:
        path = condition_file(condition)
        for seed in seeds:
            specs.append(RunSpec(out / f"{path.stem}-s{seed}", max_env_steps,
                                 ["--curriculum", str(path), "--seed", str(seed), *(extra or [])], path.stem, seed))
    return specs


def run_all(specs: list[RunSpec], parallel: int, log=say, poll_s: float = 2.0) -> int:
    """Run every spec not yet at its budget, ``parallel`` at a time; returns how many failed.
    Each run's own output goes to ``<run>/train.log``."""
    todo = [s for s in specs if s.steps_done() < s.max_env_steps]
    for s in specs:
        if s not in todo:
            log(f"[ablation] {s.run_dir.name}: done ({s.steps_done()} env steps), skipped")
    running: list[tuple[RunSpec, subprocess.Popen, object]] = []
    failed = 0
    last_report = time.monotonic()
    try:
        previous = on_stop_signals(_raise_stopped)
    except ValueError:  # not the main thread: signals stay with whoever handles them there
        previous = {}
    try:
        while todo or running:
            while todo and len(running) < parallel:
                spec = todo.pop(0)
                spec.run_dir.mkdir(parents=True, exist_ok=True)
                handle = open(spec.run_dir / "train.log", "a")
                cmd = spec.command()
                proc = subprocess.Popen(cmd, stdout=handle, stderr=subprocess.STDOUT,
                                        env={**os.environ, "PYTHONUNBUFFERED": "1"})
                log(f"[ablation] {spec.run_dir.name}: started ({'resumed' if '--resume' in cmd else 'new'}, "
                    f"budget {spec.max_env_steps} env steps, pid {proc.pid})")
                running.append((spec, proc, handle))
            for item in list(running):
                spec, proc, handle = item
                code = proc.poll()
                if code is None:
                    continue
                handle.close()
                running.remove(item)
                if code != 0:
                    failed += 1
                log(f"[ablation] {spec.run_dir.name}: {'finished' if code == 0 else f'FAILED (exit {code})'} at "
                    f"{spec.steps_done()} env steps; output in {spec.run_dir / 'train.log'}")
            if running and time.monotonic() - last_report >= 60:
                last_report = time.monotonic()
                log("[ablation] " + "; ".join(f"{s.run_dir.name} {_latest_steps(s.run_dir)}/{s.max_env_steps}"
                                              for s, _, _ in running))
            time.sleep(poll_s)
    finally:  # Ctrl-C, SIGTERM, SIGHUP or an error: no run is left training on its own
        restore_signals(previous)
        for _, proc, _ in running:
            proc.terminate()  # each run saves a checkpoint on SIGTERM: `ablation run` again resumes
        for _, proc, handle in running:
            try:
                proc.wait(timeout=120)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            handle.close()
    return failed


class _Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP to ``ablation run``: handled like Ctrl-C."""


def _raise_stopped(signum: int, _frame) -> None:
    raise _Stopped(f"signal {signum}")


def _latest_steps(run_dir: Path) -> int:
    rows = read_csv(run_dir / "metrics.csv")
    return int(float(rows[-1]["env_steps"])) if rows else 0


# -- the report -----------------------------------------------------------------------------------
@dataclass
class RunResult:
    """What one saved run shows: its evaluations per target and its stage switches."""

    run_dir: Path
    condition: str
    seed: int
    env_steps: int
    wall_s: float
    curves: dict[str, list[tuple[int, float, float]]]  # target -> [(env steps, success, base collisions/trial)]
    advances: list[dict]  # {stage, substep, env_steps, wall_s}

    def first_reaching(self, target: str, rate: float) -> int | None:
        return next((steps for steps, success, _ in self.curves.get(target, []) if success >= rate), None)

    def final(self, target: str) -> tuple[float, float]:
        points = self.curves.get(target) or [(0, math.nan, math.nan)]
        return points[-1][1], points[-1][2]

    def best(self, target: str) -> float:
        return max((s for _, s, _ in self.curves.get(target, [])), default=math.nan)


def load_run(run_dir: Path) -> RunResult | None:
    """A saved run (config.yaml, eval.csv, summary.json), or None if it is not a curriculum run."""
    try:
        config = yaml.safe_load((run_dir / "config.yaml").read_text())
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError, yaml.YAMLError):
        return None
    curriculum_file = (config.get("curriculum") or {}).get("file")
    if not curriculum_file:
        return None
    try:
        name = yaml.safe_load(Path(curriculum_file).read_text()).get("name") or Path(curriculum_file).stem
    except (OSError, yaml.YAMLError, AttributeError):
        name = Path(curriculum_file).stem
    curves: dict[str, list] = {}
    for row in read_csv(run_dir / "eval.csv"):
        target = f"{row['world']}/{row['pair']}"
        curves.setdefault(target, []).append((int(float(row["env_steps"])), float(row["success_rate"]),
                                              float(row["collisions_per_episode"])))
    advances = list((summary.get("curriculum") or {}).get("advances", []))
    return RunResult(run_dir, str(name), int(config.get("seed", 0)), int(summary.get("env_steps", 0)),
                     float(summary.get("wall_s", 0.0)), curves, advances)


def fixed_targets(run_dir: Path) -> list[str]:
    """The curriculum's ``evaluate`` targets as eval.csv names them (world stem / pair)."""
    from curlnav.scheduler.curriculum import load_curriculum

    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    curriculum = load_curriculum(config["curriculum"]["file"])
    return [f"{Path(w).stem}/{p or 'held-out'}" for w, p in curriculum.evaluation_targets()]


def write_report(folder: Path, runs: list[RunResult] | None = None, headline: str | None = None) -> Path:
    """ablation.png, ablation.csv and ablation.md in ``folder`` from its run folders."""
    runs = runs if runs is not None else [r for r in (load_run(d) for d in sorted(folder.iterdir()) if d.is_dir())
                                          if r is not None]
    if not runs:
        raise AblationError(f"no curriculum runs (config.yaml + summary.json + eval.csv) under {folder}")
    targets = fixed_targets(runs[0].run_dir)
    headline = headline or targets[-1]
    runs.sort(key=lambda r: (*_condition_rank(r.condition), r.condition, r.seed))
    _plot(folder / "ablation.png", runs, targets)
    rows = []
    for r in runs:
        final, collisions = r.final(headline)
        row = {"condition": r.condition, "seed": r.seed, "env_steps": r.env_steps, "wall_min": round(r.wall_s / 60, 1),
               f"final {headline}": final, f"best {headline}": r.best(headline),
               f"base collisions/trial {headline}": collisions,
               f"steps to 50% {headline}": r.first_reaching(headline, 0.5)}
        for t in targets:
            row[f"final {t}"] = r.final(t)[0]
        row["stage switches (env steps)"] = "; ".join(f"{a['stage']}.{a['substep']}@{a['env_steps']}"
                                                      for a in r.advances) or "-"
        rows.append(row)
    with (folder / "ablation.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (folder / "ablation.md").write_text(_markdown(rows, runs, headline))
    return folder / "ablation.md"


def _condition_rank(condition: str) -> tuple[int, int]:
    """Report order: the paper's four conditions in the paper's order, each followed by its
    variants (``s1+s2-budget`` after ``s1+s2``), then any other curriculum."""
    for i, paper in enumerate(PAPER_CONDITIONS):
        if condition == paper:
            return i, 0
        if condition.startswith(paper + "-"):
            return i, 1
    return len(PAPER_CONDITIONS), 0


def _fmt(value) -> str:
    if value is None:
        return "never"
    if isinstance(value, float):
        return "-" if math.isnan(value) else (f"{value:.0%}" if 0 <= value <= 1 else f"{value:.2f}")
    return str(value)


def _markdown(rows: list[dict], runs: list[RunResult], headline: str) -> str:
    keys = ["condition", "seed", "env_steps", "wall_min", f"final {headline}", f"best {headline}",
            f"base collisions/trial {headline}", f"steps to 50% {headline}", "stage switches (env steps)"]
    lines = [f"# Curriculum ablation: held-out success on {headline}", "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for row in rows:
        plain = {f"base collisions/trial {headline}", "wall_min"}  # numbers, not rates
        lines.append("| " + " | ".join(_fmt(row[k]) if k not in plain
                                       else (f"{row[k]:.2f}" if not math.isnan(row[k]) else "-") for k in keys) + " |")
    lines += ["", "Per condition (mean over seeds of the last evaluation):", ""]
    by_condition: dict[str, list[RunResult]] = {}
    for r in runs:
        by_condition.setdefault(r.condition, []).append(r)
    targets = [k[len("final "):] for k in rows[0] if k.startswith("final ")]
    lines += ["| condition | seeds | " + " | ".join(targets) + " |", "|" + "---|" * (len(targets) + 2)]
    for condition, group in by_condition.items():
        means = [sum(r.final(t)[0] for r in group) / len(group) for t in targets]
        lines.append(f"| {condition} | {len(group)} | " + " | ".join(_fmt(m) for m in means) + " |")
    lines += ["", "Environment steps until held-out success first reached 50 %, per target:", "",
              "| condition | seed | " + " | ".join(targets) + " |", "|" + "---|" * (len(targets) + 2)]
    for r in runs:
        lines.append(f"| {r.condition} | {r.seed} | " + " | ".join(_fmt(r.first_reaching(t, 0.5)) for t in targets)
                     + " |")
    lines += ["", "Success: greedy policy, collisions counted and the trial goes on (the evaluation protocol); base "
              "collisions/trial counts control steps in contact with a wall. Figure: ablation.png."]
    return "\n".join(lines) + "\n"


def _plot(path: Path, runs: list[RunResult], targets: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    conditions = list(dict.fromkeys(r.condition for r in runs))
    colours = {c: plt.get_cmap("tab10")(i) for i, c in enumerate(conditions)}
    fig, axes = plt.subplots(1, len(targets), figsize=(4.2 * len(targets), 3.6), sharey=True, squeeze=False)
    for ax, target in zip(axes[0], targets):
        for condition in conditions:
            group = [r for r in runs if r.condition == condition and r.curves.get(target)]
            for r in group:
                xs, ys = zip(*[(s, v) for s, v, _ in r.curves[target]])
                ax.plot(xs, ys, color=colours[condition], alpha=0.35, lw=0.8)
                for a in r.advances:
                    ax.axvline(a["env_steps"], color=colours[condition], ls=":", lw=0.8, alpha=0.6)
            if group:
                grid = sorted({s for r in group for s, _, _ in r.curves[target]})
                mean = [sum(_at(r.curves[target], s) for r in group) / len(group) for s in grid]
                ax.plot(grid, mean, color=colours[condition], lw=2.0,
                        label=f"{condition} ({len(group)} seed{'s' if len(group) > 1 else ''})")
        ax.set_title(f"held-out success: {target}")
        ax.set_xlabel("environment steps")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success rate")
    axes[0][-1].legend(loc="lower right", fontsize=8)
    fig.suptitle("Curriculum ablation (dotted: stage / sub-step switches)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _at(points: list[tuple[int, float, float]], steps: int) -> float:
    """Success at ``steps``: the last evaluation at or before it (0 before the first)."""
    value = 0.0
    for s, v, _ in points:
        if s > steps:
            break
        value = v
    return value
