"""``curlnav eval``, ``curlnav policy run`` and ``curlnav rollout``: the parsers and their handlers.

Imported when the parser is built, so only the planner registry (``curlnav.planners``, no planner
module) loads here; the handlers import what they run. The MCAP recorder (``curlnav.ros2.recording``)
is handed to the comparison and the episode loop from here: the evaluation library does not import it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from curlnav.planners import agents_help
from curlnav.sim.config import SENSOR_NOISE_FIELDS, SENSOR_NOISE_PRESETS, SensorNoiseConfig
from curlnav.worlds.builtin import WORLD_FORMS


def _load_policy(path: str):
    """``curlnav.learner.artefact.load_policy``, imported when a policy is named (not for planners alone)."""
    from curlnav.learner.artefact import load_policy

    return load_policy(path)


def _mcap_file(path, env, observation):
    """The MCAP recorder of ``--mcap``: ROS 2 schemas (``curlnav.ros2.recording.EpisodeMcap``)."""
    from curlnav.ros2.recording import EpisodeMcap

    return EpisodeMcap(path, env, observation)


def _cmd_eval(args: argparse.Namespace) -> int:
    """Evaluate one or more agents (policies and the planners of ``curlnav.planners.PLANNERS``) side
    by side (``curlnav.evaluation.compare``)."""
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.barn import policy_loader
    from curlnav.evaluation.compare import (
        OVERALL,
        SUITES,
        Comparison,
        comparison_table,
        draw_trajectories,
        episode_pairs,
        summarise,
        table_ii,
        write_csv,
    )
    from curlnav.planners import make_agent
    from curlnav.sim import get_world
    from curlnav.sim.robots import load_profile
    from curlnav.worlds.pairs import check_pairs_possible

    if args.suite == "barn":
        return _eval_barn(args)
    if args.worlds is not None:
        raise ValueError("--worlds A-B picks worlds of --suite barn; use --world for other worlds")
    suite = SUITES[args.suite] if args.suite else None
    if suite is not None:
        given = [flag for flag, value in (("--world", args.world), ("--pair", args.pair), ("--pairs", args.pairs),
                                          ("--episodes", args.episodes), ("--seeds", args.seeds)) if value is not None]
        if given:
            raise ValueError(f"--suite {suite.name} fixes the worlds, pairs and ball placements; drop {', '.join(given)}")
        args.seeds = 1  # the suite's pairs list a pair once per ball placement
        print(f"suite {suite.name}: {suite.about}")
    args.seeds = 1 if args.seeds is None else args.seeds
    if args.seeds < 1:
        raise ValueError(f"--seeds must be at least 1, got {args.seeds}")
    sensor_noise = SensorNoiseConfig.from_strings(args.sensor_noise, args.sensor_set or ())
    profile = load_profile(args.robot or "husky")
    env_config = profile.apply(ExperimentConfig().eval_env.replace(sensor_noise=sensor_noise))
    if args.robot:
        print(f"robot {profile.describe()}")
    if not sensor_noise.is_exact:
        print(f"sensor noise: {sensor_noise.describe()} (every agent sees the same noisy observations)")
    worlds = [get_world(spec) for spec in (suite.worlds if suite else args.world or ["open-room"])]
    for world in worlds:
        check_pairs_possible(world)

    load = policy_loader(env_config, _load_policy, resample=False)  # a policy drives only the robot it was made for
    agents = dict(make_agent(spec, env_config, load, args.global_plan) for spec in args.agents)
    if len(agents) < len(args.agents):
        raise ValueError(f"an agent is named twice: {' '.join(args.agents)}")
    _say_deploy_stacks(args.agents)
    pairs_of = suite.pairs_of if suite else lambda w: episode_pairs(w, args.pair or (), args.pairs, args.episodes)
    comparison = Comparison(agents, worlds, pairs_of, env_config)
    from tqdm import tqdm

    with tqdm(total=comparison.episode_count(args.seeds), unit="episode", desc="eval", disable=None) as bar:
        episodes = comparison.run(args.seeds, on_episode=lambda e: bar.update(), mcap=args.mcap,
                                  recorder=_mcap_file if args.mcap else None)
    summaries = summarise(episodes, senses=sensor_noise.senses)
    for s in summaries:
        if s.world != OVERALL or len(worlds) > 1:
            print(s.line())
    if suite is not None:
        print(table_ii(summaries))
    elif len(agents) > 1 or len(worlds) > 1:
        print(comparison_table(summaries))
    if args.mcap:
        print(f"wrote {len(episodes)} MCAP episodes in {args.mcap}")
    if args.out:
        files = write_csv(episodes, summaries, args.out)
        if suite is not None:
            (Path(args.out) / "table2.md").write_text(f"Suite {suite.name}: {suite.about}.\n\n{table_ii(summaries)}\n")
        pictures = draw_trajectories(episodes, worlds, Path(args.out) / "trajectories", env_config.robot.base_width / 2)
        print(f"wrote {files['episodes']}, {files['summary']} and {len(pictures)} trajectory pictures in "
              f"{Path(args.out) / 'trajectories'}")
    return 0


def _eval_barn(args: argparse.Namespace) -> int:
    """``--suite barn``: the BARN Challenge's worlds, rules and score (``curlnav.evaluation.barn``)."""
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.barn import (
        BarnTrial,
        jackal_env_config,
        policy_loader,
        reference_line,
        summarise,
        write_csv,
    )
    from curlnav.evaluation.compare import Comparison
    from curlnav.planners import make_agent
    from curlnav.worlds import barn

    if args.robot not in (None, "jackal"):
        raise ValueError(f"--suite barn drives the Jackal (the challenge's robot); drop --robot {args.robot}")
    given = [flag for flag, value in (("--world", args.world), ("--pair", args.pair), ("--pairs", args.pairs),
                                      ("--episodes", args.episodes), ("--seeds", args.seeds)) if value is not None]
    if given:
        raise ValueError(f"--suite barn fixes the worlds (--worlds A-B picks some), the start and the goal; drop "
                         f"{', '.join(given)}")
    numbers = barn.parse_range(args.worlds) if args.worlds is not None else list(range(barn.COUNT))
    sensor_noise = SensorNoiseConfig.from_strings(args.sensor_noise, args.sensor_set or ())
    env_config = jackal_env_config(ExperimentConfig().eval_env.replace(sensor_noise=sensor_noise))
    load = policy_loader(env_config, _load_policy)  # checks each artefact's robot before it loads it
    agents = dict(make_agent(spec, env_config, load, args.global_plan) for spec in args.agents)
    if len(agents) < len(args.agents):
        raise ValueError(f"an agent is named twice: {' '.join(args.agents)}")
    _say_deploy_stacks(args.agents)
    print(f"suite barn: the BARN Challenge's worlds {numbers[0]}-{numbers[-1]} ({len(numbers)}), a Jackal from "
          f"({barn.START[0]:g}, {barn.START[1]:g}) facing +y to the goal 10 m ahead, within {barn.GOAL_RADIUS:g} m, "
          f"{barn.TIME_LIMIT:g} s, any collision ends the trial; in curlnav's simulator, not Gazebo")
    if not sensor_noise.is_exact:
        print(f"sensor noise: {sensor_noise.describe()} (every agent sees the same noisy observations)")
    comparison = Comparison(agents, [barn.world(n) for n in numbers], lambda world: list(world.pairs), env_config)
    from tqdm import tqdm

    with tqdm(total=comparison.episode_count(1), unit="episode", desc="barn", disable=None) as bar:
        episodes = comparison.run(1, on_episode=lambda e: bar.update())
    trials = [BarnTrial.of(e.agent, int(e.world.rsplit("-", 1)[1]), e.success, e.base_collisions, e.time_s)
              for e in episodes]
    summaries = summarise(trials, senses=sensor_noise.senses)
    print(reference_line())
    for summary in summaries:
        for trial in sorted((t for t in trials if t.agent == summary.agent), key=lambda t: t.world):
            print(trial.line())
        print(summary.line())
    if args.out:
        files = write_csv(trials, summaries, args.out)
        print(f"wrote {files['trials']} and {files['summary']}")
    return 0


def _cmd_policy_run(args: argparse.Namespace) -> int:
    from curlnav.evaluation.animation import drive_and_draw
    from curlnav.evaluation.protocol import evaluation_config
    from curlnav.planners import deploy_notice, deploy_stack, make_agent
    from curlnav.policy import PolicyArtefact
    from curlnav.sim.robots import PROFILES, check_observation, check_robot, load_profile, recorded_robot, speed_limited

    policy = PolicyArtefact(args.artefact)
    if args.robot is None:  # the artefact's own robot, when it is a built-in profile
        try:  # an artefact that records no robot at all is from the Husky's days
            name = recorded_robot(policy.metadata)[0] if "robot" in policy.metadata else "husky"
        except ValueError as exc:
            raise ValueError(f"{args.artefact}: {exc}; give the robot with --robot") from None
        if name not in PROFILES:
            raise ValueError(f"{args.artefact}: trained for the {name}, not a built-in robot: give its profile "
                             f"file with --robot FILE.yaml")
        args.robot = name
    profile = load_profile(args.robot)
    env_config = profile.apply(evaluation_config())
    check_robot(policy.metadata, profile.robot, args.artefact)
    check_observation(policy.metadata, env_config, args.artefact)
    agent = speed_limited(policy, profile.robot)
    stack = "" if args.bare else deploy_stack(args.artefact)
    label = f"policy-v{policy.version}"
    if stack:  # an artefact drives as it is shipped, as in eval and ros2 run
        print(deploy_notice(args.artefact, "--bare: the network alone"))
        _, agent = make_agent(args.artefact + stack, env_config, lambda name: agent)
        label += stack.replace("+", "-")
    return drive_and_draw(agent, args.world, args.pair, args.seed, env_config, args.out, label, gif=args.gif,
                          mcap=args.mcap, recorder=_mcap_file if args.mcap else None)


def _cmd_rollout(args: argparse.Namespace) -> int:
    """Drive the goal-seeking controller for one episode and draw it."""
    from curlnav.evaluation.animation import drive_and_draw
    from curlnav.sim import EnvConfig
    from curlnav.sim.controllers import GoalSeekingController

    cfg = EnvConfig(max_episode_steps=args.steps, end_on_base_collision=False)
    return drive_and_draw(GoalSeekingController(cfg).act, args.world, args.pair, args.seed, cfg, args.out, "rollout")


def add_commands(sub) -> None:
    """``eval`` and ``policy run`` (``rollout``: ``add_rollout_command``, listed with the worlds)."""
    p = sub.add_parser("eval", help="greedy evaluation on held-out start/goal pairs; several agents side by side",
                       epilog="e.g. curlnav eval tare-l dwa oracle runs/x/policy-best --world namo-office:0 --world "
                              "namo-indoor:0 --pairs 10 --seeds 2 --out results/")
    p.add_argument("agents", nargs="+", metavar="AGENT", help=agents_help())
    p.add_argument("--global-plan", action="store_true",
                   help="every policy's goal input is a waypoint 3 m ahead on the oracle's A* path of the static "
                        "map, advanced as it goes, instead of the final goal (a learned local planner in a "
                        "navigation stack)")
    p.add_argument("--world", action="append",
                   help="built-in world name, world YAML path or FAMILY:SEED; repeat for several (default: open-room)")
    p.add_argument("--pair", action="append", help="start/goal pair name or index; repeat for several "
                                                    "(default: held-out pairs)")
    p.add_argument("--pairs", type=int, default=None, help="the first N held-out pairs of each world, once per seed")
    p.add_argument("--episodes", type=int, default=None,
                   help="episodes per world and seed: held-out pairs (default: 50), or the --pair pairs in turn "
                        "(default: one each)")
    p.add_argument("--seeds", type=int, default=None,
                   help="runs of every pair, each with its own ball places (worlds that re-place balls on reset; "
                        "default 1)")
    p.add_argument("--suite", choices=["unseen", "real", "barn"], default=None,
                   help="a fixed set of worlds nobody trains on. unseen: NAMO office, indoor and auditorium at seeds "
                        "300 and 301, barn-3x3 and slam-office at seed 300; 8 trials each: pairs x ball placements; prints "
                        "Table II's layout (success with a 95%% interval, contact events, time, SPL), and with --out "
                        "writes table2.md beside the CSV files and pictures. real: nine real buildings' SLAM maps "
                        "(vendored, whole; unknown cells are walls), 6 pairs 6-20 m apart and 8 balls on their paths "
                        "per map, fixed by seed; the same outputs as unseen. barn: the BARN Challenge's 300 worlds "
                        "(vendored), its start, goal, 1 m radius, 100 s, collision rule and score, with the Jackal and "
                        "its LiDAR, in curlnav's simulator (not Gazebo); per world and overall success, collisions, "
                        "timeouts, mean time and score beside the challenge's published DWA figure")
    p.add_argument("--worlds", default=None, metavar="A-B",
                   help="with --suite barn: only BARN worlds A to B (0-299; default all)")
    p.add_argument("--robot", default=None, metavar="PROFILE",
                   help="the robot every agent drives: husky (default), jackal (the default and only choice of "
                        "--suite barn) or a profile file (docs/guide/robots.md); a policy artefact trained for another "
                        "robot is refused")
    p.add_argument("--sensor-noise", default="none", metavar="PRESET",
                   help=f"imperfect senses for every agent: {', '.join(SENSOR_NOISE_PRESETS)} (default none: the "
                        "exact simulator); range noise, dropouts, spurious returns, label errors, latency, odometry "
                        "drift (heading from an IMU in realistic and harsh), acceleration limits, lag and wheel slip, "
                        "drawn from each episode's seed "
                        "(docs/guide/environment.md)")
    p.add_argument("--sensor-set", action="append", metavar="FIELD=VALUE",
                   help=f"override one field of the --sensor-noise preset; repeat for several. Fields: "
                        f"heading (wheels or imu), {', '.join(SENSOR_NOISE_FIELDS)}")
    p.add_argument("--out", default=None, help="folder for episodes.csv, summary.csv and trajectories/*.png")
    p.add_argument("--mcap", default=None, metavar="DIR",
                   help="also write every episode of every agent to an MCAP file with ROS 2 schemas in DIR "
                        "(AGENT__WORLD__PAIR__NNN.mcap; Foxglove opens them), as `curlnav policy run --mcap`")
    p.set_defaults(func=_cmd_eval)

    policy = sub.add_parser("policy", help="use exported policy artefacts")
    policy_sub = policy.add_subparsers(dest="policy_command", required=True)
    p = policy_sub.add_parser("run", help="drive the robot with an artefact and draw the trajectory")
    p.add_argument("artefact", help="artefact folder (with metadata.json, actor.onnx)")
    p.add_argument("--world", default="open-room", help=WORLD_FORMS)
    p.add_argument("--pair", default=None, help="start/goal pair name or index (default: drawn)")
    p.add_argument("--seed", type=int, default=0, help="episode seed (pair draw, ball places)")
    p.add_argument("--out", default="runs/policy-run", help="folder for the picture")
    p.add_argument("--gif", action="store_true", help="also write an animated GIF of the episode beside the picture")
    p.add_argument("--robot", default=None, metavar="PROFILE",
                   help="the robot: husky, jackal or a profile file (default: the artefact's own built-in robot); "
                        "an artefact trained for another robot is refused")
    p.add_argument("--mcap", default=None, metavar="FILE",
                   help="also write the episode to an MCAP file with ROS 2 schemas (Foxglove opens it)")
    p.add_argument("--bare", action="store_true",
                   help="the network alone: without the helpers its artefact's metadata ships it with (deploy)")
    p.set_defaults(func=_cmd_policy_run)


def add_rollout_command(sub) -> None:
    """``rollout``: the goal-seeking controller for one episode, drawn."""
    p = sub.add_parser("rollout", help="drive a reactive controller for one episode and draw the trajectory")
    p.add_argument("--world", default="door-corridor", help=WORLD_FORMS)
    p.add_argument("--pair", default=None, help="start/goal pair name or index (default: drawn)")
    p.add_argument("--steps", type=int, default=300, help="episode length limit (steps of 0.2 s)")
    p.add_argument("--seed", type=int, default=0, help="episode seed (pair draw, ball places)")
    p.add_argument("--out", default="runs/rollout", help="folder for the picture")
    p.set_defaults(func=_cmd_rollout)


def _say_deploy_stacks(specs: list[str]) -> None:
    """One line per artefact named alone whose metadata ships it with helpers (``deploy_stack``)."""
    from curlnav.planners import deploy_notice

    for spec in specs:
        line = deploy_notice(spec, f"{spec}+bare: the network alone")
        if line:
            print(line)
