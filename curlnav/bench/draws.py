"""``curlnav bench draws``: environment steps/s of the episode loop when every episode (or every
K-th) is in a newly drawn world of a distribution, against one fixed world.

Each row runs the real ``EpisodeLoop`` (``NamoEnv``, an n-step writer, a uniform random policy)
for the same number of steps, episodes of ``episode_steps`` steps (no end at a collision, so
every row has the same episodes), after one warm-up episode; the figure counts world
generation and scene building, which is what drawing costs.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass

HELP = "episode-loop steps/s drawing a new world per episode (or every K) vs one world"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("distribution", nargs="?", default="barn-3x3:0-99", help="a world distribution, FAMILY:LO-HI(...)")
    p.add_argument("--steps", type=int, default=3000, help="timed environment steps per row")
    p.add_argument("--episode-steps", type=int, default=150, help="steps per episode")
    p.add_argument("--every", default="1,4", help="comma-separated episodes per fresh world, one row each")
    p.add_argument("--repeats", type=int, default=1, help="runs per row, taken in turn; the fastest is shown")


def main(args: argparse.Namespace) -> int:
    every = tuple(int(k) for k in args.every.split(","))
    run_draw_bench(args.distribution, steps=args.steps, episode_steps=args.episode_steps, every=every,
                   repeats=args.repeats)
    return 0


@dataclass(frozen=True)
class DrawBenchRow:
    mode: str
    steps: int
    episodes: int
    seconds: float
    worlds_generated: int
    scenes_built: int

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds

    def line(self) -> str:
        return (f"{self.mode:<44} {self.steps_per_second:8.0f} steps/s  ({self.steps} steps, {self.episodes} episodes, "
                f"{self.worlds_generated} worlds generated, {self.scenes_built} scenes built)")


def _measure(mode: str, spec, steps: int, episode_steps: int, seed: int) -> DrawBenchRow:
    import numpy as np

    from curlnav.actor.loop import EpisodeLoop
    from curlnav.layout import ObservationLayout
    from curlnav.replay import NStepWriter
    from curlnav.sim import EnvConfig, NamoEnv
    from curlnav.worlds.distribution import WorldDraws

    cfg = EnvConfig(max_episode_steps=episode_steps, end_on_base_collision=False)
    layout = ObservationLayout.from_env_config(cfg)
    rng = np.random.default_rng(seed)
    low, high = np.array([0.0, -1.0, 0.0]), np.array([1.0, 1.0, 1.0])
    draws = WorldDraws(seed=seed)
    first = draws.resolve(spec) if isinstance(spec, str) else spec
    loop = EpisodeLoop(NamoEnv(first, cfg), lambda obs: rng.uniform(low, high).astype(np.float32),
                       NStepWriter(layout, 5, 0.99), draws)
    try:
        loop.begin(seed, {"world": spec})  # warm-up: numba, the first scene
        while loop.step() is None:
            loop.flush()
        generated, builds = draws.generated, loop.env.scene_builds
        episodes, start = 0, time.perf_counter()
        loop.begin(seed + 1, {"world": spec})
        for _ in range(steps):
            if loop.step() is not None:
                episodes += 1
                loop.begin(seed + 1 + episodes, {"world": spec})
            loop.flush()
        seconds = time.perf_counter() - start
        return DrawBenchRow(mode, steps, episodes, seconds, draws.generated - generated,
                            loop.env.scene_builds - builds)
    finally:
        loop.close()


def run_draw_bench(distribution: str = "barn-3x3:0-99", steps: int = 3000, episode_steps: int = 150,
                   every: tuple[int, ...] = (1, 4), seed: int = 0, repeats: int = 1) -> list[DrawBenchRow]:
    """One row for the distribution's first world alone, then one per ``every`` (episodes per
    fresh world); each the fastest of ``repeats`` runs taken in turn (on a shared machine the
    other load only ever slows a run down); prints them."""
    from curlnav.worlds.distribution import WorldDistribution

    dist = WorldDistribution.parse(distribution)
    modes = [(f"one world ({dist.family} seed {dist.lo})", dist.world(dist.lo))]
    for k in every:
        label = "new world every episode" if k == 1 else f"new world every {k} episodes (pool {dist.pool})"
        modes.append((label, dataclasses.replace(dist, every=k).key))
    best: dict[str, DrawBenchRow] = {}
    for _ in range(max(repeats, 1)):
        for label, spec in modes:
            row = _measure(label, spec, steps, episode_steps, seed)
            if label not in best or row.seconds < best[label].seconds:
                best[label] = row
    rows = [best[label] for label, _ in modes]
    for row in rows:
        print(row.line(), flush=True)
    return rows
