"""The figure of docs/results/s2-knobs: held-out success on T-Maze p4 over the fine-tune's environment
steps, one line per knob and seed, from each run folder's eval.csv (rows with pair p4).

    python docs/results/s2-knobs/plot_knobs.py OUT.png START_SUCCESS RUN_DIR [RUN_DIR ...]

START_SUCCESS: the starting policy's p4 success (``curlnav eval``, 30 episodes), drawn at 0 steps.

A run folder named ``<knob>`` is seed 0, ``<knob>-s1`` seed 1 (the knob runs' naming)."""
import csv
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

out, start, runs = Path(sys.argv[1]), float(sys.argv[2]), [Path(p) for p in sys.argv[3:]]
knobs = list(dict.fromkeys(r.name.removesuffix("-s1") for r in runs))
colours = {k: plt.get_cmap("tab10")(i) for i, k in enumerate(knobs)}
fig, ax = plt.subplots(figsize=(10, 4.2))
for run in runs:
    knob, seed = run.name.removesuffix("-s1"), 1 if run.name.endswith("-s1") else 0
    rows = [r for r in csv.DictReader((run / "eval.csv").open()) if r["pair"] == "p4"]
    xs = [int(float(r["env_steps"])) / 1000 for r in rows]
    ys = [float(r["success_rate"]) for r in rows]
    ax.plot(xs, ys, color=colours[knob], ls="-" if seed == 0 else "--", marker="o", ms=2.5, lw=1.2,
            label=f"{knob} (seed {seed})")
ax.plot([0], [start], "k*", ms=10, label=f"start: barn policy ({start:.0%}, 30 episodes)")
ax.set_xlabel("fine-tune environment steps (thousands; S2 on T-Maze, sub-steps p1..p4)")
ax.set_ylabel("held-out success on p4 (10 episodes)")
ax.set_ylim(-0.03, 1.03)
ax.grid(alpha=0.3)
ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
ax.set_title("S2 fine-tunes from one barn policy (248k steps): what each learner knob bought", fontsize=10)
fig.tight_layout()
fig.savefig(out, dpi=110)
