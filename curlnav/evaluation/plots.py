"""Learning-curve pictures from a run folder's CSV logs."""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _read(path: Path) -> list[dict]:
    """Rows of a CSV log: numbers as floats, other values (stage names, pairs) as strings."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        rows = []
        for row in csv.DictReader(f):
            out: dict = {}
            for k, v in row.items():
                if v in ("", None) or k is None:
                    continue
                try:
                    out[k] = float(v)
                except ValueError:
                    out[k] = v
            rows.append(out)
        return rows


def _evaluations(rows: list[dict]) -> tuple[list[dict], dict[str, list[tuple[dict, float]]]]:
    """eval.csv rows grouped by evaluation: the mean over its (world, pair) rows, and each pair's
    own series when an evaluation covers several pairs."""
    groups: dict = {}
    for r in rows:
        if "success_rate" in r:
            groups.setdefault(r.get("evaluation", len(groups)), []).append(r)
    means, pairs = [], {}
    for group in groups.values():
        means.append({**group[0], "success_rate": sum(r["success_rate"] for r in group) / len(group)})
        if len(group) > 1:
            for r in group:
                pairs.setdefault(f"{r.get('world', '')}/{r.get('pair', '')}", []).append((group[0], r["success_rate"]))
    return means, pairs


def _legend_below(ax, handles=None, labels=None) -> None:
    """The legend under the axes (below its x label), where it covers no data."""
    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)


def plot_learning_curve(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Success rate (training, last 100 episodes; held-out evaluation) against wall-clock minutes
    and environment steps, plus critic loss. Writes ``learning_curve.png`` in the run folder; the
    legends sit under the panels, off the data."""
    run_dir = Path(run_dir)
    train = _read(run_dir / "metrics.csv")
    evals, pairs = _evaluations(_read(run_dir / "eval.csv"))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), dpi=100)
    for ax, key, label in ((axes[0], "wall_s", "wall clock (min)"), (axes[1], "env_steps", "environment steps")):
        scale = 60.0 if key == "wall_s" else 1.0
        if train:
            ax.plot([r[key] / scale for r in train], [r.get("train_success_100", 0) for r in train],
                    label="training success (last 100 episodes, with noise)", color="tab:blue")
        if evals:
            ax.plot([r.get(key, 0) / scale for r in evals], [r["success_rate"] for r in evals], "o-",
                    label="evaluation success (greedy; mean over pairs)", color="tab:red")
        for name, series in pairs.items():
            ax.plot([r.get(key, 0) / scale for r, _ in series], [v for _, v in series], ".:", lw=0.8, label=name)
        ax.axhline(0.8, ls="--", color="grey", lw=0.8)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel(label)
        ax.set_ylabel("success rate")
        ax.grid(alpha=0.3)
        _legend_below(ax)
    if train:
        axes[2].plot([r["env_steps"] for r in train], [r.get("losses/critic", float("nan")) for r in train],
                     color="tab:purple", label="critic loss")
        ax2 = axes[2].twinx()
        ax2.plot([r["env_steps"] for r in train], [r.get("return_100", float("nan")) for r in train],
                 color="tab:green", label="return (last 100)")
        ax2.set_ylabel("episode return")
        axes[2].set_xlabel("environment steps")
        axes[2].set_ylabel("critic loss (cross-entropy)")
        (loss, loss_label), (ret, ret_label) = (a.get_legend_handles_labels() for a in (axes[2], ax2))
        _legend_below(axes[2], loss + ret, loss_label + ret_label)
    fig.suptitle(f"curlnav learning curve: {run_dir.name}")
    fig.tight_layout()
    out = Path(out) if out else run_dir / "learning_curve.png"
    fig.savefig(out, bbox_inches="tight")  # the legends under the panels included
    plt.close(fig)
    return out
