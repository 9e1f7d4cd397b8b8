"""``curlnav train --serial``: the episode loop and the learner in one process.

The same parts as the distributed service, made by the same ``D4PGBuilder`` from the same
``ExperimentConfig``: ``EpisodeLoop`` (environment, behaviour policy of actor 0, n-step writer),
``ReplayTable`` with its rate limiter, ``sgd_step``, ``EvaluationProtocol``. They are driven in
turn: step the environment while the limiter accepts inserts, update while it allows samples.
Neither ever waits on the other, so it cannot deadlock.

A run folder holds ``config.yaml`` (the experiment), ``metrics.csv`` (training), ``eval.csv``
(held-out evaluations), TensorBoard event files in ``tensorboard/``, ``learning_curve.png``,
``summary.json`` (one entry per session), ``checkpoints/`` (learner + replay, resumable),
``policy/`` (the latest exported artefact) and ``policy-best/`` (the best held-out evaluation).
SIGINT, SIGTERM and SIGHUP stop it with a checkpoint (exit code 130 from ``curlnav train``).
The time budget counts from the start of the command (loading the checkpoint and the replay
count); the final evaluation and checkpoint follow it.

With a curriculum file (``--curriculum``), the scheduler's own core (``CurriculumState``) runs
in-process: every episode takes its (world, pair) from it and reports its outcome to it, exactly
as the actors and the scheduler service do over the bus. Evaluations then cover the current
stage and the curriculum's fixed ``evaluate`` targets (e.g. T-Maze p1..p4), one eval.csv row
each; ``policy-best/`` keeps the policy best on the last fixed target. This is the cheap
instrument for ablations: one core per condition.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from curlnav.actor.loop import EpisodeEnd, EpisodeLoop
from curlnav.builder import D4PGBuilder
from curlnav.bus.transport import STOP_SIGNALS, ignore_stop_signals, on_stop_signals, restore_signals
from curlnav.config import ExperimentConfig
from curlnav.evaluation.protocol import EvalResult, EvaluationProtocol
from curlnav.learner.artefact import export_policy, training_worlds
from curlnav.learner.d4pg import act, check_resumed_layout, load_checkpoint, save_checkpoint, sgd_step
from curlnav.learner.feed import BatchAssembler
from curlnav.learner.init_from import inherited_stack
from curlnav.nav.roles import NETWORK, ControlSteps
from curlnav.run.record import (
    EVAL_FIELDS,
    TRAIN_FIELDS,
    CsvLog,
    RunSummary,
    TensorBoardLog,
    absolute,
    control_text,
    last_evaluation_number,
    now_iso,
    outcome_fields,
    record_init_from,
    strict_json,
)
from curlnav.sim.robots import sensor_metadata


@dataclass(frozen=True)
class SerialRunConfig:
    """How the serial trainer runs (nothing here changes what it learns)."""

    checkpoint_every_s: float = 300.0  # s between checkpoints (learner, replay, policy)
    save_replay: bool = True  # include the replay in checkpoints (needed for an exact resume)
    torch_threads: int = 2
    progress: bool = True  # a tqdm progress bar


class SerialTrainer:
    """One serial run in ``run_dir``. ``run()`` trains to the budget and returns a summary."""

    def __init__(self, run_dir: str | Path, experiment: ExperimentConfig, run: SerialRunConfig | None = None,
                 resume: bool = False, started: float | None = None) -> None:
        # the session's clock (time.monotonic()) starts with its command: loading counts against the budget
        self.started = time.monotonic() if started is None else started
        self.run_dir = absolute(run_dir)
        self.experiment = experiment
        self.run_cfg = run or SerialRunConfig()
        torch.set_num_threads(self.run_cfg.torch_threads)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        self.builder = builder = D4PGBuilder(experiment)
        self.evaluation = EvaluationProtocol(experiment)
        self.counters = {"env_steps": 0, "episodes": 0, "elapsed_s": 0.0, "evals": []}
        # a resumed run's evaluations go on after the last in eval.csv, see _next_evaluation_number
        self._last_evaluation_number = last_evaluation_number(self.run_dir / "eval.csv")
        ckpt, replay_path = self.ckpt_dir / "latest.safetensors", self.ckpt_dir / "replay.npz"
        if resume and ckpt.exists():
            self.state, extra = load_checkpoint(ckpt)
            check_resumed_layout(self.state, builder.layout, ckpt, "run folder")
            self.counters.update(extra.get("counters", {}))
            self.table = builder.restore_replay_table(replay_path) if replay_path.exists() else builder.make_replay_table()
            print(f"resumed from {ckpt}: {self.state.steps} updates, {self.counters['env_steps']} env steps, "
                  f"replay {self.table.size} transitions")
        else:
            self.state = self._initial_state(builder)
            self.table = builder.make_replay_table()
        self.assembler = BatchAssembler(self.state.device)
        self.curriculum = self._load_curriculum()
        # what artefacts name as their training (worlds, curriculum): fixed for the run, read once
        self.artefact_training = training_worlds(str(experiment.curriculum.world), experiment.curriculum.file)
        # a fine-tuned policy ships behind the stack of the policy it started from
        self.artefact_stack = inherited_stack(experiment.init_from)
        excluded = set(self.evaluation.excluded) if self.curriculum is None else self._curriculum_excluded()
        env = builder.make_env(excluded_pairs=excluded)  # held out, as in every actor
        self.policy = builder.make_behaviour_policy(actor_index=0, actor_count=1, stream=self.counters["env_steps"])
        self.policy.use_network(self.state.actor)
        self.policy.steps = self.counters["env_steps"]  # the warm-up is not repeated on resume
        if self.counters.get("init_from"):  # a run saved before init_from was a config field
            self.policy.steps = max(self.policy.steps, self.policy.warmup_steps)  # a trained policy acts at once
        self.loop = EpisodeLoop(env, builder.make_acting_agent(self.policy), builder.make_nstep_writer(),
                                builder.make_world_draws(0, stream=self.counters["env_steps"]),
                                helpers=builder.make_training_helpers(0, 1, stream=self.counters["env_steps"]),
                                memory=builder.make_memory())
        self.loop.steps = self.counters["env_steps"]  # the helpers' fade goes on from where the run is
        self.recent: deque[tuple[bool, float, int]] = deque(maxlen=100)  # success, return, base collisions
        self.recent_control: deque[dict[str, int]] = deque(maxlen=100)  # control steps by chooser, per episode
        self.metrics: dict[str, float] = {}
        self.task: tuple[str, str, int] = (str(experiment.curriculum.world), "", 0)  # world, pair, epoch

    def _initial_state(self, builder: D4PGBuilder):
        """Fresh networks, or those of ``init_from`` (``D4PGBuilder.make_learner_state``: a policy
        artefact's actor, or a run's or checkpoint's networks with their optimiser moments, for
        fine-tuning); the update count starts at 0. Where it started is recorded in the run folder."""
        state = builder.make_learner_state(say=print)
        if self.experiment.init_from:
            self.counters["init_from"] = record_init_from(self.run_dir, self.experiment.init_from)["path"]
        return state

    # -- the curriculum (in-process scheduler core) ------------------------------------------
    def _load_curriculum(self):
        if not self.experiment.curriculum.file:
            return None
        from curlnav.scheduler.curriculum import CurriculumState, load_curriculum

        seed = self.experiment.seed
        state = CurriculumState(load_curriculum(self.experiment.curriculum.file), seed=seed)
        saved = self.counters.get("curriculum")
        if saved:
            state = CurriculumState.from_dict(state.curriculum, saved, seed=seed)
        return state

    def _curriculum_excluded(self) -> set:
        """The held-out pairs of every curriculum world that draws random pairs."""
        from curlnav.evaluation.protocol import excluded_keys, held_out_pairs
        from curlnav.sim import get_world
        from curlnav.worlds.core.pairs import draws_random_pairs

        worlds = {w for s in self.curriculum.curriculum.stages for w in s.worlds}
        worlds |= {w for w, _ in self.curriculum.curriculum.evaluate}
        keys: set = set()
        for world in sorted(worlds):
            if draws_random_pairs(get_world(world)):
                keys |= excluded_keys(held_out_pairs(world, self.experiment.evaluation.episodes))
        return keys

    def _eval_targets(self):
        """The current stage's targets, then the fixed ``evaluate`` targets (the last one is the
        run's headline: policy-best and ``stop_at_success`` follow it)."""
        from curlnav.run.evaluator import evaluation_plan

        state = self.curriculum
        return evaluation_plan(self.experiment, state.curriculum, {"stage_index": state.stage, "substep": state.substep})

    def _stage_fields(self) -> dict:
        if self.curriculum is None:
            return {"stage_index": 0, "stage": "train", "substep": 0}
        state = self.curriculum
        return {"stage_index": state.stage, "stage": state.current.name, "substep": state.substep}

    # -- the parts of one iteration -------------------------------------------------------------
    def act_once(self) -> EpisodeEnd | None:
        """One environment step, its transitions into the table; a new episode after an end."""
        end = self.loop.step()
        self.table.insert(self.loop.flush(), timeout=0)
        self.counters["env_steps"] += 1
        if end is not None:
            self.counters["episodes"] += 1
            self.recent.append((end.success, end.episode_return, int(end.info["base_collisions"])))
            self.recent_control.append(end.control_steps)
            if self.curriculum is not None:
                world, pair, epoch = self.task
                if self.curriculum.record(world, pair, end.success, epoch, int(end.info["steps"])):
                    self._note_advance()
            self._begin()
        return end

    def learn_once(self) -> None:
        """One update from a sampled batch (importance-weighted and re-prioritised when the
        replay is prioritized)."""
        batch_size = self.experiment.d4pg.batch_size
        # frames gathered from the table, stacked into float32 by torch (numpy's float16
        # conversion took most of an update's sampling time)
        sample = self.table.sample_frames(batch_size, timeout=0)
        weights = self.builder.importance_weights(sample["probabilities"], self.table.size)
        self.state, self.metrics, item_loss = sgd_step(self.state, self.assembler(sample, weights))
        if self.experiment.replay.prioritized:
            self.table.update_priorities(sample["keys"], item_loss + 1e-6)

    def _next_evaluation_number(self) -> int:
        """The next evaluation's number in eval.csv. A resumed run continues after the highest
        number already there: evaluations made after its last checkpoint stay in eval.csv (they
        measured a policy that existed) and must not share a number with the ones that follow."""
        self._last_evaluation_number = max(self._last_evaluation_number, len(self.counters["evals"])) + 1
        return self._last_evaluation_number

    def _greedy_policy(self):
        """The actor without exploration noise, as evaluation runs it; a network that reads a
        memory builds it from each step's odometry (``curlnav.memory``)."""
        policy = lambda o: act(self.state.actor, o)  # noqa: E731
        if not self.state.layout.memory_beams:
            return policy
        from curlnav.memory import RememberingPolicy

        return RememberingPolicy(policy, self.state.layout, self.experiment.env.lidar_fov)

    def evaluate(self, start: float) -> EvalResult:
        if self.curriculum is not None:
            return self._evaluate_curriculum(start)
        self.state.actor.eval()
        result = self.evaluation.run(self._greedy_policy())
        self.state.actor.train()
        row = {"evaluation": self._next_evaluation_number(), "wall_s": time.monotonic() - start,
               "env_steps": self.counters["env_steps"], "updates": self.state.steps,
               "policy_version": self.state.steps, "stage_index": 0, "stage": "train", "substep": 0,
               "world": Path(str(self.experiment.curriculum.world)).stem, "pair": "held-out", "rows": 1,
               **dataclasses.asdict(result)}
        self.eval_log.write(row)
        self.counters["evals"].append(strict_json(row))
        self.board.scalars({"eval/success_rate": result.success_rate,
                            f"eval/success/{row['world']}/held-out": result.success_rate,
                            f"eval/base_collisions_per_episode/{row['world']}/held-out": result.collisions_per_episode},
                           self.counters["env_steps"])
        from curlnav.run.evaluator import RANKING, best_rank, rank_beats

        rank = list(best_rank(None, [row]))
        earlier = self.counters.get("best_success")  # a checkpoint of an older curlnav ranked success only
        if rank_beats(rank, self.counters.get("best_rank") or (None if earlier is None else [earlier, earlier])):
            self.counters["best_rank"] = rank
            folder = export_policy(self.state, self.run_dir / "policy-best", self.experiment.env,
                                   worlds=[str(self.experiment.curriculum.world)], env_steps=self.counters["env_steps"],
                                   stack=self.artefact_stack)
            (folder / "selected.json").write_text(json.dumps(strict_json(
                {"why": "best held-out evaluation so far", "ranked_by": RANKING, "rank": rank,
                 "evaluation": row["evaluation"], "success_rate": result.success_rate,
                 "collisions_per_episode": result.collisions_per_episode, "env_steps": row["env_steps"],
                 "updates": row["updates"], "wall_s": row["wall_s"]}), indent=2))
        self._print(f"[eval {row['wall_s'] / 60:5.1f} min, {self.counters['env_steps']} steps, {self.state.steps} "
                    f"updates] {result.line()}")
        return result

    def _evaluate_curriculum(self, start: float) -> EvalResult:
        """The current stage's targets and the fixed ``evaluate`` targets, one eval.csv row each;
        returns the last fixed target's result (policy-best and ``stop_at_success`` use it)."""
        from curlnav.run.evaluator import RANKING, BesideEvaluator, best_rank, rank_beats

        if self._evaluator is None:
            self._evaluator = BesideEvaluator(self.run_dir, self.experiment, self.curriculum.curriculum)
        targets = self._eval_targets()
        epoch = self.curriculum.epoch
        self.state.actor.eval()
        rows = self._evaluator.evaluate(self._greedy_policy(), targets)
        self.state.actor.train()
        head = {"evaluation": self._next_evaluation_number(), "wall_s": time.monotonic() - start,
                "env_steps": self.counters["env_steps"],
                "updates": self.state.steps, "policy_version": self.state.steps, "rows": len(rows)}
        for row in rows:
            self.eval_log.write({**head, **row})
            self.board.scalars({f"eval/success/{row['world']}/{row['pair']}": row["success_rate"],
                                f"eval/base_collisions_per_episode/{row['world']}/{row['pair']}":
                                    row["collisions_per_episode"]}, self.counters["env_steps"])
        self._advance_on_evaluation(targets, rows, epoch)
        final = rows[-1]
        result = EvalResult(final["episodes"], final["success_rate"], final["collisions_per_episode"],
                            final["end_effector_collisions_per_episode"], final["mean_time_to_goal_s"],
                            final["mean_episode_time_s"])
        summary = {**head, **self._stage_fields(), "target": f"{final['world']}/{final['pair']}",
                   "success_rate": result.success_rate, "collisions_per_episode": result.collisions_per_episode,
                   "per_target": {f"{r['world']}/{r['pair']}": r["success_rate"] for r in rows}}
        self.counters["evals"].append(strict_json(summary))
        self.board.scalars({"eval/success_rate": result.success_rate}, self.counters["env_steps"])
        rank = list(best_rank(self.curriculum.curriculum, rows))
        if rank_beats(rank, self.counters.get("best_rank")):
            self.counters["best_rank"] = rank
            worlds, extra = self.artefact_training
            folder = export_policy(self.state, self.run_dir / "policy-best", self.experiment.env, worlds=worlds,
                                   extra=extra, curriculum_stage=self.curriculum.current.name,
                                   env_steps=self.counters["env_steps"], stack=self.artefact_stack)
            (folder / "selected.json").write_text(json.dumps(strict_json(
                {"why": f"best held-out evaluation on {summary['target']} so far", "ranked_by": RANKING,
                 "rank": rank, **summary}), indent=2))
        per = "  ".join(f"{r['world']}/{r['pair']} {r['success_rate']:.0%}" for r in rows)
        self._print(f"[eval {summary['wall_s'] / 60:5.1f} min, {self.counters['env_steps']} steps, {self.state.steps} "
                    f"updates, {summary['stage']}.{summary['substep']}] {per}; base collisions/trial on "
                    f"{summary['target']}: {result.collisions_per_episode:.2f}")
        return result

    def _advance_on_evaluation(self, targets, rows: list[dict], epoch: int) -> None:
        """Give the current step's held-out rows to a criterion ``source: evaluation``."""
        from curlnav.run.evaluator import current_step_rate

        step = current_step_rate(self.curriculum.curriculum, targets, rows)
        if step is not None and self.curriculum.record_evaluation(step[0], step[1], epoch):
            self._note_advance()

    def _note_advance(self) -> None:
        step = self.curriculum.history[-1]
        self._print(f"[curriculum] advanced to {step['stage']} sub-step {step['substep']} after "
                    f"{self.counters['env_steps']} env steps ({step['reason']})")
        self.counters.setdefault("advances", []).append(
            {**step, "env_steps": self.counters["env_steps"],
             "wall_s": time.monotonic() - self._start if self._start else 0.0})

    _evaluator = None
    _start = 0.0

    def checkpoint(self, start: float) -> None:
        if self.curriculum is not None:
            self.counters["curriculum"] = self.curriculum.to_dict()
        self.counters["elapsed_s"] = time.monotonic() - start
        save_checkpoint(self.state, self.ckpt_dir / "latest.safetensors",
                        extra={"counters": self.counters, **sensor_metadata(self.experiment.env),
                               **({"stack": self.artefact_stack} if self.artefact_stack else {})})
        if self.run_cfg.save_replay:
            self.table.save(self.ckpt_dir / "replay.npz")
        worlds, extra = self.artefact_training
        export_policy(self.state, self.run_dir / "policy", self.experiment.env, worlds=worlds, extra=extra,
                      curriculum_stage=self.curriculum.current.name if self.curriculum is not None else "none",
                      env_steps=self.counters["env_steps"], stack=self.artefact_stack)

    def _begin(self) -> None:
        if self.curriculum is None:
            self.loop.begin(seed=self.experiment.seed + self.counters["episodes"])
            return
        world, pair = self.curriculum.assign()
        self.task = (world, pair, self.curriculum.epoch)
        options = {"world": world, **({"pair": pair} if pair else {})}
        self.loop.begin(seed=self.experiment.seed + self.counters["episodes"], options=options)

    def _print(self, line: str) -> None:
        (self.bar.write if self.bar is not None else print)(line)

    # -- the loop ----------------------------------------------------------------------------------
    def run(self) -> dict:
        """Train until the budget, a held-out success target or Ctrl-C; returns the summary."""
        from tqdm import tqdm

        from curlnav.evaluation.plots import plot_learning_curve

        experiment, budget = self.experiment, self.experiment.budget
        self.train_log = CsvLog(self.run_dir / "metrics.csv", TRAIN_FIELDS)
        self.eval_log = CsvLog(self.run_dir / "eval.csv", EVAL_FIELDS)
        self.board = TensorBoardLog(self.run_dir)
        history = RunSummary(self.run_dir)
        session = {"started": now_iso(), "mode": "serial", "env_steps_before": self.counters["env_steps"]}
        session_start = self.started
        received: list[int] = []
        previous = on_stop_signals(lambda signum, frame: received.append(signum))
        budget_s = budget.minutes * 60.0
        start = self._start = self.started - self.counters["elapsed_s"]
        self.bar = tqdm(total=int(budget_s), unit="s", disable=not self.run_cfg.progress,
                        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} s {postfix}")
        last_log = last_eval = last_ckpt = time.monotonic()
        at_log = (self.counters["env_steps"], self.state.steps)
        final: EvalResult | None = None
        stop_reason = "time budget"
        self._begin()
        try:
            self._evaluate_before()
            last_eval = time.monotonic()
            while time.monotonic() - start < budget_s:
                if received:
                    stop_reason = f"interrupted by {STOP_SIGNALS[received[0]]}"
                    self._print(f"{stop_reason}: saving a checkpoint and the policy")
                    break
                if budget.max_env_steps is not None and self.counters["env_steps"] >= budget.max_env_steps:
                    stop_reason = "env step budget"
                    break
                if self.table.can_insert(1):
                    self.act_once()
                if self.table.can_sample(experiment.d4pg.batch_size):
                    self.learn_once()
                now = time.monotonic()
                if now - last_log >= 5.0:
                    self._log(now, start, now - last_log, at_log, budget_s)
                    last_log, at_log = now, (self.counters["env_steps"], self.state.steps)
                if (self.counters["env_steps"] > self.policy.warmup_steps
                        and now - last_eval >= experiment.evaluation.every_s):
                    result = self.evaluate(start)
                    last_eval = time.monotonic()
                    target = experiment.evaluation.stop_at_success
                    if target is not None and result.success_rate >= target:
                        final = result
                        stop_reason = f"held-out success {result.success_rate:.0%} >= {target:.0%}"
                        break
                if now - last_ckpt >= self.run_cfg.checkpoint_every_s:
                    self.checkpoint(start)
                    last_ckpt = time.monotonic()
        except KeyboardInterrupt:
            stop_reason = "interrupted by SIGINT (Ctrl-C)"
            self._print("interrupted: saving a checkpoint and the policy")
        finally:
            self.bar.close()
            self.bar = None
            ignore_stop_signals()  # a second signal must not cut the checkpoint short
        try:
            if final is None:
                final = self.evaluate(start)
            self.checkpoint(start)
            self.train_log.close()
            self.eval_log.close()
            self.board.close()
            plot_learning_curve(self.run_dir)
            self.loop.close()
            self.evaluation.close()
            if self._evaluator is not None:
                self._evaluator.close()
        finally:
            restore_signals(previous)
        exit_code = 130 if stop_reason.startswith("interrupted") else 0
        session.update({"stopped": now_iso(), "stop_reason": stop_reason, "exit_code": exit_code,
                        "wall_s": time.monotonic() - session_start, "env_steps": self.counters["env_steps"],
                        "updates": self.state.steps,
                        # the session's control steps by chooser (the network's alone without helpers)
                        "control_steps": dict(self.loop.helpers.steps.counts) if self.loop.helpers is not None
                        else {NETWORK: self.counters["env_steps"] - session["env_steps_before"]}})
        return history.close_session(
            session, stop_reason=stop_reason, exit_code=exit_code, wall_s=time.monotonic() - start,
            env_steps=self.counters["env_steps"], updates=self.state.steps, episodes=self.counters["episodes"],
            final_eval=dataclasses.asdict(final),
            curriculum=None if self.curriculum is None else {
                "name": self.curriculum.curriculum.name, "stage": self.curriculum.current.name,
                "substep": self.curriculum.substep, "advances": self.counters.get("advances", []),
                "replays": self.curriculum.replays},
            run_dir=str(self.run_dir), **outcome_fields(self.run_dir))  # every evaluation of the run, all sessions

    bar = None

    def _evaluate_before(self) -> None:
        """A run from a policy (``init_from``): that policy as it came, before any update, once."""
        from curlnav.run.evaluator import before_line, evaluate_before
        from curlnav.run.record import BEFORE_FILE

        if self.experiment.init_from and not (self.run_dir / BEFORE_FILE).exists():
            curriculum = self.curriculum.curriculum if self.curriculum is not None else None
            self._print(before_line(evaluate_before(self.run_dir, self.experiment, curriculum)))

    def _log(self, now: float, start: float, dt: float, at_log: tuple[int, int], budget_s: float) -> None:
        sps = (self.counters["env_steps"] - at_log[0]) / dt
        ups = (self.state.steps - at_log[1]) / dt
        recent = self.recent
        success = float(np.mean([r[0] for r in recent])) if recent else 0.0
        shares = ControlSteps.summed(self.recent_control).shares()
        row = {"wall_s": now - start, "env_steps": self.counters["env_steps"], "updates": self.state.steps,
               "episodes": self.counters["episodes"], "train_success_100": success,
               "return_100": float(np.mean([r[1] for r in recent])) if recent else 0.0,
               "base_collisions_100": float(np.mean([r[2] for r in recent])) if recent else 0.0,
               "env_steps_per_s": sps, "updates_per_s": ups, "replay_size": self.table.size,
               "policy_version": self.state.steps, "policy_lag": 0, **self._stage_fields(),
               "live_actors": 1, "network_control_share_100": shares.get(NETWORK, 0.0) if shares else None, **self.metrics}
        self.train_log.write(row)
        world = Path(str(self.experiment.curriculum.world)).stem
        self.board.scalars({"train/success_last_100": success, "train/return_last_100": row["return_100"],
                            "train/base_collisions_last_100": row["base_collisions_100"],
                            f"train/success/{world}/random": success, "speed/env_steps_per_s": sps,
                            "speed/updates_per_s": ups, "replay/size": self.table.size, "policy/lag_versions": 0,
                            "curriculum/stage": row["stage_index"], "curriculum/substep": row["substep"],
                            **{f"train/control_steps/{role}": share for role, share in shares.items()},
                            **self.metrics}, self.counters["env_steps"])
        if self.bar is not None:
            self.bar.n = min(int(now - start), int(budget_s))
            self.bar.set_postfix_str(f"steps {self.counters['env_steps']} ({sps:.0f}/s) updates {self.state.steps} "
                                     f"({ups:.1f}/s) episodes {self.counters['episodes']} success {success:.0%} "
                                     f"{row['stage']}.{row['substep']} "
                                     + (f"| control steps: {control_text(shares)} " if self.loop.helpers and shares
                                        else "")
                                     + f"| {max(budget_s - (now - start), 0) / 60:.1f} min left")


def train_serial(run_dir: str | Path, experiment: ExperimentConfig, run: SerialRunConfig | None = None,
                 resume: bool = False, started: float | None = None) -> dict:
    """Train in one process; returns a summary with the final evaluation (see ``SerialTrainer``).
    The budget's clock starts at ``started`` (``time.monotonic()``; default now)."""
    return SerialTrainer(run_dir, experiment, run, resume, started).run()
