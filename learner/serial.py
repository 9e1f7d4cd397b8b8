"""``curlnav train --serial``: environment loop and learner in one process.

The same cores as the distributed service (``NamoEnv``, ``NStepWriter``, ``ReplayTable`` with
its rate limiter, ``sgd_step``), driven in turn: step the environment while the limiter accepts
inserts, update while it allows samples. Neither ever waits on the other, so it cannot deadlock.

A run folder holds ``config.json``, ``metrics.csv`` (training), ``eval.csv`` (held-out
evaluations), ``learning_curve.png``, ``checkpoints/`` (learner + replay, resumable) and
``policy/`` (the latest exported artefact).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from curlnav.evaluate import EvalResult, evaluate, excluded_keys, held_out_pairs
from curlnav.layout import ObservationLayout
from curlnav.sim import EnvConfig, NamoEnv
from curlnav.replay import NStepWriter, ReplayTable, SampleToInsertRatio

from .artefact import export_policy
from .config import D4PGConfig
from .d4pg import TensorBatch, act, init_state, load_checkpoint, save_checkpoint, sgd_step


@dataclass(frozen=True)
class SerialTrainConfig:
    """One serial training run. Durations in seconds unless named otherwise."""

    world: str = "open-room"
    minutes: float = 15.0  # wall-clock budget, evaluations included
    max_env_steps: int | None = None  # stop earlier after this many environment steps
    warmup_steps: int = 2000  # uniformly random actions before the policy acts
    max_episode_steps: int = 200  # training episodes (40 s); evaluation uses 300 (60 s)
    eval_every_s: float = 120.0
    eval_episodes: int = 50
    stop_at_success: float | None = None  # stop once a held-out evaluation reaches this rate
    checkpoint_every_s: float = 300.0
    save_replay: bool = True  # include the replay in checkpoints (needed for an exact resume)
    torch_threads: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        if self.minutes <= 0 or self.eval_episodes < 1 or self.max_episode_steps < 1 or self.torch_threads < 1:
            raise ValueError("minutes, eval_episodes, max_episode_steps and torch_threads must be positive")


class CsvLog:
    def __init__(self, path: Path, fields: list[str]) -> None:
        self.path = path
        self.fields = fields
        new = not path.exists()
        self._file = open(path, "a", newline="")
        self._writer = csv.DictWriter(self._file, fieldnames=fields, extrasaction="ignore")
        if new:
            self._writer.writeheader()

    def write(self, row: dict) -> None:
        self._writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        self._file.flush()

    def close(self) -> None:
        self._file.close()


TRAIN_FIELDS = ["wall_s", "env_steps", "updates", "episodes", "train_success_100", "return_100",
                "base_collisions_100", "env_steps_per_s", "updates_per_s", "losses/critic", "losses/actor",
                "values/q_mean", "replay_size"]
EVAL_FIELDS = ["wall_s", "env_steps", "updates", "train_episodes", "episodes", "success_rate", "collisions_per_episode",
               "end_effector_collisions_per_episode", "mean_time_to_goal_s"]


def make_table(d4pg: D4PGConfig, layout: ObservationLayout) -> ReplayTable:
    limiter = SampleToInsertRatio(d4pg.samples_per_insert, d4pg.replay_min_size, d4pg.error_buffer)
    limiter.check_batch(d4pg.batch_size)
    return ReplayTable(layout, d4pg.replay_max_size, limiter, "prioritized" if d4pg.prioritized else "uniform",
                       seed=d4pg.seed)


def train_serial(run_dir: str | Path, cfg: SerialTrainConfig, d4pg: D4PGConfig, resume: bool = False,
                 progress: bool = True) -> dict:
    """Train; returns a summary with the final evaluation. Safe to interrupt (Ctrl-C saves)."""
    from tqdm import tqdm

    torch.set_num_threads(cfg.torch_threads)
    run_dir = Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    env_cfg = EnvConfig(max_episode_steps=cfg.max_episode_steps, end_on_base_collision=True)
    layout = ObservationLayout.from_env_config(env_cfg)
    eval_pairs = held_out_pairs(cfg.world, cfg.eval_episodes)
    env = NamoEnv(cfg.world, env_cfg)
    env.excluded_pairs = excluded_keys(eval_pairs)
    eval_env = NamoEnv(cfg.world, dataclasses.replace(env_cfg, end_on_base_collision=False, max_episode_steps=300))

    counters = {"env_steps": 0, "episodes": 0, "elapsed_s": 0.0, "evals": []}
    ckpt_path = ckpt_dir / "latest.safetensors"
    replay_path = ckpt_dir / "replay.npz"
    if resume and ckpt_path.exists():
        state, extra = load_checkpoint(ckpt_path)
        d4pg = state.config
        counters.update(extra.get("counters", {}))
        table = (ReplayTable.restore(replay_path, make_table(d4pg, layout).rate_limiter)
                 if replay_path.exists() else make_table(d4pg, layout))
        print(f"resumed from {ckpt_path}: {state.steps} updates, {counters['env_steps']} env steps, "
              f"replay {table.size} transitions")
    else:
        state = init_state(d4pg, layout)
        table = make_table(d4pg, layout)
    (run_dir / "config.json").write_text(json.dumps({"train": dataclasses.asdict(cfg), "d4pg": d4pg.to_dict(),
                                                     "env": {"world": cfg.world, "max_episode_steps": cfg.max_episode_steps},
                                                     "replay_bytes_per_transition": table.bytes_per_transition},
                                                    indent=2))
    train_log = CsvLog(run_dir / "metrics.csv", TRAIN_FIELDS)
    eval_log = CsvLog(run_dir / "eval.csv", EVAL_FIELDS)
    writer = NStepWriter(layout, d4pg.n_step, d4pg.discount)
    rng = np.random.default_rng(cfg.seed + counters["env_steps"])
    recent = deque(maxlen=100)  # (success, return, base collisions) of the last 100 episodes
    metrics: dict[str, float] = {}
    device = state.device

    obs, _ = env.reset(seed=cfg.seed + counters["episodes"])
    writer.first(obs)
    episode_return = 0.0
    start = time.monotonic() - counters["elapsed_s"]
    last_log = last_eval = last_ckpt = time.monotonic()
    steps_at_log, updates_at_log = counters["env_steps"], state.steps
    budget_s = cfg.minutes * 60.0
    bar = tqdm(total=int(budget_s), unit="s", disable=not progress, bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} s {postfix}")
    final: EvalResult | None = None
    stop_reason = "time budget"

    def run_eval() -> EvalResult:
        state.actor.eval()
        result = evaluate(lambda o: act(state.actor, o), cfg.world, eval_pairs, env.config, env=eval_env)
        state.actor.train()
        wall = time.monotonic() - start
        row = {"wall_s": wall, "env_steps": counters["env_steps"], "updates": state.steps,
               "train_episodes": counters["episodes"], **dataclasses.asdict(result)}
        eval_log.write(row)
        counters["evals"].append(row)
        bar.write(f"[eval {wall / 60:5.1f} min, {counters['env_steps']} steps, {state.steps} updates] {result.line()}")
        return result

    def checkpoint() -> None:
        counters["elapsed_s"] = time.monotonic() - start
        save_checkpoint(state, ckpt_path, extra={"counters": counters})
        if cfg.save_replay:
            table.save(replay_path)
        export_policy(state, run_dir / "policy", env.config, worlds=[cfg.world], env_steps=counters["env_steps"])

    try:
        while True:
            now = time.monotonic()
            elapsed = now - start
            if elapsed >= budget_s:
                break
            if cfg.max_env_steps is not None and counters["env_steps"] >= cfg.max_env_steps:
                stop_reason = "env step budget"
                break
            # -- act ---------------------------------------------------------------------------
            if table.can_insert(1):
                if counters["env_steps"] < cfg.warmup_steps:
                    action = rng.uniform((0.0, -1.0, 0.0), (1.0, 1.0, 1.0)).astype(np.float32)
                else:
                    action = act(state.actor, obs, d4pg.exploration_sigma, rng)
                next_obs, reward, terminated, truncated, info = env.step(action)
                writer.step(action, reward, next_obs, terminated, truncated)
                table.insert(writer.flush(), timeout=0)
                counters["env_steps"] += 1
                episode_return += reward
                obs = next_obs
                if terminated or truncated:
                    counters["episodes"] += 1
                    recent.append((info["is_success"], episode_return, info["base_collisions"]))
                    obs, _ = env.reset(seed=cfg.seed + counters["episodes"])
                    writer.first(obs)
                    episode_return = 0.0
            # -- learn -------------------------------------------------------------------------
            if table.can_sample(d4pg.batch_size):
                sample = table.sample(d4pg.batch_size, timeout=0)
                weights = None
                if d4pg.prioritized:
                    weights = (1.0 / (table.size * sample.probabilities)) ** 0.4
                    weights = weights / weights.max()
                state, metrics, item_loss = sgd_step(state, TensorBatch.from_sample(sample, device, weights))
                if d4pg.prioritized:
                    table.update_priorities(sample.keys, item_loss + 1e-6)
            # -- report ------------------------------------------------------------------------
            now = time.monotonic()
            if now - last_log >= 5.0:
                dt = now - last_log
                sps = (counters["env_steps"] - steps_at_log) / dt
                ups = (state.steps - updates_at_log) / dt
                success = float(np.mean([r[0] for r in recent])) if recent else 0.0
                row = {"wall_s": now - start, "env_steps": counters["env_steps"], "updates": state.steps,
                       "episodes": counters["episodes"], "train_success_100": success,
                       "return_100": float(np.mean([r[1] for r in recent])) if recent else 0.0,
                       "base_collisions_100": float(np.mean([r[2] for r in recent])) if recent else 0.0,
                       "env_steps_per_s": sps, "updates_per_s": ups, "replay_size": table.size, **metrics}
                train_log.write(row)
                bar.n = min(int(now - start), int(budget_s))
                bar.set_postfix_str(f"steps {counters['env_steps']} ({sps:.0f}/s) updates {state.steps} ({ups:.1f}/s) "
                                    f"episodes {counters['episodes']} success {success:.0%}")
                last_log, steps_at_log, updates_at_log = now, counters["env_steps"], state.steps
            if counters["env_steps"] > cfg.warmup_steps and now - last_eval >= cfg.eval_every_s:
                result = run_eval()
                last_eval = time.monotonic()
                if cfg.stop_at_success is not None and result.success_rate >= cfg.stop_at_success:
                    final = result
                    stop_reason = f"held-out success {result.success_rate:.0%} >= {cfg.stop_at_success:.0%}"
                    break
            if now - last_ckpt >= cfg.checkpoint_every_s:
                checkpoint()
                last_ckpt = time.monotonic()
    except KeyboardInterrupt:
        stop_reason = "interrupted"
        bar.write("interrupted: saving a checkpoint and the policy")
    finally:
        bar.close()
    if final is None:
        final = run_eval()
    checkpoint()
    train_log.close()
    eval_log.close()
    from curlnav.plots import plot_learning_curve

    plot_learning_curve(run_dir)
    env.close()
    eval_env.close()
    summary = {"stop_reason": stop_reason, "wall_s": time.monotonic() - start, "env_steps": counters["env_steps"],
               "updates": state.steps, "episodes": counters["episodes"], "final_eval": dataclasses.asdict(final),
               "first_eval_reaching_80": next((e for e in counters["evals"] if e["success_rate"] >= 0.8), None),
               "run_dir": str(run_dir)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
