"""``curlnav eval``, ``curlnav policy run`` and ``curlnav rollout``: the parsers and their handlers.

Imported when the parser is built, so only the planner registry (``curlnav.nav``, no planner
module) loads here; the handlers import what they run. The MCAP recorder (``curlnav.ros2.recording``)
is handed to the comparison and the episode loop from here: the evaluation library does not import it.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from functools import partial
from pathlib import Path

from curlnav.nav import agents_help
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


def _eval_agent(spec: str, env_config, global_plan: bool = False, resample: bool = False) -> tuple[str, object]:
    """``(label, agent)`` of one AGENT argument of ``curlnav eval``: the one place the command makes
    its agents, in its own process and in every worker process (``eval_plan``'s ``agent_of``). A
    policy is checked against the robot of ``env_config`` before it loads (``policy_loader``); with
    ``resample`` (``--suite barn``) a policy of that robot with a coarser LiDAR reads the suite's
    scan through the ROS 2 node's resampler, without it a policy drives only the robot it was made for."""
    from curlnav.evaluation.barn import policy_loader
    from curlnav.nav import build_stack, stack_of

    return build_stack(stack_of(spec, global_plan), env_config, policy_loader(env_config, _load_policy, resample=resample))


def eval_plan(options: dict, say: Callable[[str], None] | None = None):
    """What ``curlnav eval`` runs (a ``curlnav.evaluation.compare.ComparisonPlan``), from its parsed
    options as plain data (``vars(args)`` without ``func``), checked (``ValueError``, one line); the
    lines it prints at the start go to ``say``. The command calls it, and so does every worker
    process of ``--jobs N`` (``curlnav.evaluation.parallel``) with the same options, so both make
    the worlds and the agents alike."""
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.compare import SUITES, ComparisonPlan, episode_pairs
    from curlnav.sim import get_world
    from curlnav.sim.robots import load_profile

    say = say or (lambda line: None)
    if options["suite"] == "barn":
        return _barn_plan(options, say)
    if options["worlds"] is not None:
        raise ValueError("--worlds A-B picks worlds of --suite barn; use --world for other worlds")
    suite = SUITES[options["suite"]] if options["suite"] else None
    seeds = options["seeds"]
    if suite is not None:
        given = [flag for flag, key in (("--world", "world"), ("--pair", "pair"), ("--pairs", "pairs"),
                                        ("--episodes", "episodes"), ("--seeds", "seeds")) if options[key] is not None]
        if given:
            raise ValueError(f"--suite {suite.name} fixes the worlds, pairs and ball placements; drop {', '.join(given)}")
        seeds = 1  # the suite's pairs list a pair once per ball placement
        say(f"suite {suite.name}: {suite.about}")
    seeds = 1 if seeds is None else seeds
    if seeds < 1:
        raise ValueError(f"--seeds must be at least 1, got {seeds}")
    sensor_noise = SensorNoiseConfig.from_strings(options["sensor_noise"], options["sensor_set"] or ())
    profile = load_profile(options["robot"] or "husky")
    env_config = profile.apply(ExperimentConfig().eval_env.replace(sensor_noise=sensor_noise))
    if options["robot"]:
        say(f"robot {profile.describe()}")
    if not sensor_noise.is_exact:
        say(f"sensor noise: {sensor_noise.describe()} (every agent sees the same noisy observations)")
    chosen = (options["pair"] or (), options["pairs"], options["episodes"])
    mcap = options["mcap"]
    return ComparisonPlan(env_config, tuple(suite.worlds if suite else options["world"] or ["open-room"]), get_world,
                          suite.pairs_of if suite else lambda world: episode_pairs(world, *chosen),
                          tuple(options["agents"]),
                          partial(_eval_agent, env_config=env_config, global_plan=options["global_plan"]), seeds,
                          sensor_noise.senses, suite, mcap, _mcap_file if mcap else None, options["global_plan"])


def _barn_plan(options: dict, say: Callable[[str], None]):
    """``eval_plan`` of ``--suite barn``: the BARN Challenge's worlds, rules and robot."""
    from curlnav.config import ExperimentConfig
    from curlnav.evaluation.barn import jackal_env_config
    from curlnav.evaluation.compare import ComparisonPlan
    from curlnav.worlds.barn_challenge import barn

    if options["robot"] not in (None, "jackal"):
        raise ValueError(f"--suite barn drives the Jackal (the challenge's robot); drop --robot {options['robot']}")
    given = [flag for flag, key in (("--world", "world"), ("--pair", "pair"), ("--pairs", "pairs"),
                                    ("--episodes", "episodes"), ("--seeds", "seeds")) if options[key] is not None]
    if given:
        raise ValueError(f"--suite barn fixes the worlds (--worlds A-B picks some), the start and the goal; drop "
                         f"{', '.join(given)}")
    numbers = barn.parse_range(options["worlds"]) if options["worlds"] is not None else list(range(barn.COUNT))
    sensor_noise = SensorNoiseConfig.from_strings(options["sensor_noise"], options["sensor_set"] or ())
    env_config = jackal_env_config(ExperimentConfig().eval_env.replace(sensor_noise=sensor_noise))
    say(f"suite barn: the BARN Challenge's worlds {numbers[0]}-{numbers[-1]} ({len(numbers)}), a Jackal from "
        f"({barn.START[0]:g}, {barn.START[1]:g}) facing +y to the goal 10 m ahead, within {barn.GOAL_RADIUS:g} m, "
        f"{barn.TIME_LIMIT:g} s, any collision ends the trial; in curlnav's simulator, not Gazebo")
    if not sensor_noise.is_exact:
        say(f"sensor noise: {sensor_noise.describe()} (every agent sees the same noisy observations)")
    # resample: checks each artefact's robot before it loads it, and reads the full scan for a coarser LiDAR
    return ComparisonPlan(env_config, tuple(numbers), barn.world, lambda world: list(world.pairs),
                          tuple(options["agents"]),
                          partial(_eval_agent, env_config=env_config, global_plan=options["global_plan"], resample=True),
                          senses=sensor_noise.senses, global_plan=options["global_plan"])


def _eval_options(args: argparse.Namespace) -> tuple[dict, int]:
    """The parsed options as plain data (what a worker process gets) and the number of jobs."""
    from curlnav.evaluation.parallel import default_jobs

    options = {key: value for key, value in vars(args).items() if key != "func"}
    jobs = default_jobs() if options.get("jobs") is None else options["jobs"]
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    return options, jobs


def _eval_agents(plan) -> dict:
    """Every agent of ``plan`` (label -> agent), in order; an agent named twice is refused."""
    agents = dict(plan.agent_of(spec) for spec in plan.agents)
    if len(agents) < len(plan.agents):
        raise ValueError(f"an agent is named twice: {' '.join(plan.agents)}")
    _say_deploy_stacks(list(plan.agents), plan.global_plan)
    return agents


def _worker_pool(plan, options: dict, jobs: int):
    """The worker processes of ``--jobs`` (none for one job or one unit), started before this process
    builds its worlds and agents, so that they load meanwhile; each makes the plan with ``eval_plan``."""
    from curlnav.evaluation.parallel import WorkerPool, worker_count

    return WorkerPool(f"{__name__}:eval_plan", options, worker_count(jobs, plan))


def _run_trials(comparison, plan, pool, rows_file: Path | None, columns: list[str], row_of: Callable):
    """Every trial of ``comparison``, in the workers of ``pool`` if it has any
    (``curlnav.evaluation.parallel.run_trials``), a line each as it finishes (flushed) and its row
    (``row_of(episode)``) appended to ``rows_file`` at once."""
    from curlnav.evaluation.parallel import Progress, RowStream, run_trials

    progress = Progress(comparison.episode_count(plan.seeds), plan.env_config.end_on_base_collision)
    with RowStream(rows_file, columns) as rows:

        def on_trial(episode) -> None:
            rows.write(row_of(episode))  # first: a trial's printed line means its row is in the file
            print(progress.line(episode), flush=True)

        return run_trials(comparison, plan, pool, on_trial)


def _ended(trials, out: Path | None) -> int:
    """0 when every trial finished. Else a line of how many did (kept in ``out``), then 130 after
    SIGINT, or a one-line error (``ValueError``) naming the worker's unit that failed."""
    if trials.stopped is None:
        return 0
    count = f"{len(trials.episodes)} of {trials.total} trials finished" + (
        f"; their rows and summary are in {out}" if out and trials.episodes else "")
    if trials.stopped == "interrupted":
        print(f"interrupted: {count}", flush=True)
        return 130
    raise ValueError(f"{trials.stopped}; {count}")


def agent_specs(args: argparse.Namespace) -> list[str]:
    """The agents ``curlnav eval`` runs: its AGENT arguments, then each ``--stack FILE``."""
    specs = list(args.agents or []) + list(getattr(args, "stack", None) or [])
    if not specs:
        raise ValueError("name an agent (a planner, a policy artefact with its suffixes) or give --stack FILE.yaml")
    return specs


def _cmd_eval(args: argparse.Namespace) -> int:
    """Evaluate one or more agents (policies and the planners of ``curlnav.nav.PLANNERS``) side
    by side (``curlnav.evaluation.compare``), ``--jobs`` (world, agent) units at a time."""
    from curlnav.evaluation.compare import (
        OVERALL,
        Comparison,
        Episode,
        comparison_table,
        draw_trajectories,
        summarise,
        table_ii,
        write_csv,
    )
    from curlnav.worlds.core.pairs import check_pairs_possible

    args.agents = agent_specs(args)
    options, jobs = _eval_options(args)
    if args.suite == "barn":
        return _eval_barn(options, jobs)
    plan = eval_plan(options, say=print)
    suite = plan.suite
    out = Path(args.out) if args.out else None
    with _worker_pool(plan, options, jobs) as pool:
        worlds = [plan.world_of(spec) for spec in plan.worlds]
        for world in worlds:
            check_pairs_possible(world)
        agents = _eval_agents(plan)
        comparison = Comparison(agents, worlds, plan.pairs_of, plan.env_config)
        trials = _run_trials(comparison, plan, pool, out / "episodes.csv" if out else None, Episode.columns(),
                             Episode.row)
    episodes = trials.episodes
    summaries = summarise(episodes, senses=plan.senses)
    for s in summaries:
        if s.world != OVERALL or len(worlds) > 1:
            print(s.line())
    if suite is not None and episodes:
        print(table_ii(summaries))
    elif (len(agents) > 1 or len(worlds) > 1) and episodes:
        print(comparison_table(summaries))
    if args.mcap:
        print(f"wrote {len(episodes)} MCAP episodes in {args.mcap}")
    if out:
        files = write_csv(episodes, summaries, out)
        if suite is not None:
            (out / "table2.md").write_text(f"Suite {suite.name}: {suite.about}.\n\n{table_ii(summaries)}\n")
        if trials.stopped is None:
            pictures = draw_trajectories(episodes, worlds, out / "trajectories", plan.env_config.robot.base_width / 2)
            print(f"wrote {files['episodes']}, {files['summary']} and {len(pictures)} trajectory pictures in "
                  f"{out / 'trajectories'}")
        else:
            print(f"wrote {files['episodes']} and {files['summary']}")
    return _ended(trials, out)


def _eval_barn(options: dict, jobs: int) -> int:
    """``--suite barn``: the BARN Challenge's worlds, rules and score (``curlnav.evaluation.barn``)."""
    from curlnav.evaluation.barn import BarnTrial, reference_line, summarise, write_csv
    from curlnav.evaluation.compare import Comparison

    def trial_of(e) -> BarnTrial:
        return BarnTrial.of(e.agent, int(e.world.rsplit("-", 1)[1]), e.success, e.base_collisions, e.time_s,
                            e.control_steps)

    plan = eval_plan(options, say=print)
    out = Path(options["out"]) if options["out"] else None
    with _worker_pool(plan, options, jobs) as pool:
        comparison = Comparison(_eval_agents(plan), [plan.world_of(n) for n in plan.worlds], plan.pairs_of,
                                plan.env_config)
        run = _run_trials(comparison, plan, pool, out / "barn-trials.csv" if out else None,
                          [f.name for f in dataclasses.fields(BarnTrial)], lambda e: dataclasses.asdict(trial_of(e)))
    trials = [trial_of(e) for e in run.episodes]
    summaries = summarise(trials, senses=plan.senses)
    print(reference_line())
    for summary in summaries:
        for trial in sorted((t for t in trials if t.agent == summary.agent), key=lambda t: t.world):
            print(trial.line())
        print(summary.line())
    if out and trials:
        files = write_csv(trials, summaries, out)
        print(f"wrote {files['trials']} and {files['summary']}")
    return _ended(run, out)


def _cmd_policy_run(args: argparse.Namespace) -> int:
    from curlnav.evaluation.animation import drive_and_draw
    from curlnav.evaluation.protocol import evaluation_config
    from curlnav.nav import build_stack, deploy_notice, deploy_stack, parse_agent
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
    network = speed_limited(policy, profile.robot)
    stack = parse_agent(args.artefact + ("+bare" if args.bare else ""))
    label = f"policy-v{policy.version}"
    _, agent = build_stack(stack, env_config, controller=network)  # as it is shipped, as in eval and ros2 run
    helpers = "" if args.bare else deploy_stack(args.artefact)
    if helpers:
        print(deploy_notice(args.artefact, "--bare: the network alone"))
        label += helpers.replace("+", "-")
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
    p.add_argument("agents", nargs="*", metavar="AGENT", help=agents_help())
    p.add_argument("--stack", action="append", metavar="FILE.yaml",
                   help="a navigation stack file (curlnav stack show AGENT --out FILE.yaml writes one): every role's "
                        "entry and settings; its label names it in the results; repeat for several")
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
                        "(downloaded once by scripts/vendor-real-maps.py, not in the repository; used whole, unknown "
                        "cells are walls), 6 pairs 6-20 m apart and 8 balls on their paths per map, fixed by seed; "
                        "the same outputs as unseen. barn: the BARN Challenge's 300 worlds (vendored: in the "
                        "repository), its start, goal, 1 m radius, 100 s, collision rule and score, with the Jackal and "
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
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="run the (world, agent) units in N worker processes at once (default: the CPUs this "
                        "process may use; 1: all in this process); every trial's outcome is the same whatever N. "
                        "A line per trial as it finishes; Ctrl-C keeps the finished trials (--out) and exits 130")
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


def _say_deploy_stacks(specs: list[str], global_plan: bool = False) -> None:
    """One line per artefact named alone whose metadata ships it with helpers (``deploy_stack``)."""
    from curlnav.nav import deploy_notice

    for spec in specs:
        line = deploy_notice(spec, f"{spec}+bare: the network alone", global_plan=global_plan)
        if line:
            print(line)


def _cmd_stack_show(args: argparse.Namespace) -> int:
    """Print the fully resolved stack of an agent argument, artefact or stack file, as YAML."""
    from curlnav.nav import stack_of

    text = stack_of(args.agent, args.global_plan).to_yaml()
    if args.out:
        out = Path(args.out)
        if out.suffix not in (".yaml", ".yml"):
            raise ValueError(f"--out {args.out}: a stack file ends in .yaml")
        tmp = out.with_name(out.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(out)
        print(f"wrote {out}: the stack of {args.agent} (curlnav eval --stack {out} runs it)")
    else:
        print(text, end="")
    return 0


def add_stack_command(sub) -> None:
    """``stack show``: the navigation stack an agent argument names, every role with its settings."""
    p = sub.add_parser("stack", help="navigation stacks: which entry each role runs, with its settings")
    stack_sub = p.add_subparsers(dest="stack_command", required=True)
    show = stack_sub.add_parser("show", help="print the fully resolved stack of an agent as YAML: every role, its "
                                             "entry and every setting (docs/guide/evaluation.md)",
                                epilog="e.g. curlnav stack show policies/namo-robust --out robust.yaml; "
                                       "curlnav eval --stack robust.yaml --world namo-office:90 --pairs 4")
    show.add_argument("agent", metavar="AGENT", help="an agent argument as curlnav eval takes it (a planner, a "
                                                     "policy artefact with suffixes or +bare) or a stack file")
    show.add_argument("--global-plan", action="store_true", help="as curlnav eval --global-plan")
    show.add_argument("--out", default=None, metavar="FILE.yaml", help="write the YAML to FILE instead of printing it")
    show.set_defaults(func=_cmd_stack_show)
