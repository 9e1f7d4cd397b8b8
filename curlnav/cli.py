"""The ``curlnav`` command line. Each sub-command lives in the module that owns its work."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

#: every world argument takes the same forms (one resolver, ``curlnav.sim.get_world``)
WORLD_HELP = "built-in world name, world YAML path, or FAMILY:SEED for a generated world (e.g. t-maze:0)"

DEFAULT_BENCH_WORLDS = ("bench-36m", "barn-3x3:0", "slam-office:0")


def _cmd_bench_env(args: argparse.Namespace) -> int:
    from curlnav.sim.bench import run_env_bench

    specs = args.world or list(DEFAULT_BENCH_WORLDS)
    run_env_bench(steps=args.steps, worlds=[_world_from_spec(spec) for spec in specs], pin=not args.no_pin)
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from curlnav.run.train import run_train

    return run_train(args)


def _cmd_config_show(args: argparse.Namespace) -> int:
    from curlnav.run.train import show_config

    return show_config(args)


def _cmd_bench_learner(args: argparse.Namespace) -> int:
    from curlnav.learner.bench import run_learner_bench

    run_learner_bench(presets=args.presets.split(","), seconds=args.seconds, batch_size=args.batch, threads=args.threads,
                      device=args.device, variants=args.variants.split(","), check_amp=args.check_amp,
                      check_steps=args.check_steps)
    return 0


def _world_from_spec(spec: str):
    """A world argument, resolved as everywhere else (``curlnav.sim.get_world``): a built-in
    name, a world YAML path, or FAMILY:SEED for a generated world."""
    from curlnav.sim import get_world

    return get_world(spec)


def _parse_params(items: list[str]) -> dict:
    params = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--param takes KEY=VALUE, got {item!r}")
        params[key.replace("-", "_")] = float(value) if any(ch in value for ch in ".e") else int(value)
    return params


def _cmd_worlds_generate(args: argparse.Namespace) -> int:
    from curlnav.sim import save_world
    from curlnav.worlds.families import generate

    out = Path(args.out)
    for seed in range(args.seed, args.seed + args.count):
        world = generate(args.family, seed, **_parse_params(args.param))
        path = save_world(world, out / f"{world.name}.yaml")
        print(f"{path}: {world.size[0]:.1f} m x {world.size[1]:.1f} m, {len(world.pairs)} pairs, "
              f"{len(world.balls)} balls, {len(world.doors)} doors")
    return 0


def _cmd_worlds_show(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from curlnav.sim.render import draw_world
    from curlnav.worlds.rank import measure, measured_pairs, path_points, world_paths

    world = _world_from_spec(args.world)
    pairs = measured_pairs(world)
    _, paths = world_paths(world)
    d = measure(world)
    x0, y0, x1, y1 = world.bounds
    fig, ax = plt.subplots(figsize=(8, 8 * (y1 - y0) / max(x1 - x0, 1e-9) + 0.6), dpi=110)
    draw_world(ax, world, pairs=pairs)
    for path in paths:
        ax.plot(*path_points(world, path), "-", lw=1, color="tab:green")
    ax.set_title(f"{world.name}: Dist {d.distance:.2f}  Vis {d.visibility:.2f}  Disp {d.dispersion:.2f}  "
                 f"CD {d.characteristic_dimension:.2f}  Tor {d.tortuosity:.2f}", fontsize=9)
    out = Path(args.out or f"runs/worlds/{world.name}.png")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    drawn = "" if world.pairs else " (seeded random: the map has none)"
    print(f"{world.name}: {world.size[0]:.1f} m x {world.size[1]:.1f} m, {len(pairs)} pairs{drawn}; picture: {out}")
    return 0


def _cmd_worlds_scatter_balls(args: argparse.Namespace) -> int:
    from curlnav.sim import save_world
    from curlnav.worlds.scatter import scatter_balls

    world = _world_from_spec(args.world)
    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"--out must be a world YAML path (.yaml), got {args.out!r}")
    task = scatter_balls(world, args.count, seed=args.seed, radius=args.radius, mass=args.mass, pairs=args.pairs)
    path = save_world(task.with_changes(name=out.stem), out)
    print(f"{path}: {len(task.balls) - len(world.balls)} balls on the shortest paths of {len(task.pairs)} pairs "
          f"({', '.join(p.name for p in task.pairs)}) of {world.name}")
    return 0


def _check_world(spec: str) -> None:
    """Fail fast, before any service or PyBullet scene starts: the world loads and, when it
    draws random pairs, a pair is possible (one-line ``WorldError`` otherwise)."""
    from curlnav.sim import get_world
    from curlnav.worlds.pairs import check_pairs_possible

    check_pairs_possible(get_world(spec))


def _cmd_worlds_rank(args: argparse.Namespace) -> int:
    import time as _time

    from curlnav.worlds.rank import rank, ranking_table, write_outputs

    worlds = [_world_from_spec(spec) for spec in args.worlds]
    t0 = _time.perf_counter()
    rows = rank(worlds)
    elapsed = _time.perf_counter() - t0
    print(ranking_table(rows))
    files = write_outputs(rows, args.out)
    print(f"measured {len(worlds)} worlds in {elapsed:.2f} s; wrote {files['csv']}, {files['json']}, {files['png']}")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from curlnav.run.launch import serve

    return serve(args)


def _cmd_pull(args: argparse.Namespace) -> int:
    from curlnav.policy import PolicyArtefact
    from curlnav.run.pull import pull_policy, unreachable_reason

    try:
        folder = pull_policy(args.source, args.out, args.version, max_bytes=args.max_bytes, max_files=args.max_files,
                             deadline_s=args.deadline_s)
    except OSError as exc:
        raise ValueError(f"cannot reach {args.source} ({unreachable_reason(exc)}): is the learner running?") from None
    policy = PolicyArtefact(folder)
    print(f"pulled policy v{policy.version} into {folder} (sha256 verified)")
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from curlnav.run.status import run_status

    return run_status(args.target, raw_json=args.json)


def _cmd_bench_transport(args: argparse.Namespace) -> int:
    from curlnav.bench.transport import run_transport_bench

    run_transport_bench(publishers=args.publishers, batches=args.batches, paths=tuple(args.paths.split(",")),
                        in_flight=args.in_flight, insert_rates=tuple(float(r) for r in args.insert_rates.split(",")),
                        per_request=args.per_request, learner_device=args.learner_device,
                        learner_variant=args.learner_variant)
    return 0


def _cmd_bench_draws(args: argparse.Namespace) -> int:
    from curlnav.bench.draws import run_draw_bench

    every = tuple(int(k) for k in args.every.split(","))
    run_draw_bench(args.distribution, steps=args.steps, episode_steps=args.episode_steps, every=every,
                   repeats=args.repeats)
    return 0


def _cmd_bench_actor(args: argparse.Namespace) -> int:
    from curlnav.bench.actor import run_actor_bench

    try:
        envs = tuple(int(k) for k in args.envs.split(","))
    except ValueError:
        raise SystemExit(f"curlnav: error: --envs takes whole numbers separated by commas, got {args.envs[:40]!r}") from None
    if not envs or min(envs) < 1 or args.steps < 1 or args.episode_steps < 1 or args.repeats < 1:
        raise SystemExit("curlnav: error: --envs, --steps, --episode-steps and --repeats must be at least 1")
    backends = tuple(args.inference.split(","))
    if not set(backends) <= {"onnx", "torch"}:
        raise SystemExit(f"curlnav: error: --inference takes onnx and/or torch, got {args.inference[:40]!r}")
    run_actor_bench(args.world, envs=envs, steps=args.steps, episode_steps=args.episode_steps, repeats=args.repeats,
                    inference=backends)
    return 0


def _cmd_bench_faults(args: argparse.Namespace) -> int:
    from curlnav.bench.faults import run_fault_bench

    rows = run_fault_bench(actors=args.actors, warm_s=args.warm_s, run_dir=args.run_dir)
    return 0 if all(r.get("lost", 0) == 0 and r.get("forward", True) and r.get("back_s") is not None
                    for r in rows) else 1


def _cmd_bench_chaos(args: argparse.Namespace) -> int:
    from curlnav.bench.chaos import run_chaos_bench

    result = run_chaos_bench(args.minutes, actors=args.actors, every_s=args.every_s, seed=args.seed,
                             run_dir=args.run_dir)  # bad input: ValueError, one line, exit 2
    return 0 if result.ok else 1


def _cmd_bench_hosts(args: argparse.Namespace) -> int:
    from curlnav.bench.hosts import run_hosts_bench
    from curlnav.bench.netns import unavailable

    why = unavailable()
    if why:
        raise SystemExit(f"curlnav: error: bench hosts needs network namespaces: {why}")
    result = run_hosts_bench(hosts=args.hosts, actors_per_host=args.actors_per_host, partition_s=args.partition_s,
                             minutes=args.minutes, run_dir=args.run_dir, netem=args.netem)
    return 0 if result["lost"] == 0 else 1


def _cmd_bench_metrics(args: argparse.Namespace) -> int:
    from curlnav.worlds.bench import run_metrics_bench

    run_metrics_bench(per_setting=args.per_setting)
    return 0


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that shows each option's default (unless it has none to show or says it itself)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.default == "" or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """An argument parser with ``_HelpFormatter``; its sub-command parsers are of this class too."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)


def package_version() -> str:
    """The installed distribution's version, else the one in the source tree's pyproject.toml."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("curlnav")
    except PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
        try:
            return tomllib.loads(pyproject.read_text())["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="curlnav", description=__doc__)
    parser.add_argument("--version", action="version", version=f"curlnav {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_training_commands(sub)
    _add_bus_commands(sub)
    _add_world_commands(sub)
    _add_bench_commands(sub)
    _add_ablation_commands(sub)
    _add_experiment_command(sub)
    from curlnav.ros2.commands import add_ros2_commands

    add_ros2_commands(sub)
    return parser


def _add_ablation_commands(sub) -> None:
    """ablation run, ablation report (curlnav.run.ablation)."""
    from curlnav.run.ablation import PAPER_CONDITIONS

    ablation = sub.add_parser("ablation", help="the curriculum ablation (the paper's Fig. 5): conditions x seeds "
                                               "at one env-step budget, serial runs, and their report")
    ablation_sub = ablation.add_subparsers(dest="ablation_command", required=True)
    p = ablation_sub.add_parser("run", help="run (or resume) every condition x seed, then write the report")
    p.add_argument("--out", default="runs/ablation", help="folder of the runs and the report")
    p.add_argument("--conditions", nargs="+", default=list(PAPER_CONDITIONS),
                   help="shipped curriculum names (scheduler/curricula/) or curriculum files")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1], help="experiment seeds per condition")
    p.add_argument("--max-env-steps", type=int, default=250_000, help="environment steps per run (equal budgets)")
    p.add_argument("--parallel", type=int, default=os.cpu_count() or 1, help="runs at once, one core each")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="config override for every new run (repeatable)")
    p.set_defaults(func=_cmd_ablation_run)
    p = ablation_sub.add_parser("report", help="ablation.png, ablation.csv and ablation.md from saved runs")
    p.add_argument("folder", help="the folder of the runs (ablation run --out)")
    p.set_defaults(func=_cmd_ablation_report)


def _add_experiment_command(sub) -> None:
    from curlnav.run.experiment import BUDGETS

    p = sub.add_parser("experiment", help="the paper's evaluation with our numbers: Table I, Fig. 4, Fig. 5 and "
                                          "Table II in report.md (resumable)")
    p.add_argument("--out", default="runs/experiment", help="folder of the runs, tables, figures and report.md")
    p.add_argument("--budget", default="small", choices=sorted(BUDGETS),
                   help="small: reduced budgets for a 2-core machine (under 2 h); full: the budgets the findings need")
    p.add_argument("--parallel", type=int, default=os.cpu_count() or 1, help="serial runs at once, one core each")
    p.add_argument("--report-only", action="store_true", help="regenerate report.md from the saved runs, no training")
    p.set_defaults(func=_cmd_experiment)


def _cmd_experiment(args: argparse.Namespace) -> int:
    from curlnav.run.experiment import BUDGETS, run_experiment, write_experiment_report

    out, budget = Path(args.out), BUDGETS[args.budget]
    if args.report_only:
        try:  # the report names the budget the runs were made with, whatever --budget says
            saved = json.loads((out / "experiment.json").read_text())["budget"]["name"]
        except (OSError, ValueError, KeyError, TypeError):
            saved = None
        if saved in BUDGETS and saved != budget.name:
            print(f"the runs in {out} were made with the {saved} budget: reporting them as such")
            budget = BUDGETS[saved]
        print(f"report: {write_experiment_report(out, budget)}")
        return 0
    run_experiment(out, budget, max(1, args.parallel))
    return 0


def _cmd_ablation_run(args: argparse.Namespace) -> int:
    from curlnav.run.ablation import plan_runs, run_all, write_report

    out = Path(args.out)
    specs = plan_runs(out, args.conditions, args.seeds, args.max_env_steps,
                      [a for o in args.overrides for a in ("--set", o)])
    failed = run_all(specs, max(1, args.parallel))
    print(f"report: {write_report(out)} (ablation.png, ablation.csv beside it)")
    return 1 if failed else 0


def _cmd_ablation_report(args: argparse.Namespace) -> int:
    from curlnav.run.ablation import write_report

    print(f"report: {write_report(Path(args.folder))} (ablation.png, ablation.csv beside it)")
    return 0


def _add_training_commands(sub) -> None:
    """train, config, eval, policy, serve, pull."""
    p = sub.add_parser("train", help="train a policy (--serial: environment and learner in one process)")
    p.add_argument("--serial", action="store_true", help="single-process trainer")
    p.add_argument("--actors", type=int, default=None, help="actor processes (distributed trainer; default 2)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads: the serial trainer's (default 2) or the learner service's (default 1)")
    p.add_argument("--run-dir", default=None, help="run folder (default runs/<date>-<time>-<world>-x<actors>; "
                   "--serial: runs/<date>-<time>-<world>)")
    p.add_argument("--resume", action="store_true", help="continue the run folder's run (its saved config)")
    p.add_argument("--init-from", default=None, metavar="RUN_OR_CHECKPOINT",
                   help="--serial: start from the networks of a serial run (or checkpoint file) instead of fresh "
                        "ones: two-stage fine-tuning, e.g. an easy world's run, then a hard world. Training "
                        "settings (d4pg.n_step, batch_size, learning rates, replay, exploration) may differ; the "
                        "network settings (encoder, widths, atoms, support) and observation layout must agree")
    from curlnav.run.options import add_config_arguments, add_train_options

    add_train_options(p)
    add_config_arguments(p)
    p.set_defaults(func=_cmd_train)

    config = sub.add_parser("config", help="the experiment config")
    config_sub = config.add_subparsers(dest="config_command", required=True)
    p = config_sub.add_parser("show", help="print the resolved config (preset, --config, CURLNAV_*, --set) and its hash")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_config_show)

    from curlnav.evaluation.commands import add_commands as add_evaluation_commands

    add_evaluation_commands(sub)

    p = sub.add_parser("serve", help="run one service (the container entry point)")
    from curlnav.run.launch import add_serve_arguments

    add_serve_arguments(p)
    p.set_defaults(func=_cmd_serve)

    p = sub.add_parser("pull", help="download a policy artefact from a learner")
    p.add_argument("--from", dest="source", required=True, help="learner URL, e.g. http://localhost:8081")
    p.add_argument("--version", default="latest", help="policy version: a number or latest")
    p.add_argument("--out", default="policy", help="artefact folder to write")
    from curlnav.run.pull import DEFAULT_DEADLINE_S, DEFAULT_MAX_BYTES, DEFAULT_MAX_FILES

    p.add_argument("--max-bytes", type=int, default=DEFAULT_MAX_BYTES,
                   help=f"refuse an artefact above this many bytes in all (default {DEFAULT_MAX_BYTES >> 20} MiB)")
    p.add_argument("--max-files", type=int, default=DEFAULT_MAX_FILES,
                   help=f"refuse a listing of more files (default {DEFAULT_MAX_FILES})")
    p.add_argument("--deadline-s", type=float, default=DEFAULT_DEADLINE_S,
                   help=f"give the whole pull up after this many seconds (default {DEFAULT_DEADLINE_S:g})")
    p.set_defaults(func=_cmd_pull)

    p = sub.add_parser("status", help="where a distributed run's curriculum, learner, replay and actors stand")
    p.add_argument("target", nargs="?", default=None,
                   help="run folder (with run.json) or the scheduler's URL (default: newest run under runs/ with a run.json)")
    p.add_argument("--json", action="store_true", help="print the scheduler's /status JSON as it is")
    p.set_defaults(func=_cmd_status)


def _add_bus_commands(sub) -> None:
    """bus credentials: the run's Zenoh users and access control (curlnav.bus.security)."""
    from curlnav.run.launch import env_default

    def credentials(args: argparse.Namespace) -> int:
        from curlnav.bus.security import acl_table, make_credentials

        tls = {}
        for item in filter(None, (i.strip() for i in args.tls.split(","))):
            name, _, address = item.partition("=")
            tls[name.strip()] = address.strip()
        done = make_credentials(args.out, args.run, actors=args.actors, shared_actor=args.shared_actor,
                                tls_hosts=tls or None)
        print(f"bus credentials of run {args.run!r} in {args.out}: "
              + ", ".join(f"{role} ({state})" for role, state in done.items()))
        print(f"give `--bus-credentials {args.out}` (CURLNAV_BUS_CREDENTIALS) to every `curlnav serve`, or to each "
              f"service only its own folder {args.out}/<role> (an actor: {args.out}/actor-<n>, which it then is; given "
              f"the folder of every actor-<n>, each actor claims a free one)")
        if tls:
            from curlnav.bus.mesh import router_flags

            print(f"TLS between routers: the run's CA {args.out}/tls/ca.pem (keep {args.out}/tls/ca.key off the hosts); "
                  f"start the main host's router with `curlnav serve router {' '.join(router_flags('NAME'))}` and "
                  f"every other host's with `curlnav serve router {' '.join(router_flags('NAME', 'MAIN_ADDRESS'))}`")
        print("access control, default deny (keys under curlnav/<run>/):\n" + acl_table())
        return 0

    bus = sub.add_parser("bus", help="the bus's security: Zenoh users and access control of a run")
    bus_sub = bus.add_subparsers(dest="bus_command", required=True)
    p = bus_sub.add_parser("credentials", help="write a run's bus credentials: one user per role with a random "
                                              "password, the router's dictionary and access control")
    p.add_argument("--out", required=True, help="folder to write (0700, files 0600); passwords already there are kept")
    p.add_argument("--run", default=env_default("run", "default"), help="the run (Zenoh key prefix) they are for")
    p.add_argument("--actors", type=int, default=env_default("max_actors", 8),
                   help="the declared maximum of actor replicas (CURLNAV_MAX_ACTORS): one user per actor, actor-0 .. "
                        "actor-<N-1>, each allowed to put only under its own id; a replica claims one at start "
                        "(more may be added later; none are removed)")
    p.add_argument("--shared-actor", action="store_true",
                   help="also one user any actor may use, under any actor id (before replicas claimed an identity "
                        "each; kept for runs that rely on it)")
    p.add_argument("--tls", default="", metavar="NAME=ADDRESS,...",
                   help="routers linked over TLS: the run's CA (tls/ca.pem) and a certificate per router name, for "
                        "the address where it listens (an IP or a DNS name)")
    p.set_defaults(func=credentials)


def _add_world_commands(sub) -> None:
    """rollout and worlds (generate, show, scatter-balls, rank)."""
    from curlnav.evaluation.commands import add_rollout_command

    add_rollout_command(sub)

    worlds = sub.add_parser("worlds", help="generate, draw and rank worlds")
    worlds_sub = worlds.add_subparsers(dest="worlds_command", required=True)
    p = worlds_sub.add_parser("generate", help="write generated worlds as world files")
    from curlnav.worlds.families import FAMILIES

    p.add_argument("family", help=", ".join(FAMILIES))
    p.add_argument("--seed", type=int, default=0, help="seed of the first world")
    p.add_argument("--count", type=int, default=1, help="worlds with seeds seed, seed+1, ...")
    p.add_argument("--param", action="append", help="generator parameter KEY=VALUE (e.g. fill_pct=0.3)")
    p.add_argument("--out", default="worlds", help="folder for the world files")
    p.set_defaults(func=_cmd_worlds_generate)
    p = worlds_sub.add_parser("show", help="draw a world with its pairs and their shortest paths")
    p.add_argument("world", help="built-in name, world YAML, or FAMILY:SEED")
    p.add_argument("--out", default=None, help="PNG path")
    p.set_defaults(func=_cmd_worlds_show)
    p = worlds_sub.add_parser("scatter-balls", help="a NAMO task from any map: balls on the shortest paths of its pairs")
    p.add_argument("world", help="built-in name, world YAML (e.g. a plain ROS SLAM map), or FAMILY:SEED")
    p.add_argument("--count", type=int, default=6, help="balls to add")
    p.add_argument("--seed", type=int, default=0, help="seed of the random pairs (plain maps) and of the places")
    p.add_argument("--pairs", type=int, default=3, help="random pairs to draw when the map has none")
    p.add_argument("--radius", type=float, default=0.25, help="ball radius (m)")
    p.add_argument("--mass", type=float, default=0.5, help="ball mass (kg)")
    p.add_argument("--out", required=True, help="world YAML to write (its image is written beside it)")
    p.set_defaults(func=_cmd_worlds_scatter_balls)
    p = worlds_sub.add_parser("rank", help="Table I and the MDS picture for a set of worlds")
    p.add_argument("worlds", nargs="+", help="built-in names, world YAMLs, or FAMILY:SEED")
    p.add_argument("--out", default="runs/ranking", help="folder for the table (CSV, JSON) and the picture")
    p.set_defaults(func=_cmd_worlds_rank)


def _add_bench_commands(sub) -> None:
    """Benchmarks that print their figures."""
    bench = sub.add_parser("bench", help="benchmarks that print their figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    p = bench_sub.add_parser("env", help="environment steps/s on one core vs a bare PyBullet loop")
    p.add_argument("--steps", type=int, default=5000, help="timed environment steps per world")
    p.add_argument("--world", action="append",
                   help="world to measure (repeat for several): built-in, YAML or FAMILY:SEED "
                        f"(default: {', '.join(DEFAULT_BENCH_WORLDS)})")
    p.add_argument("--no-pin", action="store_true", help="do not pin the process to one CPU core")
    p.set_defaults(func=_cmd_bench_env)
    p = bench_sub.add_parser("learner", help="D4PG learner updates/s per preset")
    p.add_argument("--presets", default="default,paper", help="comma-separated config presets")
    p.add_argument("--seconds", type=float, default=20.0, help="timed seconds per preset")
    p.add_argument("--batch", type=int, default=256, help="batch size")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: cuda when present)")
    p.add_argument("--variants", default="eager", help="how the update runs, comma-separated: eager, async, compile, "
                                                      "cudagraphs, bf16, bf16+compile (see curlnav.learner.bench)")
    p.add_argument("--check-amp", action="store_true", help="also train float32 and bf16 side by side and compare "
                                                           "their critic losses")
    p.add_argument("--check-steps", type=int, default=500, help="updates of the amp check")
    p.set_defaults(func=_cmd_bench_learner)
    p = bench_sub.add_parser("transport", help="replay service throughput from 4 publishers, sampling, weight latency")
    p.add_argument("--publishers", type=int, default=4, help="publishing processes")
    p.add_argument("--batches", type=int, default=400, help="batches of 64 transitions per publisher")
    p.add_argument("--paths", default="plain,shm", help="sampling paths to measure: plain (sockets), shm (Zenoh "
                                                       "shared memory), comma-separated")
    p.add_argument("--in-flight", type=int, default=4, help="sample requests the learner keeps outstanding")
    p.add_argument("--per-request", type=int, default=4, help="batches of 256 in one sample request (the learner "
                                                              "service's batches_per_request)")
    p.add_argument("--learner-device", default=None, help="also step a D4PG learner on each sampled batch, on this "
                                                         "device (cpu, cuda)")
    p.add_argument("--learner-variant", default="async", help="how that learner runs (curlnav bench learner --variants)")
    p.add_argument("--insert-rates", default="0,12500", help="insert rates to measure sampling beside, transitions/s in all, "
                                                       "comma-separated; 0: the publishers as fast as they go")
    p.set_defaults(func=_cmd_bench_transport)
    p = bench_sub.add_parser("metrics", help="difficulty metrics: 240 x 240 timing and the BARN parameter grid")
    p.add_argument("--per-setting", type=int, default=25, help="worlds per fill/smoothing setting (BARN: 25)")
    p.set_defaults(func=_cmd_bench_metrics)
    p = bench_sub.add_parser("draws", help="episode-loop steps/s drawing a new world per episode (or every K) vs one world")
    p.add_argument("distribution", nargs="?", default="barn-3x3:0-99", help="a world distribution, FAMILY:LO-HI(...)")
    p.add_argument("--steps", type=int, default=3000, help="timed environment steps per row")
    p.add_argument("--episode-steps", type=int, default=150, help="steps per episode")
    p.add_argument("--every", default="1,4", help="comma-separated episodes per fresh world, one row each")
    p.add_argument("--repeats", type=int, default=1, help="runs per row, taken in turn; the fastest is shown")
    p.set_defaults(func=_cmd_bench_draws)
    p = bench_sub.add_parser("actor", help="an actor process's steps/s with K environments on one core vs the bare "
                                           "environment (run it as: taskset -c 0 curlnav bench actor)")
    p.add_argument("--world", default="barn-3x3:0", help="world: built-in, YAML or FAMILY:SEED")
    p.add_argument("--envs", default="1,2,4,8", help="comma-separated environments per process, one row each")
    p.add_argument("--steps", type=int, default=4000, help="timed environment steps per row")
    p.add_argument("--episode-steps", type=int, default=200, help="steps per episode")
    p.add_argument("--repeats", type=int, default=1, help="runs per row; the fastest is shown")
    p.add_argument("--inference", default="onnx", help="the policy network's backend(s), comma-separated: onnx (the "
                                                       "actors' default, actor.inference), torch")
    p.set_defaults(func=_cmd_bench_actor)
    p = bench_sub.add_parser("faults", help="kill -9 replay, learner and scheduler of a local run: what was lost")
    p.add_argument("--actors", type=int, default=2)
    p.add_argument("--warm-s", type=float, default=60.0, help="s of training before the first kill")
    p.add_argument("--run-dir", default="runs/bench-faults")
    p.set_defaults(func=_cmd_bench_faults)
    p = bench_sub.add_parser("chaos", help="a long local run under chaos: kill -9 of a random service (router, replay, "
                                          "learner, scheduler, an actor) or a stall, every few tens of seconds; "
                                          "what was lost, whether versions, curriculum and policy stayed intact")
    p.add_argument("--minutes", type=float, required=True, metavar="M", help="minutes of chaos (after the run has started)")
    p.add_argument("--actors", type=int, default=2, metavar="N", help="actor processes")
    p.add_argument("--every-s", type=float, default=30.0, metavar="S",
                   help="mean seconds between faults (each gap uniform in [S/2, 3S/2])")
    p.add_argument("--seed", type=int, default=0, metavar="K", help="the fault schedule's and the run's seed")
    p.add_argument("--run-dir", default="runs/bench-chaos", metavar="DIR",
                   help="a new folder, or one this bench made (cleared)")
    p.set_defaults(func=_cmd_bench_chaos)
    p = bench_sub.add_parser("hosts", help="a run over network namespaces (a router per host, TLS between them): "
                                          "cut an actor host off, heal, train on; what was lost (root)")
    p.add_argument("--hosts", type=int, default=3, help="namespaces: host 0 runs replay, learner and scheduler")
    p.add_argument("--actors-per-host", type=int, default=2, help="actors on each of hosts 1..H-1")
    p.add_argument("--partition-s", type=float, default=20.0, help="seconds host 1 stays cut off (its link down)")
    p.add_argument("--minutes", type=float, default=None, help="the whole run (default: 30 s before and after)")
    p.add_argument("--netem", default="", help="latency and loss on the actor hosts' links, as tc netem takes "
                                               "them (e.g. 'delay 20ms loss 1%%'), where the kernel has netem")
    p.add_argument("--run-dir", default="runs/bench-hosts")
    p.set_defaults(func=_cmd_bench_hosts)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "pair", None) is not None and str(args.pair).isdigit():
        args.pair = int(args.pair)
    from curlnav.bus.service import ConfigMismatch
    from curlnav.bus.transport import RouterUnreachable
    from curlnav.policy import ArtefactError
    from curlnav.worlds.metrics import MetricsError
    from curlnav.worlds.world import WorldError

    try:
        return int(args.func(args) or 0)
    except (WorldError, KeyError, ArtefactError, MetricsError, ValueError, RouterUnreachable, ConfigMismatch) as exc:
        message = " ".join(str(exc.args[0] if exc.args else exc).split())  # one line, whatever the library said
        if len(message) > 1000:  # a user value that no loader cut short (issue 26)
            message = message[:1000] + " ..."
        print(f"curlnav: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("curlnav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
