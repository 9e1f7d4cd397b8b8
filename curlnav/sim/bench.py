"""``curlnav bench env``: environment steps per second against a bare PyBullet loop."""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from .builtin import get_world
from .config import EnvConfig
from .env import NamoEnv
from .scene import RAY_MASK, Scene
from .world import merge_cells_into_rectangles


@dataclass(frozen=True)
class EnvBenchResult:
    env_steps_per_second: float
    bare_steps_per_second: float
    steps: int
    episodes: int

    @property
    def ratio(self) -> float:
        return self.env_steps_per_second / self.bare_steps_per_second


def _pin_to_one_core() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned (no sched_setaffinity)"


def bare_pybullet_steps_per_second(world_name: str, cfg: EnvConfig, steps: int) -> float:
    """The floor: the same world's bodies, the same physics substeps, one 241-ray batch, nothing else."""
    scene = Scene(get_world(world_name), cfg)
    pair = scene.world.pairs[0]
    scene.reset((pair.x, pair.y, pair.yaw), [(b.x, b.y) for b in scene.world.balls])
    c = scene.client
    n = cfg.lidar_beams
    angles = np.linspace(-cfg.lidar_fov / 2, cfg.lidar_fov / 2, n)
    starts = np.tile([pair.x, pair.y, cfg.lidar_height], (n, 1))
    ends = starts.copy()
    ends[:, 0] += cfg.lidar_max_range * np.cos(angles)
    ends[:, 1] += cfg.lidar_max_range * np.sin(angles)
    substeps = cfg.physics_substeps
    t0 = time.perf_counter()
    for _ in range(steps):
        for _ in range(substeps):
            pb.stepSimulation(physicsClientId=c)
        pb.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=RAY_MASK, physicsClientId=c)
    elapsed = time.perf_counter() - t0
    scene.close()
    return steps / elapsed


def env_steps_per_second(world_name: str, cfg: EnvConfig, steps: int, seed: int = 0) -> tuple[float, int]:
    """Full ``NamoEnv.step`` (physics, contacts, LiDAR, reward, stacked observation), with a
    wandering action sequence, resets included. Returns (steps/s, episodes)."""
    env = NamoEnv(world_name, cfg)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    episodes = 1
    actions = np.stack([rng.uniform(0.3, 1.0, steps), rng.uniform(-0.5, 0.5, steps), rng.uniform(0, 1, steps)], 1)
    t0 = time.perf_counter()
    for i in range(steps):
        _, _, terminated, truncated, _ = env.step(actions[i])
        if terminated or truncated:
            env.reset()
            episodes += 1
    elapsed = time.perf_counter() - t0
    env.close()
    return steps / elapsed, episodes


def run_env_bench(steps: int = 5000, world: str = "bench-36m", cfg: EnvConfig | None = None,
                  pin: bool = True) -> EnvBenchResult:
    cfg = cfg or EnvConfig()
    pinned = _pin_to_one_core() if pin else "not pinned"
    w = get_world(world)
    print(f"machine: {platform.machine()} {platform.processor() or ''} cpus={os.cpu_count()} "
          f"python={platform.python_version()} pybullet={pb.getAPIVersion()} ({pinned})")
    print(f"world: {w.name} {w.size[0]:.0f} m x {w.size[1]:.0f} m, {int(w.occupancy.sum())} obstacle cells "
          f"merged into {len(merge_cells_into_rectangles(w.occupancy))} boxes, "
          f"{len(w.balls)} balls, {len(w.doors)} doors")
    print(f"settings: control period {cfg.control_period} s, {cfg.physics_substeps} physics substeps, "
          f"{cfg.solver_iterations} solver iterations, {cfg.lidar_beams} beams, observation {cfg.observation_size} floats")
    # Warm up both paths once so that neither pays first-call costs in the timed part.
    bare_pybullet_steps_per_second(world, cfg, 200)
    env_steps_per_second(world, cfg, 200)
    env_rate, episodes = env_steps_per_second(world, cfg, steps)
    bare_rate = bare_pybullet_steps_per_second(world, cfg, steps)
    result = EnvBenchResult(env_rate, bare_rate, steps, episodes)
    print(f"env:  {env_rate:8.0f} steps/s  ({steps} steps, {episodes} episodes, full observation)")
    print(f"bare: {bare_rate:8.0f} steps/s  (stepSimulation x {cfg.physics_substeps} + one rayTestBatch)")
    print(f"ratio env/bare: {result.ratio:.2f}")
    return result
