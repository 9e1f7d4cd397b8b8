"""``curlnav train``: one experiment config, two modes (``--serial``: one process; default: the
services as local processes). Every option works in both modes or is refused with exit 2.

The run folder keeps the resolved config as ``config.yaml``. A folder that already holds a run
is continued only with ``--resume`` (with its saved config: only the budget and the stopping
target may change), and ``--resume`` on a folder with nothing to resume is refused.

The time budget (``budget.minutes``) counts every session of the run from the moment its command
started: the interpreter's start-up, loading the checkpoint and the replay and starting the services
count, so a session ends at the budget (then the orderly stop, a few seconds). A resume with less than
``MIN_RESUME_S`` of the budget left is refused (one line, exit 2): it would spend it starting and
stopping, training nothing.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from curlnav.config import (
    ConfigError,
    ExperimentConfig,
    apply_overrides,
    config_differences,
    config_hash,
    config_to_dict,
    config_to_yaml,
    load_config,
    overrides_from_environment,
    service_config_hash,
)
from curlnav.run.options import experiment_from_args, option_overrides

DEFAULT_ACTORS = 2
#: the least budget a resume must have left (s): less goes on starting the services (or loading the
#: replay) and stopping them again
MIN_RESUME_S = 60.0
RESUMABLE_CHANGES = ("budget.", "evaluation.stop_at_success")  # fields a resume may change


class TrainRefused(ValueError):
    """A train invocation that cannot run as asked (exit 2, one line)."""


def _saved_state(run_dir: Path, serial: bool) -> Path | None:
    if serial:
        candidates = [run_dir / "checkpoints" / "latest.safetensors"]
    else:
        candidates = [run_dir / "learner" / "latest.safetensors",
                      *sorted((run_dir / "replay" / "wal").glob("seg-*.log"))[:1], run_dir / "replay" / "replay.npz"]
    return next((p for p in candidates if p.exists()), None)


def resolve_train_config(args: argparse.Namespace, run_dir: Path) -> ExperimentConfig:
    """The experiment of this invocation. On ``--resume``, the saved config with this command
    line's overrides on top; only ``budget.*`` and ``evaluation.stop_at_success`` may differ."""
    saved_state = _saved_state(run_dir, args.serial)
    if not args.resume:
        if saved_state is not None:
            raise TrainRefused(f"run folder {run_dir} already holds a run ({saved_state.name}): add --resume to "
                               f"continue it, or choose another --run-dir")
        return experiment_from_args(args)
    if saved_state is None:
        raise TrainRefused(f"--resume: nothing to resume in {run_dir} (no checkpoint or replay there)")
    saved_path = run_dir / "config.yaml"
    if not saved_path.exists():
        return experiment_from_args(args)
    saved = load_config(saved_path)
    if args.preset or args.config:  # a whole config named again: it must be the saved one
        candidates = [experiment_from_args(args)]
    else:
        candidates = [apply_overrides(saved, overrides_from_environment() + option_overrides(args) + list(args.overrides))]
    experiment = candidates[0]
    changed = [d for d in config_differences(config_to_dict(experiment), config_to_dict(saved))
               if not d.startswith(RESUMABLE_CHANGES)]
    if changed:
        raise TrainRefused(f"--resume: {saved_path} was trained with another config ({'; '.join(changed[:3])}; "
                           f"command line first): only budget.* and evaluation.stop_at_success may change")
    return experiment


def check_before_start(experiment: ExperimentConfig) -> None:
    """Everything the run will load, loaded now (one line, exit 2, nothing started): the world
    (never a held-out seed), that it can draw pairs, and with a curriculum every world of every stage and every named
    sub-step pair."""
    from curlnav.sim import get_world
    from curlnav.worlds.core.heldout import check_training_world
    from curlnav.worlds.core.pairs import check_pairs_possible

    check_training_world(experiment.curriculum.world)  # a held-out FAMILY:SEED: refused before any service starts
    world = get_world(experiment.curriculum.world)
    robot = experiment.env.robot
    check_pairs_possible(world, (robot.base_length, robot.base_width))
    if experiment.curriculum.file:
        from curlnav.run.evaluator import check_evaluation_criteria
        from curlnav.scheduler.curriculum import check_curriculum, load_curriculum

        curriculum = load_curriculum(experiment.curriculum.file)
        check_curriculum(curriculum, experiment.curriculum.file)
        try:
            check_evaluation_criteria(experiment, curriculum)
        except ValueError as exc:
            raise TrainRefused(str(exc)) from None


def default_run_dir(world: str, actors: int, serial: bool) -> Path:
    """``runs/<date>-<time>-<world>-x<actors>`` (``--serial``: ``runs/<date>-<time>-<world>``)."""
    name = Path(str(world)).stem.replace(":", "-")  # t-maze:0 -> t-maze-0
    return Path(f"runs/{time.strftime('%Y%m%d-%H%M%S')}-{name}{'' if serial else f'-x{actors}'}")


def run_train(args: argparse.Namespace) -> int:
    """``curlnav train``. Exit codes: 0 the budget or the target was reached, 130 interrupted
    (SIGINT, SIGTERM, SIGHUP), 1 a service failed past its restart budget, 2 refused before
    starting (a bad config, curriculum or world, a busy run folder, a resume without budget)."""
    from curlnav.run.record import RunLock, absolute, command_started

    args.started = command_started()  # the budget counts from here (the trainers read it)
    if getattr(args, "init_from", None) and not args.serial:
        raise TrainRefused("--init-from is for the serial trainer (add --serial)")
    if args.serial and args.actors is not None:
        raise TrainRefused("--actors is for the distributed trainer; --serial runs one actor in the learner's process")
    actors = DEFAULT_ACTORS if args.actors is None else args.actors
    if actors < 1:
        raise TrainRefused(f"--actors must be at least 1, got {actors}")
    if args.run_dir is None:
        if args.resume:
            raise TrainRefused("--resume needs --run-dir: the folder of the run to continue")
        experiment = experiment_from_args(args)
        run_dir = absolute(default_run_dir(experiment.curriculum.world, actors, args.serial))
    else:
        run_dir = absolute(args.run_dir)  # printed hints work from any directory
    lock = RunLock(run_dir)
    if run_dir.exists():
        lock.acquire()  # first of all: a folder another launcher is using is not even read
    try:
        experiment = resolve_train_config(args, run_dir)
        check_before_start(experiment)
        run_dir.mkdir(parents=True, exist_ok=True)
        if not lock.held:
            lock.acquire()
        return _train_locked(args, run_dir, experiment, actors)
    finally:
        lock.release()


def check_budget_left(minutes: float, used_s: float) -> None:
    """A resume must have ``MIN_RESUME_S`` of its budget left (``TrainRefused`` otherwise)."""
    left_s = minutes * 60 - used_s
    if left_s < MIN_RESUME_S:
        enough = math.ceil((used_s + MIN_RESUME_S) / 60)
        raise TrainRefused(f"--resume: {max(left_s, 0) / 60:.1f} min of its {minutes:g} min budget left ({used_s / 60:.1f} "
                           f"used by earlier sessions), less than the {MIN_RESUME_S / 60:g} min a session needs to "
                           f"start, train and stop: raise --minutes (to {enough} or more) to train on")


def _train_locked(args, run_dir: Path, experiment: ExperimentConfig, actors: int) -> int:
    """The run, once everything is checked and the run folder is this launcher's."""
    from curlnav.run.record import RunSummary

    used_s = RunSummary(run_dir).elapsed_before_s
    if args.resume:
        check_budget_left(experiment.budget.minutes, used_s)
    (run_dir / "config.yaml").write_text(config_to_yaml(experiment))
    print(f"run folder: {run_dir}; {hash_labels(experiment)}; preset "
          f"{experiment.d4pg.preset}, world {experiment.curriculum.world}, curriculum "
          f"{experiment.curriculum.file or 'none'}, {experiment.budget.minutes:g} min"
          + (f" ({used_s / 60:.1f} used before)" if used_s else "")
          + ("" if args.serial else f", {actors} actor{'s' if actors != 1 else ''}"), flush=True)
    if args.serial:
        return _train_serial(args, run_dir, experiment)
    return _train_distributed(args, run_dir, experiment, actors)


def hash_labels(experiment: ExperimentConfig) -> str:
    """The run's two config hashes, named: the experiment config's (all of config.yaml) and the
    service-agreement hash the services log and compare (the same config without ``budget`` and
    ``evaluation``, which only the launcher reads, so a resume with a new budget still agrees)."""
    return (f"experiment config {config_hash(experiment)[:12]} (config.yaml); service-agreement hash "
            f"{service_config_hash(experiment)[:12]} (the services' logs: the same config without budget, "
            f"evaluation and actor)")


def _print_evaluations(summary: dict, run_dir: Path) -> None:
    """The run's last lines: where its policies and curves are (absolute paths, only what exists)."""
    from curlnav.run.launch import shell_command
    from curlnav.run.record import absolute, policy_lines

    run_dir = absolute(run_dir)
    reached = summary.get("first_eval_reaching_80")
    if reached:
        print(f"first evaluation at >= 80%: {reached['wall_s'] / 60:.1f} min, {reached['env_steps']} env steps")
    print(policy_lines(run_dir))
    curve = run_dir / "learning_curve.png"
    print((f"learning curve: {curve}; " if curve.exists() else "") + f"metrics.csv, eval.csv, summary.json in {run_dir}; "
          f"{shell_command('tensorboard', '--logdir', run_dir / 'tensorboard')}")


def _train_serial(args, run_dir: Path, experiment: ExperimentConfig) -> int:
    from curlnav.run.serial import SerialRunConfig, train_serial

    summary = train_serial(run_dir, experiment, SerialRunConfig(torch_threads=args.threads or 2,
                                                                init_from=getattr(args, "init_from", None) or ""),
                           resume=args.resume, started=getattr(args, "started", None))
    final = summary["final_eval"]
    print(f"stopped ({summary['stop_reason']}) after {summary['wall_s'] / 60:.1f} min, {summary['env_steps']} env steps, "
          f"{summary['updates']} updates, {summary['episodes']} episodes")
    print(f"held-out evaluation: success {final['success_rate']:.0%} over {final['episodes']} episodes, "
          f"{final['collisions_per_episode']:.2f} collisions/episode, time to goal "
          f"{final['mean_time_to_goal_s'] or float('nan'):.1f} s")
    _print_evaluations(summary, run_dir)
    return summary["exit_code"]


def _train_distributed(args, run_dir: Path, experiment: ExperimentConfig, actors: int) -> int:
    from curlnav.run.supervise import say, train_distributed

    outcome = train_distributed(run_dir, experiment, actors, learner_threads=args.threads or 1,
                                started=getattr(args, "started", None))
    summary = outcome.summary
    say(f"stopped ({outcome.stop_reason}) after {summary['sessions'][-1]['wall_s'] / 60:.1f} min "
        f"(run total {summary['elapsed_s'] / 60:.1f} min), exit code {outcome.exit_code}")
    if summary["evals"]:
        last = summary["evals"][-1]
        say(f"last evaluation: success {last['success_rate']:.0%} on {last['target']}, "
            f"{last['collisions_per_episode']:.2f} collisions/episode (policy v{last['version']}); "
            f"{len(summary['evals'])} evaluation{'s' if len(summary['evals']) != 1 else ''} in the run")
    try:
        _print_evaluations(summary, run_dir)
    except OSError:
        pass
    return outcome.exit_code


def show_config(args: argparse.Namespace) -> int:
    """``curlnav config show``: the resolved config as YAML, and its hash."""
    experiment = experiment_from_args(args)
    print(config_to_yaml(experiment), end="")
    print(f"# experiment config hash {config_hash(experiment)}")
    print(f"# service-agreement hash {service_config_hash(experiment)} (without budget, evaluation and actor: "
          f"what the services compare)")
    return 0


__all__ = ["MIN_RESUME_S", "ConfigError", "TrainRefused", "default_run_dir", "resolve_train_config", "run_train",
           "show_config"]
