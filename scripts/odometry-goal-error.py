"""How far from the true goal an agent that steers by its odometry can end, whatever it has learnt.

Drives the ``oracle`` (A* on the true map, steered by the true pose) through the trials of
``curlnav eval --world ... --pairs N --seeds S --sensor-noise PRESET``: the same worlds, pairs,
ball placements and noise draws. Where it reaches the goal, the robot's odometry estimate then
is off the true pose by some distance; an agent that reads its goal from odometry (every policy
here, and any map-less stack) would have stopped where its odometry put the goal, that far from
the true one, and fails when it is more than the goal tolerance (0.8 m). The oracle drives the
shortest route: a policy that wanders, turns and pushes more drifts more, so the fraction printed
is a lower bound on such failures (an upper bound on success).

    .venv/bin/python scripts/odometry-goal-error.py --sensor-noise realistic [--sensor-set heading=wheels]
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from curlnav.config import ExperimentConfig
from curlnav.evaluation.compare import SEED_STRIDE, episode_pairs
from curlnav.evaluation.protocol import EVAL_SEED, evaluate
from curlnav.nav import make_planner
from curlnav.nav.perception.scan_match import ScanMatchedPolicy, compose, relative
from curlnav.sim import NamoEnv, get_world
from curlnav.sim.config import SensorNoiseConfig


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", action="append",
                        default=None, help="worlds (default: the issue-37 bar's namo-office/indoor/auditorium:300)")
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--sensor-noise", default="realistic")
    parser.add_argument("--sensor-set", action="append", default=[])
    parser.add_argument("--tolerance-m", type=float, default=0.8, help="the goal tolerance (m)")
    parser.add_argument("--scan-match", action="store_true",
                        help="measure the laser odometry of +scan-match (curlnav.nav.perception.scan_match) instead")
    args = parser.parse_args()
    worlds = args.world or ["namo-office:300", "namo-indoor:300", "namo-auditorium:300"]
    noise = SensorNoiseConfig.from_strings(args.sensor_noise, args.sensor_set)
    cfg = ExperimentConfig().eval_env.replace(sensor_noise=noise)
    errors: list[float] = []
    reached = trials = 0
    for spec in worlds:
        world = get_world(spec)
        pairs = episode_pairs(world, (), args.pairs, None)
        env = NamoEnv(world, cfg)
        try:
            for k in range(args.seeds):
                agent = make_planner("oracle", cfg)
                if args.scan_match:  # the oracle still steers by the true pose; the estimate runs beside it
                    agent = ScanMatchedPolicy(agent, cfg)

                def record(i: int, info: dict, agent=agent) -> None:
                    nonlocal reached, trials
                    trials += 1
                    if info["is_success"]:
                        reached += 1
                        estimate = info["odometry"]
                        if args.scan_match:  # its estimate at the last act, moved on by the wheels since
                            estimate = compose(agent.pose, relative(agent.poses[-1], info["odometry"]))
                        (x, y, _), (ex, ey, _) = info["pose"], estimate
                        errors.append(math.hypot(ex - x, ey - y))

                evaluate(agent, world, pairs, cfg, seed=EVAL_SEED + k * SEED_STRIDE, on_episode=record, env=env)
        finally:
            env.close()
    print(f"sensor noise: {noise.describe()}" + (" (laser odometry, +scan-match)" if args.scan_match else ""))
    if not errors:
        print(f"oracle reached none of {trials} goals: no odometry error to measure")
        return 1
    e = np.array(errors)
    off = int((e > args.tolerance_m).sum())
    print(f"oracle reached {reached} of {trials} goals; odometry off the true pose there: median {np.median(e):.2f} m, "
          f"90th percentile {np.percentile(e, 90):.2f} m, max {e.max():.2f} m")
    print(f"{off} of {reached} ({100 * off / max(reached, 1):.0f} %) more than {args.tolerance_m:g} m off: an agent "
          f"steering by odometry would stop outside the goal tolerance there")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
