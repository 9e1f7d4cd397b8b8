"""``curlnav ros2 run`` and ``curlnav ros2 sim``: the parsers and their handlers."""

from __future__ import annotations

import argparse
import signal
import sys
import time

from curlnav.nav import agents_help


def add_ros2_commands(sub) -> None:
    """The ``ros2`` command group of ``curlnav``."""
    ros2 = sub.add_parser("ros2", help="the policy as a ROS 2 node and the simulator as a ROS 2 robot, over DDS "
                                       "(ROS 2 type names, rt/ topics, ROS_DOMAIN_ID; no ROS install needed)")
    ros2_sub = ros2.add_subparsers(dest="ros2_command", required=True)
    p = ros2_sub.add_parser("run", help="AGENT as a node: /scan, /odom, /goal_pose, /goal_cancel (/plan) in; "
                                        "/cmd_vel, /arm_cmd, /goal_state out")
    p.add_argument("agent", metavar="AGENT", help=agents_help(map_less_only=True))
    p.add_argument("--global-plan", action="store_true", help="follow /plan (nav_msgs/Path) waypoint by waypoint")
    p.add_argument("--scan-plan", action="store_true",
                   help="follow an A* plan on a map of the node's own scans (curlnav.nav.global_planners.scan_map; "
                        "no /plan needed)")
    p.add_argument("--rescue", action="store_true",
                   help="let dwa on a plan over the node's own scans drive while the policy stalls "
                        "(curlnav.nav.recovery.rescue)")
    p.add_argument("--bare", action="store_true",
                   help="the network alone: without the helpers its artefact's metadata ships it with (deploy)")
    p.add_argument("--shield", action="store_true",
                   help="check each command's arc against the scan before it goes out (curlnav.nav.safety.shield): "
                        "one into an obstacle is replaced by the nearest safe one")
    p.add_argument("--track", action="store_true",
                   help="vote the scan's movable labels (intensities) over the last scans before anything reads "
                        "them (curlnav.nav.perception.label_filter): a segmenter's one-frame errors are dropped")
    p.add_argument("--scan-match", action="store_true",
                   help="laser odometry in front of everything (curlnav.nav.perception.scan_match): the goal and the pose "
                        "the helpers keep their maps in come from matching each scan to a reference scan, fused with "
                        "/odom")
    p.add_argument("--rate-hz", type=float, default=None, help="control rate (default: the policy's, 5 Hz)")
    p.add_argument("--silence-s", type=float, default=0.5,
                   help="stop when /scan or /odom is older than this, or no /cmd_vel went out for this long (s)")
    p.add_argument("--scan-frame", default="base_link", help="the frame_id /scan must carry")
    p.add_argument("--odom-frame", default="odom", help="the frame_id of /odom, /goal_pose and /plan")
    p.add_argument("--goal-tolerance", type=float, default=0.8, help="goal reached within this distance (m)")
    p.add_argument("--give-up-s", type=float, default=30.0,
                   help="give a goal up after this long without 0.25 m of progress (s; /goal_state gave_up)")
    p.add_argument("--max-goal-m", type=float, default=10_000.0,
                   help="refuse goals with |x| or |y| beyond this in the odometry frame (m; /goal_state refused)")
    p.add_argument("--max-nan-fraction", type=float, default=0.05,
                   help="NaN ranges read as no return up to this fraction of a scan; a scan with more is refused "
                        "(the robot stops)")
    p.add_argument("--stats-every-s", type=float, default=10.0, help="log counts and loop latency this often (s)")
    _common(p)
    p.set_defaults(func=_cmd_run)
    p = ros2_sub.add_parser("sim", help="the simulator as a ROS 2 robot: /scan, /odom, /tf, /map out; /cmd_vel, "
                                        "/arm_cmd in; real time")
    p.add_argument("world", help="built-in name, world YAML or FAMILY:SEED")
    p.add_argument("--pair", default=None, help="start/goal pair (index or name; default: drawn with --seed)")
    p.add_argument("--seed", type=int, default=0, help="seed of the pair draw, the ball places and the sensor noise")
    p.add_argument("--sensor-noise", default="none", metavar="PRESET",
                   help="publish imperfect senses: none (default), realistic or harsh; /scan carries the noisy ranges "
                        "and labels, /odom and /tf the drifting odometry (docs/guide/environment.md)")
    p.add_argument("--sensor-set", action="append", metavar="FIELD=VALUE",
                   help="override one field of the --sensor-noise preset (heading: wheels or imu, or a magnitude: "
                        "docs/guide/environment.md); repeat for several")
    _common(p)
    p.set_defaults(func=_cmd_sim)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="husky", metavar="PROFILE",
                   help="the robot: husky (default), jackal or a profile file (docs/guide/robots.md); a policy artefact "
                        "trained for another robot is refused")
    p.add_argument("--domain-id", type=int, default=None, help="DDS domain (default: ROS_DOMAIN_ID, else 0)")
    p.add_argument("--loopback", action="store_true", help="keep DDS on this machine (loopback, no multicast)")
    p.add_argument("--remap", action="append", default=[], metavar="KEY:=/TOPIC",
                   help="rename a topic, ROS style (scan:=/front/scan); repeatable")
    p.add_argument("--duration-s", type=float, default=None, help="stop after this many seconds (default: run on)")


def _stopper(duration_s: float | None):
    """A ``stop()`` that turns true on SIGINT, SIGTERM or after ``duration_s``."""
    stopped = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopped.append(True))
    end = time.monotonic() + duration_s if duration_s is not None else float("inf")
    return lambda: bool(stopped) or time.monotonic() >= end


def _bus(args, max_sample_bytes: int | None = None):
    from .topics import Bus, domain_id_from_env

    domain = args.domain_id if args.domain_id is not None else domain_id_from_env()
    if not 0 <= domain <= 232:
        raise ValueError(f"--domain-id must be 0-232, got {domain}")
    return Bus(domain, loopback=args.loopback, max_sample_bytes=max_sample_bytes), domain


def _agent(name: str, robot: str = "husky"):
    """``(agent, layout)`` for ``curlnav ros2 run AGENT``: a map-less planner of the registry
    (``curlnav.nav.PLANNERS``) on the evaluation environment's scan and robot profile
    ``robot``, or a policy artefact with the layout of its metadata, refused (one line) when it
    was trained for another robot than ``robot``."""
    from curlnav.nav import canonical, make_planner
    from curlnav.nav.registry import planners
    from curlnav.sim.robots import check_robot, load_profile

    profile = load_profile(robot)

    from .node import ScanLayout

    planner = canonical(name)
    if planner is not None:
        if not planners()[planner].map_less:
            raise ValueError(f"{name} needs the true map and pose, which the node has not; on a robot: a policy "
                             f"artefact or a map-less planner ({', '.join(p.name for p in planners().values() if p.map_less)})")
        from curlnav.config import ExperimentConfig

        env_config = profile.apply(ExperimentConfig().eval_env)
        return make_planner(planner, env_config), ScanLayout.from_env_config(env_config)
    from curlnav.policy import PolicyArtefact

    policy = PolicyArtefact(name)
    check_robot(policy.metadata, profile.robot, name)
    layout = ScanLayout.of(policy.metadata)
    if layout.limits_problem():
        raise ValueError(f"{name}: {layout.limits_problem()}: the node cannot bound its commands")
    if layout.observation_size != policy.observation_size:
        raise ValueError(f"{name}: the metadata's layout gives {layout.observation_size} values, the policy "
                         f"takes {policy.observation_size}")
    return policy, layout


def node_env_config(layout, robot: str = "husky"):
    """The environment the node's stack is built for: the evaluation environment of robot profile
    ``robot`` with the scan, frames and command scale of ``layout`` (what the node feeds it)."""
    import dataclasses

    from curlnav.config import ExperimentConfig
    from curlnav.sim.robots import load_profile

    env = load_profile(robot).apply(ExperimentConfig().eval_env)
    return env.replace(lidar_beams=layout.beams, lidar_fov=layout.fov_rad, lidar_max_range=layout.max_range_m,
                       range_frames=layout.range_frames, label_frames=layout.label_frames,
                       goal_frames=layout.goal_frames, control_period=layout.control_period_s,
                       robot=dataclasses.replace(env.robot, max_linear_speed=layout.max_linear_speed,
                                                 max_angular_speed=layout.max_angular_speed,
                                                 max_reverse_speed=0.0))  # the node sends forward commands only


def deployed(agent, layout, robot: str = "husky", stack=None):
    """``agent`` (a policy or a map-less planner, as ``_agent`` gives it) inside ``stack`` (a
    ``curlnav.nav.NavStack`` naming it as its controller; None: the agent alone), built by
    ``curlnav.nav.build_stack`` for what the node feeds it (``node_env_config``). A plan on the true
    map is the node's own (``/plan``, ``follow_plan``), never built here."""
    if stack is None:
        from curlnav.memory import remembering

        return remembering(agent, layout.fov_rad)  # a network with a memory builds it from /odom
    import dataclasses

    from curlnav.nav import build_stack

    if stack.global_planner is not None and stack.global_planner.entry == "true-map":
        stack = dataclasses.replace(stack, global_planner=None)
    return build_stack(stack, node_env_config(layout, robot), controller=agent)[1]


def node_stack(args: argparse.Namespace):
    """``(stack, follow_plan)`` of ``curlnav ros2 run``'s agent and flags: the flags spelled as an
    agent argument's suffixes and parsed (``curlnav.nav.parse_agent``: an artefact named alone
    drives with the stack it ships); ``follow_plan``: the policy follows ``/plan`` (``--global-plan``,
    or a shipped plan on the true map)."""
    from curlnav.nav import parse_agent

    helpers = args.scan_plan or args.rescue or args.shield or args.track or args.scan_match
    if args.bare and (helpers or args.global_plan):
        raise ValueError("--bare drives the network alone: drop --global-plan, --scan-plan, --rescue, --shield, "
                         "--track and --scan-match")
    flags = ((args.scan_plan, "+scan-plan"), (args.rescue, "+rescue"), (args.shield, "+shield"),
             (args.track, "+track"), (args.scan_match, "+scan-match"), (args.bare, "+bare"))
    stack = parse_agent(args.agent + "".join(suffix for given, suffix in flags if given))
    planned = stack.global_planner.entry if stack.global_planner is not None else None
    if args.global_plan and planned == "scan-map":
        raise ValueError(f"{args.agent} ships with +scan-plan, which --global-plan replaces; add --bare, or "
                         f"name the helpers yourself")
    return stack, args.global_plan or planned == "true-map"


def _cmd_run(args: argparse.Namespace) -> int:
    from .node import NodeConfig, PolicyNode, run_node
    from .topics import NODE_MAX_SAMPLE_BYTES, NODE_TOPICS, remap

    if args.scan_plan and args.global_plan:
        raise ValueError("--scan-plan and --global-plan both set the policy's waypoints; choose one")
    policy, layout = _agent(args.agent, args.robot)
    stack, follow_plan = node_stack(args)
    if not (args.bare or args.scan_plan or args.rescue or args.shield or args.track or args.scan_match):
        from curlnav.nav import deploy_notice

        notice = deploy_notice(args.agent, "--bare: the network alone", global_plan=args.global_plan)
        if notice:
            print(notice)
    policy = deployed(policy, layout, args.robot, stack)
    config = NodeConfig(rate_hz=args.rate_hz or 1.0 / layout.control_period_s, silence_s=args.silence_s,
                        scan_frame=args.scan_frame, odom_frame=args.odom_frame, goal_tolerance_m=args.goal_tolerance,
                        give_up_s=args.give_up_s, max_goal_m=args.max_goal_m,
                        max_nan_fraction=args.max_nan_fraction)
    topics = remap(NODE_TOPICS, args.remap)
    node = PolicyNode(policy, layout, config, follow_plan=follow_plan)
    bus, domain = _bus(args, max_sample_bytes=NODE_MAX_SAMPLE_BYTES)
    print(f"curlnav ros2 run: {args.agent} on domain {domain}, {config.rate_hz:g} Hz; "
          + ", ".join(f"{k} {t.name}" for k, t in topics.items() if k != "plan" or follow_plan),
          file=sys.stderr, flush=True)
    latency = run_node(node, bus, topics, stop=_stopper(args.duration_s), stats_every_s=args.stats_every_s)
    print(f"curlnav ros2 run: {dict(node.counts)}; {latency.summary()}", file=sys.stderr, flush=True)
    return 0


def _cmd_sim(args: argparse.Namespace) -> int:
    from .sim import SimRobot, run_sim
    from .topics import SIM_TOPICS, remap

    topics = remap(SIM_TOPICS, args.remap)
    from curlnav.sim import EnvConfig
    from curlnav.sim.config import SensorNoiseConfig
    from curlnav.sim.robots import load_profile

    noise = SensorNoiseConfig.from_strings(args.sensor_noise, args.sensor_set or ())
    config = load_profile(args.robot).apply(EnvConfig(sensor_noise=noise))
    robot = SimRobot(args.world, args.pair, seed=args.seed, config=config)
    try:
        bus, domain = _bus(args)
        x, y, yaw = robot.pose
        pair = robot.env.pair
        print(f"curlnav ros2 sim: {robot.env.world.name} on domain {domain}, start ({x:.2f}, {y:.2f}), "
              f"pair {pair.name} goal ({pair.gx:.2f}, {pair.gy:.2f}); " + ", ".join(t.name for t in topics.values()),
              file=sys.stderr, flush=True)
        steps = run_sim(robot, bus, topics, stop=_stopper(args.duration_s))
        print(f"curlnav ros2 sim: {steps} steps", file=sys.stderr, flush=True)
    finally:
        robot.close()
    return 0
