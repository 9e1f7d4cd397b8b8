"""``curlnav bench actor``: what one actor process makes of its core, K environments at a time.

Rows, each the same number of environment steps after a warm-up episode, episodes of
``episode_steps`` steps (no end at a collision, so the rows do the same work):

- ``bare environment``: ``NamoEnv.step`` with uniformly random actions, nothing else (the ceiling);
- ``actor process, K envs``: what an actor process does per step: ``VectorEpisodeLoop`` with the
  default network (random weights loaded from safetensors bytes as the actor service loads a
  broadcast, past the warm-up, exploration noise), one batched policy call for the K
  environments on the actor's inference backend (``actor.inference``: ONNX Runtime by default,
  or PyTorch), the n-step writer, and a ``TransitionBatch`` encoded every ``batch_steps``
  environment steps, as it goes on the wire (the Zenoh put is not timed); with ``--memory N``
  the network reads the memory's ring of N sectors (``curlnav.memory``), which the loop builds
  from each environment's odometry at every step.

``ratio`` is a row's steps/s over the bare environment's. Run it pinned to one core (``taskset -c
0 curlnav bench actor``) with nothing else running: actors run one per core.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

LOW, HIGH = (0.0, -1.0, 0.0), (1.0, 1.0, 1.0)  # the action box
HELP = ("an actor process's steps/s with K environments on one core vs the bare environment (run it as: taskset -c 0 "
        "curlnav bench actor)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default="barn-3x3:0", help="world: built-in, YAML or FAMILY:SEED")
    p.add_argument("--envs", default="1,2,4,8", help="comma-separated environments per process, one row each")
    p.add_argument("--steps", type=int, default=4000, help="timed environment steps per row")
    p.add_argument("--episode-steps", type=int, default=200, help="steps per episode")
    p.add_argument("--repeats", type=int, default=1, help="runs per row; the fastest is shown")
    p.add_argument("--inference", default="onnx", help="the policy network's backend(s), comma-separated: onnx (the "
                                                       "actors' default, actor.inference), torch")
    p.add_argument("--memory", default="0", help="comma-separated sectors of the network memory's ring (memory.beams), "
                                                 "a set of rows each; 0: no memory")


def main(args: argparse.Namespace) -> int:
    try:
        envs = tuple(int(k) for k in args.envs.split(","))
    except ValueError:
        raise SystemExit(f"curlnav: error: --envs takes whole numbers separated by commas, got {args.envs[:40]!r}") from None
    if not envs or min(envs) < 1 or args.steps < 1 or args.episode_steps < 1 or args.repeats < 1:
        raise SystemExit("curlnav: error: --envs, --steps, --episode-steps and --repeats must be at least 1")
    backends = tuple(args.inference.split(","))
    if not set(backends) <= {"onnx", "torch"}:
        raise SystemExit(f"curlnav: error: --inference takes onnx and/or torch, got {args.inference[:40]!r}")
    try:
        memories = tuple(int(m) for m in args.memory.split(","))
    except ValueError:
        raise SystemExit(f"curlnav: error: --memory takes whole numbers separated by commas, got {args.memory[:40]!r}") from None
    if min(memories) < 0:
        raise SystemExit("curlnav: error: --memory must be at least 0")
    run_actor_bench(args.world, envs=envs, steps=args.steps, episode_steps=args.episode_steps, repeats=args.repeats,
                    inference=backends, memories=memories)
    return 0


@dataclass(frozen=True)
class ActorBenchRow:
    name: str
    envs: int
    steps: int
    seconds: float

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds


def bare_env(world: str, steps: int, episode_steps: int, seed: int = 0) -> ActorBenchRow:
    import numpy as np

    from curlnav.sim import EnvConfig, NamoEnv

    cfg = EnvConfig(max_episode_steps=episode_steps, end_on_base_collision=False)
    env = NamoEnv(world, cfg)
    rng = np.random.default_rng(seed)
    try:
        env.reset(seed=seed)
        for _ in range(episode_steps):  # warm-up: the scene, numba
            env.step(rng.uniform(LOW, HIGH).astype(np.float32))
        env.reset(seed=seed + 1)
        start = time.perf_counter()
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(rng.uniform(LOW, HIGH).astype(np.float32))
            if terminated or truncated:
                env.reset()
        return ActorBenchRow("bare environment", 1, steps, time.perf_counter() - start)
    finally:
        env.close()


def actor_process(world: str, envs: int, steps: int, episode_steps: int, batch_steps: int = 24,
                  seed: int = 0, inference: str = "onnx", memory: int = 0) -> ActorBenchRow:
    import numpy as np
    from safetensors.torch import save as safetensors_save

    from curlnav.actor.vector import VectorEpisodeLoop, VectorNStepWriter
    from curlnav.config import D4PGConfig, MemoryConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.networks import Actor, BehaviourPolicy
    from curlnav.memory import MemoryObserver
    from curlnav.proto.messages import TransitionBatch
    from curlnav.sim import EnvConfig, NamoEnv

    cfg = EnvConfig(max_episode_steps=episode_steps, end_on_base_collision=False)
    layout = ObservationLayout.of(cfg, MemoryConfig(beams=memory))
    d4pg = D4PGConfig()
    policy = BehaviourPolicy(layout, d4pg, sigma=0.3, warmup_steps=0, rng=np.random.default_rng(seed),
                             inference=inference)
    network = Actor(layout, d4pg)
    policy.load_weights(safetensors_save({k: v.contiguous() for k, v in network.state_dict().items()}))
    loop = VectorEpisodeLoop([NamoEnv(world, cfg) for _ in range(envs)], policy.batch,
                             VectorNStepWriter(layout, envs, d4pg.n_step, d4pg.discount),
                             memory=[MemoryObserver(layout, cfg.lidar_fov) for _ in range(envs)] if memory else None)
    seq = 0

    def run(n: int) -> None:
        nonlocal seq
        since_batch = 0
        target = loop.steps + n
        while loop.steps < target:
            for k in loop.waiting():
                loop.begin(k, seed=seed + 1000 * k + loop.episodes, options={"world": world})
            before = loop.steps
            ended = loop.step()
            since_batch += loop.steps - before
            if ended or since_batch >= batch_steps:
                frames = loop.flush()
                if frames.num_frames or frames.num_transitions:
                    TransitionBatch("actor-0", seq, 1, frames).encode()
                    seq += 1
                since_batch = 0

    try:
        run(episode_steps * envs)  # warm-up: scenes, numba, torch
        start = time.perf_counter()
        before = loop.steps
        run(steps)
        name = f"actor, {envs} env{'s' if envs > 1 else ''}, {inference}" + (f", memory {memory}" if memory else "")
        return ActorBenchRow(name, envs, loop.steps - before,
                             time.perf_counter() - start)
    finally:
        loop.close()


def run_actor_bench(world: str = "barn-3x3:0", envs: tuple[int, ...] = (1, 2, 4, 8), steps: int = 4000,
                    episode_steps: int = 200, repeats: int = 1, say=print,
                    inference: tuple[str, ...] = ("onnx",), memories: tuple[int, ...] = (0,)
                    ) -> list[tuple[ActorBenchRow, float]]:
    """Print the bare environment's steps/s, then each K's, with its ratio; return the rows."""
    import torch

    torch.set_num_threads(1)
    say(f"# curlnav bench actor: {world}, {steps} timed environment steps per row, episodes of {episode_steps} "
        f"steps, torch threads 1, fastest of {repeats}")
    bare = max((bare_env(world, steps, episode_steps) for _ in range(repeats)), key=lambda r: r.steps_per_second)
    say(f"{bare.name:<40} {bare.steps_per_second:8.0f} steps/s")
    rows = []
    for backend, memory, k in ((b, m, k) for b in inference for m in memories for k in envs):
        row = max((actor_process(world, k, steps, episode_steps, inference=backend, memory=memory)
                   for _ in range(repeats)), key=lambda r: r.steps_per_second)
        ratio = row.steps_per_second / bare.steps_per_second
        rows.append((row, ratio))
        say(f"{row.name:<40} {row.steps_per_second:8.0f} steps/s  ratio {ratio:.2f}")
    best_row, best_ratio = max(rows, key=lambda r: r[1])
    say(f"best: {best_row.name}, ratio {best_ratio:.2f} of the bare environment")
    return rows
