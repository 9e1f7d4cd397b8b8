"""``curlnav bench env``: environment steps per second against a bare PyBullet loop, per world.

For each world it prints the static geometry as built (obstacle cells merged into rectangles,
wall faces merged into segments, segments PyBullet holds: equal, or the scene refuses to run),
then the full ``NamoEnv.step`` rate and two floors on the same scene: the bare loop (the same 10
physics steps plus one 241-ray ``rayTestBatch`` through every wall: what a LiDAR made of
PyBullet rays costs) and the physics alone.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from curlnav.sim.config import EnvConfig
    from curlnav.worlds.core.world import World

HELP = "environment steps/s on one core vs a bare PyBullet loop"
DEFAULT_WORLDS = ("bench-36m", "barn-3x3:0", "slam-office:0")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--steps", type=int, default=5000, help="timed environment steps per world")
    p.add_argument("--world", action="append",
                   help="world to measure (repeat for several): built-in, YAML or FAMILY:SEED "
                        f"(default: {', '.join(DEFAULT_WORLDS)})")
    p.add_argument("--no-pin", action="store_true", help="do not pin the process to one CPU core")


def main(args: argparse.Namespace) -> int:
    from curlnav.worlds.builtin import get_world

    specs = args.world or list(DEFAULT_WORLDS)
    run_env_bench(steps=args.steps, worlds=[get_world(spec) for spec in specs], pin=not args.no_pin)
    return 0


@dataclass(frozen=True)
class EnvBenchResult:
    world: str
    rectangles: int
    wall_segments: int
    segments_in_physics: int
    env_steps_per_second: float
    bare_steps_per_second: float
    physics_steps_per_second: float
    steps: int
    episodes: int

    @property
    def ratio(self) -> float:
        """Environment steps/s over the bare loop's."""
        return self.env_steps_per_second / self.bare_steps_per_second


def _pin_to_one_core() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned (no sched_setaffinity)"


def _start_pose(world: World, cfg: EnvConfig) -> tuple[float, float, float]:
    import numpy as np

    from curlnav.worlds.core.pairs import check_pairs_possible

    if world.pairs:
        pair = world.pairs[0]
    else:
        sampler = check_pairs_possible(world, (cfg.robot.base_length, cfg.robot.base_width))
        pair = sampler.draw(np.random.default_rng(0))
    return pair.x, pair.y, pair.yaw


def bare_pybullet_steps_per_second(world: World, cfg: EnvConfig, steps: int, rays: bool = True) -> float:
    """The floor: the same world's bodies, the same physics substeps, and (``rays``) one
    241-ray batch through the full geometry, nothing else; the robot moves as in the env."""
    import numpy as np

    from curlnav.sim.bullet import import_pybullet
    from curlnav.sim.scene import RAY_MASK, Scene

    pb = import_pybullet()
    scene = Scene(world, cfg)
    x, y, yaw = _start_pose(world, cfg)
    scene.reset((x, y, yaw), [(b.x, b.y) for b in world.balls])
    c = scene.client
    n = cfg.lidar_beams
    angles = np.linspace(-cfg.lidar_fov / 2, cfg.lidar_fov / 2, n)
    starts = np.tile([x, y, cfg.lidar_height], (n, 1))
    ends = starts.copy()
    ends[:, 0] += cfg.lidar_max_range * np.cos(angles + yaw)
    ends[:, 1] += cfg.lidar_max_range * np.sin(angles + yaw)
    substeps = cfg.physics_substeps
    t0 = time.perf_counter()
    for _ in range(steps):
        for _ in range(substeps):
            pb.stepSimulation(physicsClientId=c)
        if rays:
            pb.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=RAY_MASK, physicsClientId=c)
    elapsed = time.perf_counter() - t0
    scene.close()
    return steps / elapsed


def env_steps_per_second(world: World | str, cfg: EnvConfig, steps: int, seed: int = 0) -> tuple[float, int]:
    """Full ``NamoEnv.step`` (physics, contacts, LiDAR, reward, stacked observation), with a
    wandering action sequence, resets included. Returns (steps/s, episodes)."""
    import numpy as np

    from curlnav.sim.env import NamoEnv

    env = NamoEnv(world, cfg)
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


def bench_world(world: World, cfg: EnvConfig, steps: int) -> EnvBenchResult:
    """Measure one world (see the module docstring) and print its lines."""
    from curlnav.sim.geometry import merge_cells_into_rectangles
    from curlnav.sim.scene import Scene

    rectangles = len(merge_cells_into_rectangles(world.occupancy))
    scene = Scene(world, cfg)  # raises StaticGeometryError if PyBullet lost a wall face
    segments, held, meshes = len(scene.static_segments), scene.static_segments_in_physics, scene.static_mesh_count
    scene.close()
    print(f"world: {world.name} {world.size[0]:.0f} m x {world.size[1]:.0f} m at {world.resolution} m, "
          f"{int(world.occupancy.sum())} obstacle cells = {rectangles} rectangles merged; "
          f"{segments} wall segments in {meshes} meshes, {held} present in physics"
          f" ({'equal' if held == segments else 'MISSING ' + str(segments - held)}); "
          f"{len(world.balls)} balls, {len(world.doors)} doors")
    warm = max(steps // 20, 50)
    env_steps_per_second(world, cfg, warm)  # first-call costs (numba, PyBullet) out of the timed part
    bare_pybullet_steps_per_second(world, cfg, warm)
    env_rate, episodes = env_steps_per_second(world, cfg, steps)
    bare_rate = bare_pybullet_steps_per_second(world, cfg, steps)
    physics_rate = bare_pybullet_steps_per_second(world, cfg, steps, rays=False)
    result = EnvBenchResult(world.name, rectangles, segments, held, env_rate, bare_rate, physics_rate, steps, episodes)
    print(f"  env:     {env_rate:7.0f} steps/s  ({steps} steps, {episodes} episodes, full observation)")
    print(f"  bare:    {bare_rate:7.0f} steps/s  (stepSimulation x {cfg.physics_substeps} + one {cfg.lidar_beams}-ray "
          f"rayTestBatch through every wall)")
    print(f"  physics: {physics_rate:7.0f} steps/s  (stepSimulation x {cfg.physics_substeps} only)")
    print(f"  ratio env/bare: {result.ratio:.2f}")
    return result


def run_env_bench(steps: int = 5000, worlds: list[World] | None = None, cfg: EnvConfig | None = None,
                  pin: bool = True) -> list[EnvBenchResult]:
    """Benchmark each of ``worlds`` (default: bench-36m, barn-3x3-0 and slam-office-0)."""
    from curlnav.sim.bullet import import_pybullet
    from curlnav.sim.config import EnvConfig

    pb = import_pybullet()
    cfg = cfg or EnvConfig()
    if worlds is None:
        from curlnav.worlds.builtin import get_world
        from curlnav.worlds.families import generate

        worlds = [get_world("bench-36m"), generate("barn-3x3", 0), generate("slam-office", 0)]
    pinned = _pin_to_one_core() if pin else "not pinned"
    print(f"machine: {platform.machine()} {platform.processor() or ''} cpus={os.cpu_count()} "
          f"python={platform.python_version()} pybullet={pb.getAPIVersion()} ({pinned})")
    print(f"settings: control period {cfg.control_period} s, {cfg.physics_substeps} physics substeps, "
          f"{cfg.solver_iterations} solver iterations, {cfg.lidar_beams} beams, observation {cfg.observation_size} floats")
    return [bench_world(world, cfg, steps) for world in worlds]
