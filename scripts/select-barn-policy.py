#!/usr/bin/env python3
"""Pick a BARN policy on validation courses, never on the challenge's worlds.

Drives each policy artefact given through ``barn-course`` seeds 90-99 (the family's validation
seeds: 0-89 train, 100 and above are held out) at several fills, under the BARN Challenge's rules
(``curlnav.evaluation.barn.jackal_env_config``: the Jackal, the full UST-10LX scan through the ROS 2
node's resampler, success within 1 m, 100 s, any collision ends the trial), and prints per policy
the success, collision and timeout rates and the mean time of the successes; the last line names
the policy with the most successes (ties: the shorter mean time).

A policy argument takes ``curlnav eval``'s suffixes: ``POLICY+shield`` checks it behind the safety
shield (``curlnav.nav.safety.shield``).

``--sensor-noise PRESET`` drives them under a robot's senses (``curlnav eval``'s presets).

Usage: ``scripts/select-barn-policy.py POLICY... [--fills 0.15,0.2,0.25] [--seeds 90-99] [--sensor-noise PRESET]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from curlnav.config import ExperimentConfig  # noqa: E402
from curlnav.evaluation.barn import jackal_env_config, policy_loader  # noqa: E402
from curlnav.evaluation.compare import Comparison  # noqa: E402
from curlnav.learner.artefact import load_policy  # noqa: E402
from curlnav.worlds.barn_challenge.barn_course import barn_course  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("policies", nargs="+")
    p.add_argument("--fills", default="0.15,0.2,0.25", help="fill_pct values of the automaton")
    p.add_argument("--seeds", default="90-99", help="validation seeds A-B (within 90-99)")
    p.add_argument("--sensor-noise", default="none", help="a sensor-noise preset (default none: exact senses)")
    p.add_argument("--sensor-set", action="append", default=[], metavar="FIELD=VALUE", help="override a magnitude")
    args = p.parse_args()
    lo, hi = (int(v) for v in args.seeds.split("-"))
    if not 90 <= lo <= hi <= 99:
        p.error("validation seeds are 90-99 (0-89 train, 100 and above are held out)")
    fills = [float(v) for v in args.fills.split(",")]
    worlds = [barn_course(seed, fill_pct=fill).with_changes(name=f"barn-course-{seed}-fill{fill:g}")
              for seed in range(lo, hi + 1) for fill in fills]
    from curlnav.sim.config import SensorNoiseConfig

    noise = SensorNoiseConfig.from_strings(args.sensor_noise, args.sensor_set)
    env_config = jackal_env_config(ExperimentConfig().eval_env.replace(sensor_noise=noise))
    print(f"senses: {noise.senses}")
    load = policy_loader(env_config, load_policy)
    from curlnav.nav import make_agent

    agents = {spec: make_agent(spec, env_config, load)[1] for spec in args.policies}
    from curlnav.evaluation.commands import _say_deploy_stacks

    _say_deploy_stacks(args.policies)  # an artefact named alone drives with its deploy stack; POLICY+bare: without
    episodes = Comparison(agents, worlds, lambda world: list(world.pairs), env_config).run(1)
    best = None
    for spec in args.policies:
        mine = [e for e in episodes if e.agent == spec]
        ok = [e for e in mine if e.success and e.base_collisions == 0]
        collided = sum(e.base_collisions > 0 for e in mine)
        mean_time = sum(e.time_s for e in ok) / len(ok) if ok else math.nan
        print(f"{spec}: success {len(ok)}/{len(mine)}, collisions {collided}, timeouts {len(mine) - len(ok) - collided}, "
              f"mean time {mean_time:.1f} s")
        key = (len(ok), -mean_time if ok else -math.inf)
        if best is None or key > best[0]:
            best = (key, spec)
    print(f"selected: {best[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
