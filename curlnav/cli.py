"""The ``curlnav`` command line. Each sub-command lives in the module that owns its work."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_rollout(args: argparse.Namespace) -> int:
    """Drive the goal-seeking controller for one episode and draw it."""
    import numpy as np

    from .sim import EnvConfig, NamoEnv
    from .sim.controllers import GoalSeekingController
    from .sim.render import save_env_picture

    cfg = EnvConfig(max_episode_steps=args.steps, end_on_base_collision=False)
    env = NamoEnv(args.world, cfg)
    options = {"pair": args.pair} if args.pair is not None else None
    obs, info = env.reset(seed=args.seed, options=options)
    controller = GoalSeekingController(cfg)
    total = 0.0
    while True:
        obs, reward, terminated, truncated, info = env.step(controller.act(obs))
        total += reward
        if terminated or truncated:
            break
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    picture = out / f"rollout-{env.world.name}-{info['pair']}.png"
    outcome = "reached the goal" if info["is_success"] else ("timed out" if truncated else "stopped")
    save_env_picture(env, picture, title=f"{env.world.name} / {info['pair']}: {outcome} after {info['steps']} steps, "
                                          f"return {total:.1f}, base collisions {info['base_collisions']}")
    print(f"world {env.world.name}, pair {info['pair']}: {outcome} after {info['steps']} steps "
          f"({info['steps'] * cfg.control_period:.1f} s simulated), return {total:.1f}, "
          f"base collisions {info['base_collisions']}, end-effector collisions {info['end_effector_collisions']}")
    print(f"picture: {picture}")
    env.close()
    return 0


def _cmd_bench_env(args: argparse.Namespace) -> int:
    from .sim.bench import run_env_bench

    run_env_bench(steps=args.steps, world=args.world, pin=not args.no_pin)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="curlnav", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("rollout", help="drive a reactive controller for one episode and draw the trajectory")
    p.add_argument("--world", default="door-corridor", help="built-in world name or world YAML path")
    p.add_argument("--pair", default=None, help="start/goal pair name or index (default: drawn)")
    p.add_argument("--steps", type=int, default=300, help="episode length limit (steps of 0.2 s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/rollout", help="folder for the picture")
    p.set_defaults(func=_cmd_rollout)

    bench = sub.add_parser("bench", help="benchmarks that print their figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    p = bench_sub.add_parser("env", help="environment steps/s on one core vs a bare PyBullet loop")
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--world", default="bench-36m")
    p.add_argument("--no-pin", action="store_true", help="do not pin the process to one CPU core")
    p.set_defaults(func=_cmd_bench_env)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "pair", None) is not None and str(args.pair).isdigit():
        args.pair = int(args.pair)
    from .sim.world import WorldError

    try:
        return int(args.func(args) or 0)
    except (WorldError, KeyError) as exc:
        print(f"curlnav: error: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("curlnav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
