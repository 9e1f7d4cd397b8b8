"""``curlnav experiment``: the paper's evaluation with our numbers, in one resumable command.

It produces ``<out>/report.md`` with its figures and tables:

- **Table I**: one world of each procedural family, its five BARN difficulty metrics, the
  easy/hard split of the ranking, and a serial run from scratch on it (held-out success over
  environment steps). Finding 1: the metrics predict which worlds train from scratch.
- **Fig. 4**: two-stage fine-tuning (the networks of the easy world's run, then the hard
  world) against training from scratch, on the hardest worlds, at equal steps. Finding 2.
- **Fig. 5**: the curriculum ablation (``curlnav.run.ablation``): S1+S2, S1 only, S2 only, no
  curriculum, held-out success on T-Maze p1..p4. Finding 3: S1+S2 is the most sample-efficient.
- **Table II**: the S1+S2 policy (alone and behind a global plan) and the no-curriculum one
  against the map-less classical planners (``tare-l``, after TARE's local planner, and ``dwa``;
  movable objects ignored, as the paper forced TARE-L) and the ``oracle`` (A* on the true map)
  on the unseen-world suite (``curlnav eval --suite unseen``: NAMO worlds with doors and balls,
  barn-3x3 and slam-office, all at held-out seeds; ``curlnav.evaluation.compare``).

Every run is a serial run (one core each, ``--parallel`` at once) in its own folder; the command
skips what is done and resumes what was cut short, so Ctrl-C and running it again loses only
minutes. ``--report-only`` regenerates the report from the saved runs without training.
Budgets: ``smoke`` (a few minutes: checks the whole pipeline, no findings), ``small`` (sized for a 2-core
machine, under 2 hours; reduced budgets, labelled as
such in the report) and ``full`` (the step budgets the findings need; for a bigger machine,
raise ``--parallel`` to its cores).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from curlnav.run.ablation import (
    PAPER_CONDITIONS,
    RunResult,
    RunSpec,
    fixed_targets,
    load_run,
    plan_runs,
    run_all,
    say,
    write_report,
)
from curlnav.run.record import read_csv

#: one world of each family for Table I (seed 0 of each)
TABLE1_FAMILIES = ("barn-3x3", "forest", "cave", "garage", "indoor", "office", "auditorium", "campus")
#: unseen NAMO worlds for Table II (seed 100 of each: never generated for training)
UNSEEN_FAMILIES = ("namo-office", "namo-indoor", "namo-auditorium")
UNSEEN_SEED = 100
TABLE2_CLASSICAL = ("tare-l", "dwa", "oracle")  # the classical agents of Table II
CONVERGED = 0.5  # held-out success that counts as "trains from scratch" in Table I


@dataclass(frozen=True)
class Budget:
    """Step budgets per run (environment steps) and evaluation sizes."""

    name: str
    table1_steps: int
    fig4_steps: int
    fig4_hard_worlds: int
    fig5_steps: int
    fig5_seeds: tuple[int, ...]
    table2_pairs: int
    table2_seeds: int
    eval_every_s: float
    eval_episodes: int
    reduced: bool

    def train_options(self) -> list[str]:
        return ["--eval-every-s", f"{self.eval_every_s:g}", "--eval-episodes", str(self.eval_episodes)]


BUDGETS = {
    "smoke": Budget("smoke", table1_steps=300, fig4_steps=300, fig4_hard_worlds=1, fig5_steps=300, fig5_seeds=(0,),
                    table2_pairs=2, table2_seeds=1, eval_every_s=600.0, eval_episodes=2, reduced=True),
    "small": Budget("small", table1_steps=25_000, fig4_steps=25_000, fig4_hard_worlds=2, fig5_steps=60_000,
                    fig5_seeds=(0,), table2_pairs=10, table2_seeds=1, eval_every_s=90.0, eval_episodes=20,
                    reduced=True),
    "full": Budget("full", table1_steps=150_000, fig4_steps=150_000, fig4_hard_worlds=3, fig5_steps=250_000,
                   fig5_seeds=(0, 1), table2_pairs=10, table2_seeds=3, eval_every_s=180.0, eval_episodes=40,
                   reduced=False),
}


class ExperimentError(ValueError):
    """A bad budget or an output folder that cannot be used (one line)."""


# -- worlds and ranking ---------------------------------------------------------------------------
def prepare_worlds(out: Path, log=say) -> tuple[list[Path], list[Path]]:
    """World files: Table I's (one per family, seed 0) and the unseen NAMO worlds (seed 100)."""
    from curlnav.sim import save_world
    from curlnav.worlds.families import generate

    folder = out / "worlds"
    folder.mkdir(parents=True, exist_ok=True)
    made = []
    for families, seed in ((TABLE1_FAMILIES, 0), (UNSEEN_FAMILIES, UNSEEN_SEED)):
        paths = []
        for family in families:
            path = folder / f"{family}-{seed}.yaml"
            if not path.exists():
                world = generate(family, seed)
                save_world(world, path)
                log(f"[experiment] world {path}: {world.size[0]:.0f} m x {world.size[1]:.0f} m, "
                    f"{len(world.pairs)} pairs, {len(world.balls)} balls, {len(world.doors)} doors")
            paths.append(path)
        made.append(paths)
    return made[0], made[1]


def ranking(out: Path, worlds: list[Path], log=say) -> list[dict]:
    """The five metrics, difficulty and easy/hard class of each Table I world (cached)."""
    from curlnav.sim import get_world
    from curlnav.worlds.difficulty.rank import rank, write_outputs

    path = out / "ranking" / "ranking.json"
    if not path.exists():
        started = time.monotonic()
        rows = rank([get_world(str(w)) for w in worlds])
        write_outputs(rows, out / "ranking")
        log(f"[experiment] ranked {len(rows)} worlds in {time.monotonic() - started:.0f} s: "
            f"easy {', '.join(r.name for r in rows if r.category == 'easy')}")
    return json.loads(path.read_text())["worlds"]


# -- the runs -------------------------------------------------------------------------------------
def table1_specs(out: Path, worlds: list[Path], budget: Budget) -> list[RunSpec]:
    return [RunSpec(out / "table1" / w.stem, budget.table1_steps,
                    ["--world", str(w), "--seed", "0", *budget.train_options()], w.stem, 0) for w in worlds]


def fig4_plan(out: Path, ranked: list[dict], budget: Budget, world_files: dict[str, Path]) -> tuple[str, list[str]]:
    """(the easy world whose run seeds the fine-tuning, the hard worlds), chosen the paper's way:
    metrics first (the ranking's easy class), then the from-scratch run that converged best
    (Table I's final held-out success; ties to the easier); the ``fig4_hard_worlds`` hardest."""
    order = sorted(ranked, key=lambda r: r["difficulty"])
    easy_class = [r["name"] for r in order if r["category"] == "easy"] or [order[0]["name"]]
    finals = {name: _final(held_out_curve(out / "table1" / name)) for name in easy_class}
    easy = max(easy_class, key=lambda n: (0.0 if math.isnan(finals[n]) else finals[n], -easy_class.index(n)))
    hard = [r["name"] for r in order[::-1][:budget.fig4_hard_worlds] if r["category"] == "hard"]
    return easy, [h for h in hard if h in world_files]


def fig4_specs(out: Path, easy: str, hard: list[str], budget: Budget, world_files: dict[str, Path]) -> list[RunSpec]:
    return [RunSpec(out / "fig4" / f"{h}-from-{easy}", budget.fig4_steps,
                    ["--world", str(world_files[h]), "--init-from", str(out / "table1" / easy), "--seed", "0",
                     *budget.train_options()], f"fine-tuned from {easy}", 0) for h in hard]


def run_experiment(out: Path, budget: Budget, parallel: int, log=say) -> Path:
    """Everything not yet done, then the report; returns the report's path."""
    started = time.monotonic()
    table1_worlds, unseen = prepare_worlds(out, log)
    ranked = ranking(out, table1_worlds, log)
    world_files = {w.stem: w for w in table1_worlds}
    specs = table1_specs(out, table1_worlds, budget)
    specs += plan_runs(out / "ablation", list(PAPER_CONDITIONS), list(budget.fig5_seeds), budget.fig5_steps,
                       budget.train_options())
    failed = run_all(specs, parallel, log=log)
    easy, hard = fig4_plan(out, ranked, budget, world_files)
    (out / "fig4").mkdir(parents=True, exist_ok=True)
    (out / "fig4" / "plan.json").write_text(json.dumps({"source": easy, "hard": hard}, indent=2))
    failed += run_all(fig4_specs(out, easy, hard, budget, world_files), parallel, log=log)
    table2(out, unseen, budget, log)
    (out / "experiment.json").write_text(json.dumps({"budget": asdict(budget), "parallel": parallel,
                                                     "last_session_s": time.monotonic() - started,
                                                     "failed_runs": failed}, indent=2))
    report = write_experiment_report(out, budget)
    log(f"[experiment] report: {report} ({(time.monotonic() - started) / 60:.1f} min this session"
        + (f"; {failed} run(s) FAILED, see their train.log" if failed else "") + ")")
    return report


def table2_agents(out: Path) -> dict[str, Path]:
    """The trained policies Table II compares with the planner: each condition's best."""
    agents = {}
    for condition in ("s1+s2", "no-curriculum"):
        best = sorted((out / "ablation").glob(f"{condition}-s*/policy-best"))
        if best:
            agents[condition] = best[0]
    return agents


def table2(out: Path, unseen: list[Path], budget: Budget, log=say) -> Path | None:
    """The comparison on the unseen-world suite (cached in ``table2/``): every trained policy
    (S1+S2 also behind a global plan), ``tare-l``, ``dwa`` and the ``oracle``. The suite's
    trials, fewer when the budget's pairs x seeds are fewer (``unseen`` is ignored: the
    suite names its worlds)."""
    from curlnav.evaluation.compare import UNSEEN

    folder = out / "table2"
    policies = table2_agents(out)
    trials = min(budget.table2_pairs * budget.table2_seeds, UNSEEN.trials)  # the smoke budget runs fewer
    key = {label: {"path": str(path), "selected": _mtime(path / "selected.json")} for label, path in policies.items()}
    key["suite"] = {"worlds": list(UNSEEN.worlds), "trials": trials, "classical": list(TABLE2_CLASSICAL)}
    try:
        cached = json.loads((folder / "agents.json").read_text())
    except (OSError, ValueError):
        cached = None
    if (folder / "summary.csv").exists() and cached == key:
        return folder  # the same policies were compared already
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.compare import (
        Comparison,
        comparison_table,
        draw_trajectories,
        summarise,
        table_ii,
        write_csv,
    )
    from curlnav.nav import make_agent
    from curlnav.nav.global_planners.global_plan import GlobalPlanAgent
    from curlnav.policy import PolicyArtefact
    from curlnav.sim import get_world

    env_config = ExperimentConfig().eval_env
    agents: dict[str, object] = {}
    for label, path in policies.items():
        agents[label] = PolicyArtefact(path)
        if label == "s1+s2":
            planned = GlobalPlanAgent(agents[label], env_config, label=label)
            agents[planned.label] = planned
    for name in TABLE2_CLASSICAL:
        label, agent = make_agent(name, env_config, PolicyArtefact)
        agents[label] = agent
    worlds = [get_world(spec) for spec in UNSEEN.worlds]
    suite = dataclasses.replace(UNSEEN, trials=trials, ball_placements=min(UNSEEN.ball_placements, trials))
    comparison = Comparison(agents, worlds, suite.pairs_of, env_config)
    total = comparison.episode_count(1)
    done = [0]

    def progress(_episode) -> None:
        done[0] += 1
        if done[0] % 10 == 0 or done[0] == total:
            log(f"[experiment] table II: {done[0]}/{total} episodes")

    episodes = comparison.run(1, on_episode=progress)
    summaries = summarise(episodes)
    folder.mkdir(parents=True, exist_ok=True)
    write_csv(episodes, summaries, folder)
    draw_trajectories(episodes, worlds, folder / "trajectories", env_config.robot.base_width / 2)
    (folder / "table.txt").write_text(comparison_table(summaries) + "\n")
    (folder / "table2.md").write_text(table_ii(summaries) + "\n")
    (folder / "agents.json").write_text(json.dumps(key, indent=2))
    return folder


def _mtime(path: Path) -> float | None:
    try:
        return path.stat().st_mtime
    except OSError:
        return None


# -- the report -----------------------------------------------------------------------------------
def _pct(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.0%}"


def held_out_curve(run_dir: Path) -> list[tuple[int, float]]:
    """(env steps, held-out success) of a single-world run's evaluations."""
    return [(int(float(r["env_steps"])), float(r["success_rate"])) for r in read_csv(run_dir / "eval.csv")]


def _final(curve: list[tuple[int, float]]) -> float:
    return curve[-1][1] if curve else float("nan")


def _spearman(x: list[float], y: list[float]) -> float:
    from scipy.stats import spearmanr

    if len(x) < 3 or len(set(y)) < 2:
        return float("nan")
    return float(spearmanr(x, y).statistic)


def write_experiment_report(out: Path, budget: Budget) -> Path:
    """report.md (and its figures) from the saved runs only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ranking_path = out / "ranking" / "ranking.json"
    if not ranking_path.exists():
        raise ExperimentError(f"no ranking in {out / 'ranking'}: run `curlnav experiment --out {out}` first")
    ranked = sorted(json.loads(ranking_path.read_text())["worlds"], key=lambda r: r["difficulty"])
    lines = [f"# curlnav experiment report ({budget.name} budget)", ""]
    if budget.reduced:
        lines += [f"**Reduced budgets** (`--budget {budget.name}`): {budget.table1_steps:,} environment steps per "
                  f"Table I run, {budget.fig4_steps:,} per Fig. 4 run, {budget.fig5_steps:,} per Fig. 5 run "
                  f"({len(budget.fig5_seeds)} seed(s)); the paper trained for millions. Findings at this budget "
                  f"are early-training findings.", ""]
    findings = []

    # Table I
    rows, xs, ys = [], [], []
    fig, ax = plt.subplots(figsize=(7, 4))
    for r in ranked:
        curve = held_out_curve(out / "table1" / Path(r["name"]).stem)
        final = _final(curve)
        rows.append((r, final, next((s for s, v in curve if v >= CONVERGED), None)))
        if curve:
            ax.plot(*zip(*curve), label=f"{r['name']} ({r['category']})",
                    ls="-" if r["category"] == "easy" else "--")
        if not math.isnan(final):
            xs.append(r["difficulty"])
            ys.append(final)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("held-out success")
    ax.set_ylim(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("Training from scratch (solid: easy by the metrics, dashed: hard)")
    fig.tight_layout()
    fig.savefig(out / "table1.png", dpi=110)
    plt.close(fig)
    lines += ["## Table I: difficulty metrics and training from scratch", "",
              "| world | size (m) | Dist | Vis | Disp | CD | Tor | difficulty | class | final held-out success | "
              f"steps to {CONVERGED:.0%} |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r, final, first in rows:
        lines.append(f"| {r['name']} | {r['width_m']:.0f} x {r['height_m']:.0f} | {r['distance']:.2f} | "
                     f"{r['visibility']:.2f} | {r['dispersion']:.2f} | {r['characteristic_dimension']:.2f} | "
                     f"{r['tortuosity']:.2f} | {r['difficulty']:.2f} | {r['category']} | {_pct(final)} | "
                     f"{first if first is not None else 'not reached'} |")
    easy = [f for r, f, _ in rows if r["category"] == "easy" and not math.isnan(f)]
    hard = [f for r, f, _ in rows if r["category"] == "hard" and not math.isnan(f)]
    rho = _spearman(xs, ys)
    mean_easy = sum(easy) / len(easy) if easy else float("nan")
    mean_hard = sum(hard) / len(hard) if hard else float("nan")
    ok1 = bool(easy and hard and mean_easy > mean_hard and rho < 0)
    lines += ["", "![training from scratch](table1.png)", "",
              f"Mean final success: easy worlds {_pct(mean_easy)}, hard worlds {_pct(mean_hard)}; Spearman rank "
              f"correlation between difficulty and final success {rho:.2f} (negative: harder trains worse).", ""]
    findings.append(("1. The difficulty metrics predict which worlds train from scratch (Table I)", ok1,
                     f"easy {_pct(mean_easy)} vs hard {_pct(mean_hard)}, Spearman {rho:.2f}"))

    # Fig. 4
    lines += ["## Fig. 4: two-stage fine-tuning against training from scratch", ""]
    try:  # this experiment's fine-tuning runs, not those of an earlier source world
        plan = json.loads((out / "fig4" / "plan.json").read_text())
        tuned_dirs = [out / "fig4" / f"{h}-from-{plan['source']}" for h in plan["hard"]]
        tuned_dirs = [d for d in tuned_dirs if d.exists()]
    except (OSError, ValueError, KeyError, TypeError):
        tuned_dirs = sorted((out / "fig4").glob("*-from-*")) if (out / "fig4").exists() else []
    wins = []
    if tuned_dirs:
        fig, axes = plt.subplots(1, len(tuned_dirs), figsize=(4.5 * len(tuned_dirs), 3.6), squeeze=False)
        lines += ["| hard world | fine-tuned from | fine-tuned final | scratch final |", "|---|---|---|---|"]
        for ax, tuned in zip(axes[0], tuned_dirs):
            world, source = tuned.name.split("-from-")
            tuned_curve, scratch_curve = held_out_curve(tuned), held_out_curve(out / "table1" / world)
            for curve, label in ((tuned_curve, f"fine-tuned from {source}"), (scratch_curve, "from scratch")):
                if curve:
                    ax.plot(*zip(*curve), label=label)
            ax.set_title(world)
            ax.set_xlabel("environment steps")
            ax.set_ylim(-0.03, 1.03)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            wins.append(_final(tuned_curve) > _final(scratch_curve))
            lines.append(f"| {world} | {source} | {_pct(_final(tuned_curve))} | {_pct(_final(scratch_curve))} |")
        axes[0][0].set_ylabel("held-out success")
        fig.tight_layout()
        fig.savefig(out / "fig4.png", dpi=110)
        plt.close(fig)
        lines += ["", "![fine-tuning](fig4.png)", ""]
    else:
        lines += ["No fine-tuning runs yet.", ""]
    findings.append(("2. Two-stage fine-tuning beats training from scratch on hard worlds (Fig. 4)",
                     bool(wins) and all(wins), f"fine-tuned ahead on {sum(wins)} of {len(wins)} hard worlds"))

    # Fig. 5
    lines += ["## Fig. 5: the curriculum ablation", ""]
    ablation = out / "ablation"
    runs: list[RunResult] = [r for r in (load_run(d) for d in sorted(ablation.iterdir()) if d.is_dir())
                             if r is not None] if ablation.exists() else []
    if runs:
        write_report(ablation, runs)
        lines += [(ablation / "ablation.md").read_text().split("\n", 2)[2], "![ablation](ablation/ablation.png)", ""]
        headline = fixed_targets(runs[0].run_dir)[-1]
        means = {}
        for r in runs:
            means.setdefault(r.condition, []).append(r.final(headline)[0])
        means = {c: sum(v) / len(v) for c, v in means.items()}
        best = max(means, key=lambda c: (means[c], c == "s1+s2"))
        missing = [c for c in ("s1+s2", "no-curriculum") if c not in means]
        ok3 = not missing and means["s1+s2"] >= max(means.values()) and means["s1+s2"] > means["no-curriculum"]
        findings.append(("3. S1+S2 is the most sample-efficient curriculum (Fig. 5)", ok3,
                         f"final {headline}: " + ", ".join(f"{c} {_pct(v)}" for c, v in means.items())
                         + f"; best: {best}" + (f"; undecided: no {' or '.join(missing)} run" if missing else "")))
    else:
        lines += ["No ablation runs yet.", ""]
        findings.append(("3. S1+S2 is the most sample-efficient curriculum (Fig. 5)", False, "no runs"))

    # Table II
    from curlnav.evaluation.compare import UNSEEN

    lines += ["## Table II: the trained policies against the classical planners on unseen worlds", "",
              "`tare-l` is a map-less local planner after TARE's (the paper's TARE-L): a library of path primitives "
              "blocked by the static beams of the current scan, scored by the goal's direction and clearance, on the "
              "policy's own inputs; `dwa` is the dynamic window approach on the same scan; both ignore movable "
              "objects, as the paper forced TARE-L to. `oracle` is A* on the true static map tracked on the true "
              "pose: an upper bound, not a baseline. `+ global plan`: the policy's goal is a waypoint 3 m ahead on "
              f"the oracle's A* path. Suite `{UNSEEN.name}`: {UNSEEN.about}; never used in training.", ""]
    summary = read_csv(out / "table2" / "summary.csv")
    if summary:
        shown = out / "table2" / "table2.md"
        old = "```\n" + (out / "table2" / "table.txt").read_text().rstrip() + "\n```"  # before the suite
        lines += [shown.read_text().rstrip() if shown.exists() else old, "", "Trajectories: `table2/trajectories/`.", ""]
        overall = {r["agent"]: r for r in summary if r.get("world") == "all"}
        policy = overall.get("s1+s2")
        baseline = overall.get("tare-l") or next(
            (r for a, r in overall.items() if a in ("oracle", "planner (TARE-L stand-in)")), None)
        if policy and baseline:
            ps, qs = float(policy["success_rate"]), float(baseline["success_rate"])
            column = ("base_collision_events_per_trial" if policy.get("base_collision_events_per_trial") not in (None, "")
                      else "base_collisions_per_trial")  # collisions as the paper counts them, when recorded
            pc, qc = float(policy[column]), float(baseline[column])
            findings.append(("4. The curriculum policy succeeds at least as often as TARE-L, with fewer base "
                             "collisions, on unseen worlds (Table II)", ps >= qs and pc < qc,
                             f"policy {_pct(ps)}, {pc:.2f} base collisions/trial; {baseline['agent']} {_pct(qs)}, "
                             f"{qc:.2f}" + (" (contact events)" if column.endswith("events_per_trial") else " (contact steps)")))
    else:
        lines += ["No comparison yet.", ""]

    lines[2:2] = ["## Findings", "", "| finding | reproduced? | our numbers |", "|---|---|---|"] + [
        f"| {name} | {'reproduced' if ok else 'not reproduced'} | {numbers} |" for name, ok, numbers in findings] + [""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
