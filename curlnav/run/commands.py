"""The commands that run training and the studies that train: ``train``, ``config show``,
``serve``, ``pull``, ``status``, ``ablation run|report`` and ``experiment``. Each handler imports
its work when it runs, so building the parser stays cheap (``curlnav --help``)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def _cmd_train(args: argparse.Namespace) -> int:
    from curlnav.run.train import run_train

    return run_train(args)


def _cmd_config_show(args: argparse.Namespace) -> int:
    from curlnav.run.train import show_config

    return show_config(args)


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


def add_training_commands(sub) -> None:
    """``train`` and ``config show``."""
    p = sub.add_parser("train", help="train a policy (--serial: environment and learner in one process)")
    p.add_argument("--serial", action="store_true", help="single-process trainer")
    p.add_argument("--actors", type=int, default=None, help="actor processes (distributed trainer; default 2)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads: the serial trainer's (default 2) or the learner service's (default 1)")
    p.add_argument("--run-dir", default=None, help="run folder (default runs/<date>-<time>-<world>-x<actors>; "
                   "--serial: runs/<date>-<time>-<world>)")
    p.add_argument("--resume", action="store_true", help="continue the run folder's run (its saved config)")
    p.add_argument("--init-from", default=None, metavar="ARTEFACT_RUN_OR_CHECKPOINT",
                   help="start the networks from a policy artefact folder (e.g. policies/namo-general: its actor; "
                        "the critic starts fresh and learns alone first, d4pg.critic_warmup_updates), a run folder "
                        "or a checkpoint .safetensors (actor, critic, optimiser moments), in either mode, with no "
                        "random warm-up: fine-tuning, e.g. to your building. Its robot, observation layout (beams, "
                        "field of view, range, frames) and network settings must be the run's (checked before "
                        "anything starts: one line, exit 2); training settings may differ. The run records the "
                        "source's sha256 and its held-out success before any update (summary.json: init_from, "
                        "before, after). init_from; CURLNAV_INIT_FROM")
    from curlnav.run.options import add_config_arguments, add_train_options

    add_train_options(p)
    add_config_arguments(p)
    # a user's map_server map without pairs (curlnav.worlds.real.own_map): the run's pairs.yaml and task world
    p.add_argument("--pairs-held-out", type=int, default=None, metavar="N",
                   help="on a map without pairs of its own: held-out pairs the evaluation scores, drawn apart from "
                        "the training pairs (default 20; the run folder's pairs.yaml)")
    p.add_argument("--pairs-train", type=int, default=None, metavar="N",
                   help="on a map without pairs of its own: training pairs (default 100)")
    p.add_argument("--balls", type=int, default=None, metavar="N",
                   help="on a map without pairs of its own: balls on the training pairs' shortest paths (default 0)")
    p.add_argument("--doors", default=None, metavar="FILE.yaml",
                   help="on a map without pairs of its own: its doors, `doors: [{hinge: [x, y], width: W, angle: A}]` "
                        "(m, rad; docs/guide/training.md)")
    p.set_defaults(func=_cmd_train)

    config = sub.add_parser("config", help="the experiment config")
    config_sub = config.add_subparsers(dest="config_command", required=True)
    p = config_sub.add_parser("show", help="print the resolved config (preset, --config, CURLNAV_*, --set) and its hash")
    add_config_arguments(p)
    p.set_defaults(func=_cmd_config_show)


def add_service_commands(sub) -> None:
    """``serve`` (one service), ``pull`` (a policy from a learner), ``status`` (a distributed run)."""
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


def add_ablation_commands(sub) -> None:
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


def add_experiment_command(sub) -> None:
    """``experiment``: the paper's evaluation (``curlnav.run.experiment``)."""
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
