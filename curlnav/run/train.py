"""``curlnav train``: one experiment config, two modes (``--serial``: one process; default: the
services as local processes). Every option works in both modes or is refused with exit 2.

The run folder keeps the resolved config as ``config.yaml``. A folder that already holds a run
is continued only with ``--resume`` (with its saved config: only the budget and the stopping
target may change), and ``--resume`` on a folder with nothing to resume is refused.

``--init-from`` (``init_from``) starts the networks from a policy artefact, a run or a checkpoint,
in either mode: its robot, observation layout and network shape are checked against the run's
before anything starts or is written (one line, exit 2), and the run records where it started
(``init_from.json``) and how that policy did before any update (``before.json``); ``summary.json``
carries both, with the newest evaluation as ``after``.

On a user's own ``map_server`` map (no pairs of its own, no curriculum) a new run draws training and
held-out pairs apart (``curlnav.worlds.real.own_map``: ``--pairs-held-out``, ``--pairs-train``,
``--balls``, ``--doors``) and writes them as ``pairs.yaml`` with the task world ``world/<map>.yaml``
that its config names; a resume reads ``pairs.yaml`` back. A map refused (no room for the robot, an
image cut short or above the cap, too few pairs) leaves nothing in the run folder.

The time budget (``budget.minutes``) counts every session of the run from the moment its command
started: the interpreter's start-up, loading the checkpoint and the replay and starting the services
count, so a session ends at the budget (then the orderly stop, a few seconds). A resume with less than
``MIN_RESUME_S`` of the budget left is refused (one line, exit 2): it would spend it starting and
stopping, training nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

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

if TYPE_CHECKING:
    from curlnav.worlds.core.world import World

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
    if experiment.helpers.stack:  # the helpers the network trains inside: a stack that can train in the loop
        from curlnav.builder import D4PGBuilder

        try:
            D4PGBuilder(experiment).training_stack()
        except ValueError as exc:
            raise TrainRefused(str(exc)) from None
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


def check_init_from(experiment: ExperimentConfig) -> str:
    """The networks' source (``init_from``): a policy artefact, run folder or checkpoint whose robot,
    observation layout and network shape are this run's (``TrainRefused``, one line, otherwise).
    Returns where the networks will come from, one line."""
    from curlnav.learner.init_from import check_starting_point, describe, find_starting_point

    try:
        point = find_starting_point(experiment.init_from)
        check_starting_point(point, experiment)
    except ValueError as exc:
        raise TrainRefused(str(exc)) from None
    return describe(point, experiment.d4pg)


def default_run_dir(world: str, actors: int, serial: bool) -> Path:
    """``runs/<date>-<time>-<world>-x<actors>`` (``--serial``: ``runs/<date>-<time>-<world>``)."""
    name = Path(str(world)).stem.replace(":", "-")  # t-maze:0 -> t-maze-0
    return Path(f"runs/{time.strftime('%Y%m%d-%H%M%S')}-{name}{'' if serial else f'-x{actors}'}")


# -- a user's own map (``curlnav.worlds.real.own_map``) -------------------------------------------
PAIRS_FILE = "pairs.yaml"  # the run's training and held-out pairs on a user's map
#: train's options for a user's map; not config fields: they make the task world that the config names
MAP_OPTIONS = {"pairs_held_out": "--pairs-held-out", "pairs_train": "--pairs-train", "balls": "--balls", "doors": "--doors"}


@dataclass(frozen=True)
class MapTask:
    """A user's map made a task: the world to write (``path``, in the run folder) and what pairs.yaml
    records it was drawn from (``about``; None: pairs.yaml is there and stays as it is)."""

    world: World
    path: Path
    about: dict | None


def _map_options(args: argparse.Namespace) -> dict[str, object]:
    """The map options the command line gave, by option name; ``TrainRefused`` for a count out of range."""
    from curlnav.worlds.real import own_map

    given = {option: getattr(args, attr) for attr, option in MAP_OPTIONS.items() if getattr(args, attr, None) is not None}
    for option, least, most in (("--pairs-held-out", 1, own_map.MAX_PAIRS), ("--pairs-train", 1, own_map.MAX_PAIRS),
                                ("--balls", 0, own_map.MAX_BALLS)):
        if option in given and not least <= given[option] <= most:
            raise TrainRefused(f"{option} must be {least}..{most}, got {given[option]}")
    return given


def keep_map_on_resume(args: argparse.Namespace, run_dir: Path) -> None:
    """On ``--resume``, ``--world MAP.yaml`` naming the map a run's pairs.yaml was drawn on means the
    run's own task world (its saved config's), not a new world."""
    from curlnav.worlds.real.own_map import read_about

    if args.resume and args.world is not None and (run_dir / PAIRS_FILE).is_file():
        recorded = read_about(run_dir / PAIRS_FILE).get("map")
        if isinstance(recorded, str) and Path(args.world).resolve() == Path(recorded).resolve():
            args.world = None


def plan_map_task(args: argparse.Namespace, run_dir: Path, experiment: ExperimentConfig) -> MapTask | None:
    """On a plain map_server map (no pairs, ``random_pairs`` or held-out pairs of its own; no
    curriculum), the task to train on: a new run draws its pairs (and places its doors and balls), a
    resume reads pairs.yaml back. None on any other world. Writes nothing; refusals are one line."""
    from curlnav.sim import get_world
    from curlnav.worlds.real import own_map

    given = _map_options(args)
    spec = experiment.curriculum.world
    pairs_file = run_dir / PAIRS_FILE
    if args.resume and pairs_file.is_file():
        world = get_world(spec)
        split = own_map.read_pairs(pairs_file, world)
        about = own_map.read_about(pairs_file)
        recorded = {"--pairs-held-out": len(split.held_out), "--pairs-train": len(split.train), "--balls": about.get("balls"),
                    "--doors": about.get("doors")}
        if "--doors" in given:
            given["--doors"] = str(Path(given["--doors"]).resolve())
        changed = [option for option, value in given.items() if value != recorded[option]]
        if changed:
            raise TrainRefused(f"--resume keeps the run's pairs, doors and balls ({pairs_file}: "
                               f"{', '.join(f'{o} {recorded[o] or 0}' for o in MAP_OPTIONS.values())}): leave out "
                               f"{', '.join(changed)}, or start a new run (another --run-dir)")
        if split == own_map.split_of(world):
            return None
        return MapTask(world.with_changes(pairs=split.train, held_out=split.held_out), Path(spec), None)
    is_file = Path(spec).suffix in (".yaml", ".yml") or Path(spec).exists()
    world = get_world(spec) if is_file and not experiment.curriculum.file and not args.resume else None
    if world is None or world.pairs or world.held_out or world.random_pairs is not None:
        if given:
            why = ("this run has a curriculum" if experiment.curriculum.file else "this run has no pairs.yaml to keep"
                   if args.resume else f"{spec} is not a map file" if world is None
                   else f"{spec} has pairs or random_pairs of its own")
            raise TrainRefused(f"{', '.join(given)}: only for a new run on a map_server map without pairs or "
                               f"random_pairs of its own; {why}")
        return None
    doors = own_map.read_doors(given["--doors"], world) if "--doors" in given else ()
    held_out = given.get("--pairs-held-out", own_map.DEFAULT_HELD_OUT)
    train = given.get("--pairs-train", own_map.DEFAULT_TRAIN)
    balls = given.get("--balls", 0)
    robot = experiment.env.robot
    task = own_map.draw_task(world.with_changes(doors=world.doors + doors), train, held_out, balls, experiment.seed,
                             (robot.base_length, robot.base_width))
    stem = re.sub(r"[^A-Za-z0-9_.-]", "-", Path(spec).stem).strip(".") or "map"
    about = {"map": str(Path(spec).resolve()), "seed": experiment.seed,
             "doors": str(Path(given["--doors"]).resolve()) if "--doors" in given else None, "balls": balls}
    return MapTask(task, run_dir.resolve() / "world" / f"{stem}.yaml", about)


def write_map_task(args: argparse.Namespace, run_dir: Path, task: MapTask, experiment: ExperimentConfig) -> ExperimentConfig:
    """Write the task world (and, for a new run, pairs.yaml) into the run folder, whole or not at
    all; the experiment naming that world, scoring each held-out pair once per evaluation, with balls
    ``own_map.PLACEMENTS_PER_PAIR`` times (each episode re-places them), unless ``--eval-episodes`` or
    ``--set evaluation.episodes`` says otherwise."""
    from curlnav.sim import save_world
    from curlnav.worlds.real import own_map

    split = own_map.split_of(task.world)
    if task.about is None:  # a resume whose pairs.yaml was edited: the world follows it
        save_world(task.world, task.path)
        print(f"pairs: {len(split.train)} training and {len(split.held_out)} held-out pairs read back from "
              f"{run_dir / PAIRS_FILE}; {task.path} follows them")
        return experiment
    made = not task.path.parent.exists()
    try:
        save_world(task.world, task.path)
        own_map.write_pairs(run_dir / PAIRS_FILE, split, task.about)
    except BaseException:
        for leftover in (task.path, task.path.with_suffix(".pgm")):
            leftover.unlink(missing_ok=True)
        if made:
            shutil.rmtree(task.path.parent, ignore_errors=True)
        raise
    print(f"pairs: {len(split.train)} training and {len(split.held_out)} held-out start/goal pairs (seed "
          f"{task.about['seed']}) in {run_dir / PAIRS_FILE}; {len(task.world.doors)} doors, {len(task.world.balls)} "
          f"balls; the task world {task.path}")
    evaluation = experiment.evaluation
    if args.eval_episodes is None and not any(o.partition("=")[0].strip() == "evaluation.episodes" for o in args.overrides):
        placements = own_map.PLACEMENTS_PER_PAIR if any(b.region is not None for b in task.world.balls) else 1
        evaluation = dataclasses.replace(evaluation, episodes=placements * len(split.held_out))
    return dataclasses.replace(experiment, curriculum=dataclasses.replace(experiment.curriculum, world=str(task.path)),
                               evaluation=evaluation)


def run_train(args: argparse.Namespace) -> int:
    """``curlnav train``. Exit codes: 0 the budget or the target was reached, 130 interrupted
    (SIGINT, SIGTERM, SIGHUP), 1 a service failed past its restart budget, 2 refused before
    starting (a bad config, curriculum or world, a busy run folder, a resume without budget)."""
    from curlnav.run.record import RunLock, absolute, command_started

    args.started = command_started()  # the budget counts from here (the trainers read it)
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
        keep_map_on_resume(args, run_dir)
        experiment = resolve_train_config(args, run_dir)
        check_before_start(experiment)
        if experiment.d4pg.anchor_weight and not experiment.init_from:
            raise TrainRefused(f"d4pg.anchor_weight ({experiment.d4pg.anchor_weight:g}) holds the actor near the policy "
                               f"the run started from: give --init-from, or set it to 0")
        if experiment.init_from and not args.resume:  # a resumed run goes on from its own checkpoint
            args.init_line = check_init_from(experiment)
        task = plan_map_task(args, run_dir, experiment)  # a user's map: its pairs drawn or read back, nothing written
        run_dir.mkdir(parents=True, exist_ok=True)
        if not lock.held:
            lock.acquire()
        if task is not None:
            experiment = write_map_task(args, run_dir, task, experiment)
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
    if getattr(args, "init_line", None) and not args.serial:  # the serial trainer says it as it loads them
        print(args.init_line, flush=True)
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
    from curlnav.run.status import start_lines

    for line in start_lines(summary):
        print(line)
    reached = summary.get("first_eval_reaching_80")
    if reached:
        print(f"first evaluation at >= 80%: {reached['wall_s'] / 60:.1f} min, {reached['env_steps']} env steps")
    print(policy_lines(run_dir))
    curve = run_dir / "learning_curve.png"
    print((f"learning curve: {curve}; " if curve.exists() else "") + f"metrics.csv, eval.csv, summary.json in {run_dir}; "
          f"{shell_command('tensorboard', '--logdir', run_dir / 'tensorboard')}")


def _train_serial(args, run_dir: Path, experiment: ExperimentConfig) -> int:
    from curlnav.run.serial import SerialRunConfig, train_serial

    summary = train_serial(run_dir, experiment, SerialRunConfig(torch_threads=args.threads or 2),
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
