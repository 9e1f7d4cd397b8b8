#!/usr/bin/env python3
"""The BARN suite's scores over the worlds' difficulty: a PNG and a Markdown table.

Reads ``barn-trials.csv`` (``curlnav eval ... --suite barn --out DIR``); the difficulty of a world is
BARN's five metrics (``curlnav.worlds.difficulty.metrics.barn_metrics`` on its grid and its reference path),
z-scored over the 300 worlds and combined as ``distance + visibility + characteristic dimension``
taken negatively plus ``dispersion + tortuosity`` (higher: harder; BARN publishes no weights).

Usage: ``scripts/plot-barn-scores.py TRIALS.csv [TRIALS.csv ...] OUT.png`` (prints the table); with
several files (runs of different agents), an agent found in two keeps the later file's trials.
"""

from __future__ import annotations

import csv
import sys
from collections import defaultdict

import numpy as np

from curlnav.worlds.barn_challenge import barn
from curlnav.worlds.difficulty.metrics import barn_metrics

SIGNS = np.array([-1.0, -1.0, 1.0, -1.0, 1.0])  # distance, visibility, dispersion, char. dimension, tortuosity
BINS = 5


def difficulty() -> np.ndarray:
    metrics = np.array([barn_metrics(barn.grid(n), barn.path_cells(n)) for n in range(barn.COUNT)])
    z = (metrics - metrics.mean(axis=0)) / metrics.std(axis=0)
    return z @ SIGNS


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(sys.argv) < 3:
        print("usage: scripts/plot-barn-scores.py TRIALS.csv [TRIALS.csv ...] OUT.png", file=sys.stderr)
        return 2
    *trials_paths, png = sys.argv[1:]
    scores: dict[str, dict[int, float]] = defaultdict(dict)
    for trials_path in trials_paths:
        with open(trials_path) as f:
            rows = list(csv.DictReader(f))
        for agent in {row["agent"] for row in rows}:
            scores.pop(agent, None)  # the later file's run of an agent replaces an earlier one
        for row in rows:
            scores[row["agent"]][int(row["world"])] = float(row["score"])
    hard = difficulty()
    edges = np.quantile(hard, np.linspace(0, 1, BINS + 1))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), dpi=110)
    header = "| difficulty quintile (worlds) | " + " | ".join(scores) + " |"
    rows = [header, "|---|" + "---|" * len(scores)]
    for b in range(BINS):
        members = [n for n in range(barn.COUNT) if edges[b] <= hard[n] <= edges[b + 1] and (b == 0 or hard[n] > edges[b])]
        cells = []
        for by_world in scores.values():
            values = [by_world[n] for n in members if n in by_world]
            cells.append(f"{np.mean(values):.3f} ({sum(v > 0 for v in values)}/{len(values)} succeeded)" if values else "-")
        rows.append(f"| {b + 1}: {edges[b]:.2f} to {edges[b + 1]:.2f} ({len(members)}) | " + " | ".join(cells) + " |")
    for i, (agent, by_world) in enumerate(scores.items()):
        worlds = sorted(by_world)
        x = hard[worlds]
        y = np.array([by_world[n] for n in worlds])
        axes[0].scatter(x, y + (i - 1) * 0.008, s=9, alpha=0.6, label=agent)
        centres, means = [], []
        for b in range(BINS):
            inside = (x >= edges[b]) & (x <= edges[b + 1])
            if inside.any():
                centres.append((edges[b] + edges[b + 1]) / 2)
                means.append(y[inside].mean())
        axes[1].plot(centres, means, "o-", label=agent)
    axes[1].axhline(0.1693, color="grey", ls="--", lw=1, label="challenge DWA in Gazebo (0.1693)")
    for ax, title in ((axes[0], "score per world"), (axes[1], "mean score per difficulty quintile")):
        ax.set_xlabel("difficulty (sum of signed z-scored BARN metrics; higher is harder)")
        ax.set_ylabel("BARN score (0.5 is the best)")
        ax.set_title(title)
        ax.set_ylim(-0.03, 0.53)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png)
    print("\n".join(rows))
    corr = {agent: np.corrcoef(hard[sorted(w)], [w[n] for n in sorted(w)])[0, 1] for agent, w in scores.items()}
    print("\ncorrelation of score with difficulty: " + ", ".join(f"{a} {c:+.2f}" for a, c in corr.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
