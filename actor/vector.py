"""One actor process, K environments: a batched policy call per step of all K, and one n-step
writer whose K streams share the frame ids of the process (issue 31).

``VectorEpisodeLoop`` is ``EpisodeLoop`` for K environments: ``begin(k, ...)`` resets environment
``k`` with its own assignment (world and pair), ``step()`` asks the behaviour policy once for all
K actions (one forward pass of the network on a (K, observation) batch), steps each environment,
writes each transition into environment ``k``'s stream and returns the episodes that ended
(``(k, EpisodeEnd)``), whose environments wait for their next ``begin``. ``flush()`` returns the
frames and transitions of all K streams as one ``FrameBatch``: frame ids are unique across the
streams, and each frame's ``prev_id`` stays within its own environment, so the replay maps them as
it maps one writer's.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from curlnav.layout import ObservationLayout
from curlnav.proto.frames import FrameBatch
from curlnav.replay.nstep import NStepWriter
from curlnav.sim import NamoEnv
from curlnav.worlds.distribution import WorldDraws

from .loop import EpisodeEnd, episode_control_steps, next_world_options

if TYPE_CHECKING:
    from curlnav.memory import MemoryObserver
    from curlnav.nav.training import TrainingHelpers


class VectorNStepWriter:
    """K n-step streams (one per environment) numbering their frames from one counter."""

    def __init__(self, layout: ObservationLayout, streams: int, n_step: int = 5, discount: float = 0.99) -> None:
        if streams < 1:
            raise ValueError(f"a vector writer needs at least one stream, got {streams}")
        self.layout = layout
        self.writers = [NStepWriter(layout, n_step, discount) for _ in range(streams)]
        ids = itertools.count()
        for writer in self.writers:
            writer.take_id = ids.__next__  # one id space for the process: ids unique across streams

    def __len__(self) -> int:
        return len(self.writers)

    @property
    def n_step(self) -> int:
        return self.writers[0].n_step

    @property
    def discount(self) -> float:
        return self.writers[0].discount

    def __getitem__(self, k: int) -> NStepWriter:
        return self.writers[k]

    def flush(self) -> FrameBatch:
        """The frames and transitions of every stream since the last flush, stream after stream."""
        parts = [w.flush() for w in self.writers]
        parts = [p for p in parts if p.num_frames or p.num_transitions]
        if not parts:
            return FrameBatch.empty(self.layout.beams, memory_beams=self.layout.memory_beams)
        if len(parts) == 1:
            return parts[0]
        return FrameBatch(*(np.concatenate([getattr(p, name) for p in parts]) for name in FrameBatch.__dataclass_fields__))


class VectorEpisodeLoop:
    """K environments stepped together with one batched policy call per step."""

    def __init__(self, envs: list[NamoEnv], policy: Callable[[np.ndarray], np.ndarray], writer: VectorNStepWriter,
                 worlds: WorldDraws | None = None, scenes: int | None = None,
                 helpers: TrainingHelpers | None = None, memory: list[MemoryObserver] | None = None) -> None:
        """``scenes``: PyBullet scenes kept built across world switches, all K environments
        together (``actor.scenes_per_process``; each keeps ``scenes // K``, at least 1); None: each
        keeps as many as ``worlds`` keeps worlds. ``helpers``: the stack the network trains inside
        (``curlnav.nav.training``, one agent per environment; None: the network alone). ``memory``:
        the network's memory of each environment (``curlnav.memory``; None: no memory)."""
        if len(envs) != len(writer):
            raise ValueError(f"{len(envs)} environments but {len(writer)} writer streams")
        if memory is not None and len(memory) != len(envs):
            raise ValueError(f"{len(envs)} environments but {len(memory)} memories")
        self.memory = memory
        self.envs = envs
        self.policy = policy  # (K, observation) -> (K, 3): BehaviourPolicy.batch
        self.writer = writer
        self.worlds = worlds if worlds is not None else WorldDraws()  # one set of draws (and pools) for all K
        self.scene_cache = None if scenes is None else max(1, scenes // len(envs))  # per environment
        self.helpers = helpers
        self.obs: list[np.ndarray | None] = [None] * len(envs)  # what the network reads (with the memory's ring)
        self.raw: list[np.ndarray | None] = [None] * len(envs)  # what each environment gave: what the helpers read
        self.infos: list[dict] = [{} for _ in envs]  # each environment's last info: the helpers' odometry
        self.returns = [0.0] * len(envs)
        self.drawn: list[tuple | None] = [None] * len(envs)  # (key, seed) of each environment's drawn world
        self.steps = 0  # environment steps, all environments
        self.episodes = 0

    @property
    def size(self) -> int:
        return len(self.envs)

    @property
    def env(self) -> NamoEnv:
        """The first environment (all K share one config)."""
        return self.envs[0]

    def waiting(self) -> list[int]:
        """The environments whose episode has ended (or never begun): each needs ``begin``."""
        return [k for k, obs in enumerate(self.obs) if obs is None]

    def begin(self, k: int, seed: int, options: dict | None = None) -> np.ndarray:
        """Reset environment ``k`` (``options``: world and pair; a distribution's key draws a world)."""
        env = self.envs[k]
        options = next_world_options(env, self.worlds, options, self.scene_cache)
        self.drawn[k] = self.worlds.take_last()  # None unless a distribution drew this episode's world
        raw, self.infos[k] = env.reset(seed=seed, options=options)
        if self.memory is not None:
            self.memory[k].reset()
        obs = self._network_view(k, raw, self.infos[k])
        self.raw[k] = raw
        if self.helpers is not None:
            self.helpers.begin(k, env.world, env.pair, self.steps)
        self.writer[k].first(obs)
        self.obs[k] = obs
        self.returns[k] = 0.0
        return obs

    def step(self) -> list[tuple[int, EpisodeEnd]]:
        """One step of every running environment (one policy call for all); the episodes that
        ended, as ``(environment index, EpisodeEnd)``."""
        running = [k for k, obs in enumerate(self.obs) if obs is not None]
        if not running:
            raise RuntimeError("begin() an environment before step()")
        actions = self.policy(np.stack([self.obs[k] for k in running]))
        ends = []
        for k, action in zip(running, actions):
            cost = 0.0
            if self.helpers is not None:  # the executed command is the one the transition keeps
                action, _, cost = self.helpers.act(k, action, self.raw[k], self.infos[k])
            raw, reward, terminated, truncated, info = self.envs[k].step(action)
            obs = self._network_view(k, raw, info)
            reward += cost
            self.writer[k].step(action, reward, obs, terminated, truncated)
            self.steps += 1
            self.returns[k] += reward
            self.obs[k], self.raw[k], self.infos[k] = obs, raw, info
            if terminated or truncated:
                self.episodes += 1
                self.obs[k] = self.raw[k] = None
                end = EpisodeEnd(info, self.returns[k], bool(truncated and not terminated),
                                 episode_control_steps(self.helpers, k, info))
                if self.drawn[k] is not None:
                    self.worlds.record_outcome(*self.drawn[k], end.success)
                    self.drawn[k] = None
                ends.append((k, end))
        return ends

    def _network_view(self, k: int, raw: np.ndarray, info: dict) -> np.ndarray:
        return raw if self.memory is None else self.memory[k](raw, info)

    def flush(self) -> FrameBatch:
        return self.writer.flush()

    def close(self) -> None:
        for env in self.envs:
            env.close()
