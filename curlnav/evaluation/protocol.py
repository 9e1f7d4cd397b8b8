"""The evaluation protocol: greedy policy on held-out start/goal pairs; success rate,
collisions, time.

It follows the authors' protocol: a base collision is counted and the trial goes on; a trial
that has not reached the goal after ``evaluation.max_episode_steps`` (60 s) is a failure.
Held-out pairs are drawn from their own seeds and excluded from training draws. The serial
trainer and the launcher of the distributed run use ``EvaluationProtocol``; ``curlnav eval``
(``curlnav.evaluation.compare``) runs ``evaluate`` on the same held-out pairs, for policies and for the
classical planner (an ``EpisodeAgent``) alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from curlnav.nav.roles import NETWORK, ControlSteps, EpisodeAgent
from curlnav.sim import EnvConfig, NamoEnv, StartGoal, World, get_world
from curlnav.sim.env import pair_key
from curlnav.worlds.core.pairs import draws_random_pairs

EVAL_SEED = 1_000_003  # seeds of held-out pairs live far from training seeds


@dataclass(frozen=True)
class EvalResult:
    episodes: int
    success_rate: float
    collisions_per_episode: float  # base collisions with walls, per episode
    end_effector_collisions_per_episode: float
    mean_time_to_goal_s: float  # over successful episodes (nan if none)
    mean_episode_time_s: float  # over all episodes

    def line(self) -> str:
        return (f"success {self.success_rate:.0%} over {self.episodes} episodes, "
                f"{self.collisions_per_episode:.2f} base collisions/episode, "
                f"{self.end_effector_collisions_per_episode:.2f} end-effector collisions/episode, "
                f"time to goal {self.mean_time_to_goal_s:.1f} s")


def evaluation_config(base: EnvConfig | None = None) -> EnvConfig:
    """The evaluation environment of the default experiment (or of ``base``'s robot and sensors)."""
    from curlnav.config import ExperimentConfig

    experiment = ExperimentConfig() if base is None else dataclasses.replace(ExperimentConfig(), env=base)
    return experiment.eval_env


def held_out_pairs(world: str | World, count: int = 50, seed: int = EVAL_SEED) -> list[StartGoal]:
    """``count`` evaluation pairs: the world's held-out pairs in turn when it names them
    (``World.held_out``: a user's map made a task by ``curlnav train``); else random draws (from
    their own seeds) for worlds that draw random pairs (``random_pairs`` set, or no pairs of their
    own), else the world's own pairs in turn."""
    world = get_world(world)
    if world.held_out:
        return [world.held_out[i % len(world.held_out)] for i in range(count)]
    if not draws_random_pairs(world):
        return [world.pairs[i % len(world.pairs)] for i in range(count)]
    env = NamoEnv(world)
    try:
        pairs = []
        for i in range(count):
            env.np_random = np.random.default_rng(seed + i)
            pair = env._draw_pair()
            pairs.append(dataclasses.replace(pair, name=f"eval-{i}"))
        return pairs
    finally:
        env.close()


def excluded_keys(pairs: list[StartGoal]) -> set:
    return {pair_key(p.x, p.y, p.gx, p.gy) for p in pairs}


class StepRecorder(Protocol):
    """What ``evaluate``'s ``recorder`` makes for an episode (``curlnav.ros2.recording.EpisodeMcap``
    is one): ``step(action, observation)`` after each ``env.step``, ``close()`` when it ends."""

    def step(self, action: np.ndarray, observation: np.ndarray) -> None: ...

    def close(self) -> None: ...


def evaluate(policy: Callable[[np.ndarray], np.ndarray] | EpisodeAgent, world: str | World,
             pairs: list[StartGoal], env_config: EnvConfig | None = None, seed: int = EVAL_SEED,
             on_episode: Callable[[int, dict], None] | None = None, env: NamoEnv | None = None,
             recorder: Callable[[int, NamoEnv, np.ndarray], StepRecorder] | None = None) -> EvalResult:
    """Run ``policy`` (``obs -> action``, or an ``EpisodeAgent``) greedily once per pair (balls
    placed from ``seed + i``) in an environment of ``env_config`` (default:
    ``evaluation_config()``; pass an evaluation environment). ``on_episode(i, info)`` gets the
    last step's ``info`` plus ``trajectory`` (the base's ``(x, y)`` at every step, m) and
    ``truncated`` (the episode ran out of time) and ``control_steps`` (``ControlSteps``: the
    episode's commands counted by the part of the stack that chose them). A pair of ``None`` is drawn by the environment.
    ``recorder(i, env, observation)``, if given, is called after each reset and returns a
    ``StepRecorder`` that sees every step of episode ``i`` and is closed when it ends."""
    cfg = env_config if env_config is not None else evaluation_config()
    own_env = env is None
    env = env or NamoEnv(world, cfg)
    agent = policy if isinstance(policy, EpisodeAgent) else None
    successes, collisions, ee_collisions, times, goal_times = 0, 0, 0, [], []
    try:
        for i, pair in enumerate(pairs):
            obs, info = env.reset(seed=seed + i, options={"world": world, "pair": pair})
            if agent is not None:
                agent.reset(env.world, env.pair)
            steps = recorder(i, env, obs) if recorder is not None else None
            chosen = ControlSteps()
            try:
                while True:
                    if agent is not None:
                        action = agent.act(obs, info)
                        chosen.add(agent)
                    else:
                        action = policy(obs)
                        chosen.counts[NETWORK] += 1
                    obs, _, terminated, truncated, info = env.step(action)
                    if steps is not None:
                        steps.step(action, obs)
                    if terminated or truncated:
                        break
            finally:
                if steps is not None:
                    steps.close()
            info["trajectory"] = list(env.trajectory)
            info["truncated"] = bool(truncated)  # out of time (not ended by the goal or a collision)
            info["control_steps"] = chosen
            successes += int(info["is_success"])
            collisions += info["base_collisions"]
            ee_collisions += info["end_effector_collisions"]
            duration = info["steps"] * cfg.control_period
            times.append(duration)
            if info["is_success"]:
                goal_times.append(duration)
            if on_episode:
                on_episode(i, info)
    finally:
        if own_env:
            env.close()
    n = max(len(pairs), 1)
    return EvalResult(len(pairs), successes / n, collisions / n, ee_collisions / n,
                      float(np.mean(goal_times)) if goal_times else float("nan"), float(np.mean(times)) if times else 0.0)


class EvaluationProtocol:
    """Held-out evaluation of one experiment on one world (``ExperimentConfig.evaluation``):
    ``pairs`` (held out: give ``excluded`` to the training environments), ``run(policy)``."""

    def __init__(self, experiment, world: str | World | None = None, episodes: int | None = None) -> None:
        self.world = world if world is not None else experiment.curriculum.world
        self.env_config = experiment.eval_env
        self.pairs = held_out_pairs(self.world, episodes or experiment.evaluation.episodes)
        self.excluded = excluded_keys(self.pairs)
        self._env: NamoEnv | None = None

    def run(self, policy: Callable[[np.ndarray], np.ndarray],
            on_episode: Callable[[int, dict], None] | None = None) -> EvalResult:
        if self._env is None:
            self._env = NamoEnv(self.world, self.env_config)
        return evaluate(policy, self.world, self.pairs, self.env_config, on_episode=on_episode, env=self._env)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None
