"""Evaluation beside a distributed run, in its own process (``python -m curlnav.run.evaluator``,
started and supervised by ``curlnav train``).

Every ``evaluation.every_s`` it takes the learner's newest policy artefact over HTTP (a version
it has not evaluated yet), asks the scheduler where the curriculum stands and evaluates
(``evaluation_plan``, the same plan as the serial trainer's):

- without a curriculum: the held-out pairs of the training world (``EvaluationProtocol``);
- with a curriculum: each world of the current stage (in a stage with sub-steps, each sub-step's
  pair; in a stage without, held-out random pairs of each world), then the curriculum's fixed
  ``evaluate`` targets (default: the last stage's worlds and pairs), ``max(5, evaluation.episodes
  // targets)`` episodes each, reported per target.

It appends one row per (world, pair) to ``eval.csv`` (the launcher reads them for the console,
TensorBoard and the stopping target) and keeps ``policy-best/``: the artefact with the best
evaluation so far, ordered by (success on the headline target, the last fixed target such as
T-Maze p4; then mean success over the targets).

A run started from a policy (``init_from``) has that policy evaluated first, as it came, before
any update (``evaluate_before``, the serial trainer's too): ``before.json``, not an eval.csv row.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import shutil
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from curlnav.config import ExperimentConfig, load_config
from curlnav.evaluation.protocol import EvaluationProtocol, evaluate
from curlnav.run.launch import die_with_launcher, http_json_or_none
from curlnav.run.record import BEFORE_FILE, EVAL_FIELDS, CsvLog, copy_policy, last_evaluation_number, write_json

log = logging.getLogger("curlnav.run.evaluator")
HELD_OUT = "held-out"


class EvaluationStopped(Exception):
    """The run is stopping: an evaluation in progress is dropped, not recorded."""


@dataclass(frozen=True)
class Target:
    """One thing to evaluate: a world and a named pair, or ``held-out`` random pairs."""

    stage_index: int
    stage: str
    substep: int
    world: str
    pair: str


def targets_for(experiment: ExperimentConfig, curriculum, status: dict | None) -> list[Target]:
    """What to evaluate now: the training world's held-out pairs, or the current stage's worlds
    and sub-step pairs (``status``: the scheduler's ``/status``)."""
    if curriculum is None:
        return [Target(0, "train", 0, experiment.curriculum.world, HELD_OUT)]
    index = int((status or {}).get("stage_index") or 0)
    index = min(max(index, 0), len(curriculum.stages) - 1)
    stage = curriculum.stages[index]
    substep = int((status or {}).get("substep") or 0)
    out = []
    for world in stage.worlds:
        for pair in (stage.substeps or (HELD_OUT,)):
            out.append(Target(index, stage.name, substep, world, pair))
    return out


def evaluation_plan(experiment: ExperimentConfig, curriculum, status: dict | None) -> list[Target]:
    """Every evaluation's targets: the current stage's (``targets_for``), then the curriculum's
    fixed ``evaluate`` targets, the last of which is the run's headline (``policy-best`` and
    ``stop_at_success`` follow it). A current target that is also fixed is evaluated once, as fixed."""
    current = targets_for(experiment, curriculum, status)
    if curriculum is None:
        return current
    fixed = [(world, pair or HELD_OUT) for world, pair in curriculum.evaluation_targets()]
    head = current[0]
    return ([t for t in current if (t.world, t.pair) not in fixed]
            + [Target(head.stage_index, head.stage, head.substep, world, pair) for world, pair in fixed])


def episodes_per_target(experiment: ExperimentConfig, targets: int) -> int:
    """Episodes each target of an evaluation gets: all ``evaluation.episodes`` for a single
    target, else ``max(5, evaluation.episodes // targets)``."""
    episodes = experiment.evaluation.episodes
    return episodes if targets == 1 else max(5, episodes // max(targets, 1))


def check_evaluation_criteria(experiment: ExperimentConfig, curriculum) -> None:
    """A criterion ``source: evaluation`` that no evaluation can meet is refused before the run:
    its step's held-out rows must hold at least ``window`` episodes. Raises ``ValueError``
    naming the stage and what to raise."""
    for index, stage in enumerate(curriculum.stages):
        for criterion, step in ((stage.advance, "advance"), (stage.substep_advance, "substep_advance")):
            if criterion is None or criterion.source != "evaluation":
                continue
            targets = evaluation_plan(experiment, curriculum, {"stage_index": index, "substep": 0})
            per_target = episodes_per_target(experiment, len(targets))
            rows = [{"episodes": per_target, "success_rate": 0.0}] * len(targets)
            episodes = (current_step_rate(curriculum, targets, rows) or (0.0, 0))[1]
            if episodes < criterion.window:
                raise ValueError(
                    f"curriculum {curriculum.name}: stage {stage.name}'s {step} (source: evaluation, window "
                    f"{criterion.window}) can never fire: each evaluation gives its step {episodes} episodes "
                    f"(evaluation.episodes={experiment.evaluation.episodes} over {len(targets)} targets); raise "
                    f"evaluation.episodes to at least {criterion.window * len(targets)} or lower the window")


def headline_key(curriculum) -> tuple[str, str] | None:
    """(world name, pair) of a curriculum's headline target as eval.csv rows name it, or None."""
    if curriculum is None:
        return None
    world, pair = curriculum.evaluation_targets()[-1]
    return world_label(world), pair or HELD_OUT


def world_label(world: str) -> str:
    """A world as eval.csv names it: a world file's stem; a built-in, ``FAMILY:SEED`` or a
    distribution's key as it is (a key's dots are not a file suffix)."""
    return Path(world).stem if world.endswith((".yaml", ".yml")) else world


#: how ``policy-best`` ranks evaluations, as ``selected.json`` says it
RANKING = ("success on the headline target (within one episode of it counts as equal), then fewer base "
           "collisions per episode there, then mean success over the targets")


def best_rank(curriculum, rows: list[dict]) -> tuple[float, float, float, int]:
    """How ``policy-best`` orders evaluations (serial and distributed; compare two with
    ``rank_beats``): (success on the headline target, minus its base collisions per episode,
    mean success over the rows, the headline's episodes). An evaluation without the headline
    target ranks below every one with it; without a curriculum the single row is the headline."""
    mean = sum(float(r["success_rate"]) for r in rows) / len(rows)
    headline = headline_key(curriculum)
    head = rows[-1:] if headline is None else [r for r in rows if (r["world"], r["pair"]) == headline]
    if not head:
        return (-1.0, -math.inf, mean, 0)
    collisions = head[0].get("collisions_per_episode")
    return (float(head[0]["success_rate"]), -float(collisions) if collisions is not None else -math.inf, mean,
            int(head[0].get("episodes") or 0))


def rank_beats(new, old) -> bool:
    """Whether an evaluation ranked ``new`` (``best_rank``) is better than one ranked ``old``:
    more headline success, where a difference of at most one episode (a coin's throw over the
    evaluation's episodes) counts as equal and fewer collisions decide; then mean success.
    ``old`` may be a rank saved by an older curlnav, (headline success, mean success)."""
    if old is None:
        return True
    old = tuple(-math.inf if v is None else v for v in old)  # JSON keeps no infinity
    if len(old) == 2:  # no collisions recorded: any measured count beats it at equal success
        old = (old[0], -math.inf, old[1], 0)
    episodes = max(int(new[3] or 0), int(old[3] or 0))
    tolerance = 1.0 / episodes + 1e-9 if episodes else 1e-9
    if abs(new[0] - old[0]) > tolerance:
        return new[0] > old[0]
    return (new[1], new[2], new[0]) > (old[1], old[2], old[0])


class BesideEvaluator:
    """The evaluation loop's parts: ``evaluate(policy, targets)`` -> eval.csv rows."""

    def __init__(self, run_dir: Path, experiment: ExperimentConfig, curriculum=None) -> None:
        self.run_dir = run_dir
        self.experiment = experiment
        self.curriculum = curriculum
        self._held_out: dict[str, EvaluationProtocol] = {}
        self._named_envs: dict[str, object] = {}
        self.evaluations = last_evaluation_number(run_dir / "eval.csv")
        self.best = self._saved_best()

    def _saved_best(self) -> tuple | None:
        note = self.run_dir / "policy-best" / "selected.json"
        try:
            saved = json.loads(note.read_text())
            return tuple(saved["rank"])
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def evaluate(self, policy, targets: list[Target], stop: threading.Event | None = None) -> list[dict]:
        """One row per target; raises ``EvaluationStopped`` as soon as ``stop`` is set. A policy
        whose network reads a memory builds it from the odometry (``curlnav.memory``)."""
        from curlnav.memory import remembering
        from curlnav.sim import NamoEnv, get_world

        policy = remembering(policy, self.experiment.env.lidar_fov)

        def check_stop(_episode: int, _info: dict) -> None:
            if stop is not None and stop.is_set():
                raise EvaluationStopped()

        per_target = episodes_per_target(self.experiment, len(targets))
        rows = []
        for t in targets:
            if t.pair == HELD_OUT:
                protocol = self._held_out.get(t.world)
                if protocol is None:
                    protocol = self._held_out[t.world] = EvaluationProtocol(self.experiment, world=t.world,
                                                                            episodes=per_target)
                result = protocol.run(policy, on_episode=check_stop)
            else:
                world = get_world(t.world)
                pair = next(p for p in world.pairs if p.name == t.pair)
                env = self._named_envs.get(t.world)
                if env is None:
                    env = self._named_envs[t.world] = NamoEnv(world, self.experiment.eval_env)
                result = evaluate(policy, world, [pair] * per_target, self.experiment.eval_env, env=env,
                                  on_episode=check_stop)
            rows.append({"stage_index": t.stage_index, "stage": t.stage, "substep": t.substep,
                         "world": world_label(t.world), "pair": t.pair, **dataclasses.asdict(result)})
        return rows

    def record(self, rows: list[dict], *, wall_s: float, version: int, env_steps: int, updates: int,
               artefact: Path) -> dict:
        """Append ``rows`` as evaluation N+1 to eval.csv; keep policy-best. Returns the overall row."""
        self.evaluations += 1
        log_file = CsvLog(self.run_dir / "eval.csv", EVAL_FIELDS)
        try:
            for row in rows:
                log_file.write({"evaluation": self.evaluations, "wall_s": wall_s, "env_steps": env_steps,
                                "updates": updates, "policy_version": version, "rows": len(rows), **row})
        finally:
            log_file.close()
        success = sum(r["success_rate"] for r in rows) / len(rows)
        headline = headline_key(self.curriculum)
        rank = best_rank(self.curriculum, rows)
        if rank_beats(rank, self.best):
            self.best = rank
            copy_policy(artefact, self.run_dir / "policy-best",
                        {"why": f"best evaluation so far (headline target {'/'.join(headline) if headline else 'held-out'})",
                         "ranked_by": RANKING, "rank": list(rank), "evaluation": self.evaluations, "policy_version": version,
                         "success_rate": success, "wall_s": wall_s, "env_steps": env_steps,
                         "rows": [{k: r[k] for k in ("world", "pair", "success_rate", "collisions_per_episode")} for r in rows]})
        return {"evaluation": self.evaluations, "success_rate": success, "version": version}

    def close(self) -> None:
        for protocol in self._held_out.values():
            protocol.close()
        for env in self._named_envs.values():
            env.close()


def evaluate_before(run_dir: Path, experiment: ExperimentConfig, curriculum=None,
                    evaluator: BesideEvaluator | None = None, stop: threading.Event | None = None) -> dict | None:
    """The run's starting policy (``init_from``: an artefact as it came, or a checkpoint's actor),
    evaluated before any update on the first evaluation's targets (``evaluation_plan`` at the first
    stage), by the protocol of every evaluation of the run. Written once to ``before.json`` (a
    resumed run keeps it) and returned: the headline target's success and base collisions per
    episode, each target's success. None for a run of fresh networks. Raises ``EvaluationStopped``
    when ``stop`` is set during it (nothing written)."""
    path = run_dir / BEFORE_FILE
    if not experiment.init_from:
        return None
    if path.exists():
        return json.loads(path.read_text())
    from curlnav.learner.artefact import load_policy
    from curlnav.learner.init_from import find_starting_point

    point = find_starting_point(experiment.init_from)
    policy = load_policy(point.path)
    own = evaluator is None
    evaluator = evaluator or BesideEvaluator(run_dir, experiment, curriculum)
    started = time.monotonic()
    try:
        rows = evaluator.evaluate(policy, evaluation_plan(experiment, curriculum, None), stop)
    finally:
        if own:
            evaluator.close()
    head = rows[-1]
    record = {"policy": str(point.path), "kind": point.kind, "target": f"{head['world']}/{head['pair']}",
              "episodes": head["episodes"], "success_rate": head["success_rate"],
              "collisions_per_episode": head["collisions_per_episode"],
              "mean_success_rate": sum(r["success_rate"] for r in rows) / len(rows),
              "per_pair": {f"{r['world']}/{r['pair']}": r["success_rate"] for r in rows},
              "evaluation_s": time.monotonic() - started}
    write_json(path, record)
    return record


def before_line(record: dict) -> str:
    """``before.json`` for a person, one line."""
    if "error" in record:
        return f"[before] {record.get('policy')}: not evaluated ({record['error']})"
    return (f"[before] {record['policy']} as it came: success {record['success_rate']:.0%} over {record['episodes']} "
            f"episodes on {record['target']}, {record['collisions_per_episode']:.2f} base collisions/episode")


def current_step_rate(curriculum, targets: list[Target], rows: list[dict]) -> tuple[float, int] | None:
    """(success rate, episodes) over the rows of the curriculum's current step, or None."""
    from curlnav.scheduler.curriculum import CurriculumState

    state = CurriculumState(curriculum, stage=targets[0].stage_index, substep=targets[0].substep) if targets else None
    mine = [r for t, r in zip(targets, rows) if state.is_current(t.world, "" if t.pair == HELD_OUT else t.pair)]
    episodes = sum(int(r["episodes"]) for r in mine)
    return (sum(r["success_rate"] * int(r["episodes"]) for r in mine) / episodes, episodes) if episodes else None


def send_evaluation(status_url: str, token: str, epoch: int, rate: float, episodes: int) -> dict | None:
    """POST a held-out evaluation of the current step to the scheduler (``/admin/evaluation``)."""
    import json as _json
    import urllib.request

    url = status_url.rsplit("/status", 1)[0] + "/admin/evaluation"
    body = _json.dumps({"epoch": epoch, "success_rate": rate, "episodes": episodes}).encode()
    request = urllib.request.Request(url, data=body, method="POST", headers={
        "Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=5.0) as reply:
            return _json.loads(reply.read())
    except (OSError, ValueError) as exc:
        log.warning("could not send the evaluation to the scheduler: %s", exc)
        return None


def run_beside(run_dir: Path, experiment: ExperimentConfig, learner_url: str, status_url: str,
               run_started_unix: float, stop: threading.Event, admin_token: str = "") -> None:
    """The loop: wait ``every_s``, evaluate the newest unevaluated policy, record, repeat; with
    an admin token, send each evaluation of the current step to the scheduler."""
    from curlnav.policy import PolicyArtefact
    from curlnav.run.pull import pull_policy

    curriculum = None
    if experiment.curriculum.file:
        from curlnav.scheduler.curriculum import load_curriculum

        curriculum = load_curriculum(experiment.curriculum.file)
    evaluator = BesideEvaluator(run_dir, experiment, curriculum)
    every_s = experiment.evaluation.every_s
    last_version = -1
    work = run_dir / ".evaluator"
    try:
        if experiment.init_from and not (run_dir / BEFORE_FILE).exists():
            try:
                log.info(before_line(evaluate_before(run_dir, experiment, curriculum, evaluator, stop)))
            except EvaluationStopped:
                log.info("stopping: the evaluation of the starting policy in progress is dropped")
                return
            except (OSError, ValueError) as exc:  # recorded, so that the launcher does not wait for it
                log.warning("could not evaluate the starting policy %s: %s", experiment.init_from, exc)
                write_json(run_dir / BEFORE_FILE, {"policy": experiment.init_from, "error": str(exc)})
        next_at = time.monotonic() + every_s
        while not stop.wait(max(0.0, next_at - time.monotonic())):
            listing = http_json_or_none(f"{learner_url}/policy/latest", timeout=5.0)
            version = int(listing["version"]) if listing and "version" in listing else -1
            if version <= last_version or version < 1:
                next_at = time.monotonic() + 2.0  # nothing new yet: look again soon
                continue
            try:
                folder = pull_policy(learner_url, work / "policy")
                policy = PolicyArtefact(folder)
            except (OSError, ValueError) as exc:
                log.warning("could not fetch policy v%d: %s", version, exc)
                next_at = time.monotonic() + 2.0
                continue
            started = time.monotonic()
            try:
                status = http_json_or_none(status_url, timeout=5.0)
                targets = evaluation_plan(experiment, curriculum, status)
                rows = evaluator.evaluate(policy, targets, stop)
            except EvaluationStopped:
                log.info("stopping: the evaluation of policy v%d in progress is dropped", policy.version)
                break
            training = policy.metadata.get("training", {})
            overall = evaluator.record(rows, wall_s=time.time() - run_started_unix, version=policy.version,
                                       env_steps=int(training.get("env_steps", 0)),
                                       updates=int(training.get("learner_steps", 0)), artefact=folder)
            log.info("evaluation %d of policy v%d: success %.0f%% (%.0f s)", overall["evaluation"], policy.version,
                     100 * overall["success_rate"], time.monotonic() - started)
            step = current_step_rate(curriculum, targets, rows) if curriculum is not None and status else None
            if admin_token and step is not None and "epoch" in status:
                reply = send_evaluation(status_url, admin_token, int(status["epoch"]), *step)
                if reply and reply.get("advanced"):
                    log.info("the curriculum advanced on this evaluation: now %s sub-step %s", reply["stage"],
                             reply["substep"])
            last_version = version
            next_at = started + every_s
    finally:
        evaluator.close()
        shutil.rmtree(work, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    from curlnav.bus.transport import stop_on_signals

    p = argparse.ArgumentParser(prog="python -m curlnav.run.evaluator", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-dir", required=True, help="the run folder (eval.csv, policy-best/)")
    p.add_argument("--config", required=True, help="the run's config.yaml")
    p.add_argument("--learner-url", required=True, help="learner HTTP base URL (policy artefacts)")
    p.add_argument("--status-url", required=True, help="the scheduler's /status URL")
    p.add_argument("--admin-token-file", default="",
                   help="file holding the scheduler's admin token: held-out evaluations are sent to it "
                        "(curricula with criteria of source: evaluation)")
    p.add_argument("--run-started-unix", type=float, required=True,
                   help="unix time at which the run's wall clock reads 0 (earlier sessions included)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s evaluator %(levelname)s %(message)s")
    stop = threading.Event()
    stop_on_signals(stop)
    die_with_launcher()
    token = Path(args.admin_token_file).read_text().strip() if args.admin_token_file else ""
    run_beside(Path(args.run_dir), load_config(args.config), args.learner_url.rstrip("/"), args.status_url,
               args.run_started_unix, stop, admin_token=token)
    return 0


if __name__ == "__main__":
    sys.exit(main())
