"""The one episode loop: environment, behaviour policy and n-step writer, stepped in turn.

The serial trainer and the actor service both drive an ``EpisodeLoop``; they differ only in
where the written frames go (straight into the replay table, or onto the bus in batches) and in
who assigns the next world and pair. An assigned world distribution (``curlnav.worlds.distribution``)
is drawn here, so both modes draw worlds the same way.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from curlnav.nav.roles import NETWORK
from curlnav.replay import FrameBatch, NStepWriter
from curlnav.sim import NamoEnv
from curlnav.worlds.distribution import WorldDraws

if TYPE_CHECKING:
    from curlnav.memory import MemoryObserver
    from curlnav.nav.training import TrainingHelpers


@dataclass(frozen=True)
class EpisodeEnd:
    """An episode that just ended: its info (``NamoEnv``'s last ``info``), return (intervention
    costs included) and its control steps by chooser (role -> steps; ``curlnav.nav.roles.chooser``)."""

    info: dict[str, Any]
    episode_return: float
    truncated: bool
    control_steps: dict[str, int] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return bool(self.info["is_success"])


def next_world_options(env: NamoEnv, draws: WorldDraws, options: dict | None,
                       scene_cache: int | None = None) -> dict | None:
    """``options`` with a world distribution's key replaced by the world ``draws`` draws for this
    episode (``WorldDraws``: never a held-out seed); ``env`` keeps the scenes of the last
    ``scene_cache`` worlds built (default: as many as the draws keep worlds). Other options are
    returned as they are."""
    if options and options.get("world") is not None:
        world = draws.resolve(options["world"])
        if world is not options["world"]:
            env.scene_cache = max(env.scene_cache, draws.cache if scene_cache is None else scene_cache)
            return {**options, "world": world}
    return options


def episode_control_steps(helpers: TrainingHelpers | None, k: int, info: dict) -> dict[str, int]:
    """The ended episode's control steps by chooser: the helpers' count, or all the network's."""
    if helpers is None:
        return {NETWORK: int(info.get("steps", 0))}
    return dict(helpers.episode[k].counts)


class EpisodeLoop:
    """``begin`` an episode, then ``step`` until it returns an ``EpisodeEnd``; ``flush``
    whenever the written transitions should go out (the writer keeps the n-step tail)."""

    def __init__(self, env: NamoEnv, policy: Callable[[np.ndarray], np.ndarray], writer: NStepWriter,
                 worlds: WorldDraws | None = None, helpers: TrainingHelpers | None = None,
                 memory: MemoryObserver | None = None) -> None:
        """``helpers``: the stack the network trains inside (``curlnav.nav.training``; None: alone).
        ``memory``: the network's memory (``curlnav.memory``), which adds its ring to each
        observation the policy and the writer see (None: the environment's observation as is)."""
        self.env = env
        self.memory = memory
        self.policy = policy
        self.writer = writer
        self.worlds = worlds if worlds is not None else WorldDraws()  # draws for distribution assignments
        self.helpers = helpers
        self.obs: np.ndarray | None = None  # what the network reads (with the memory's ring)
        self.raw: np.ndarray | None = None  # what the environment gave: what the helpers read
        self.info: dict = {}  # the last step's (or reset's) info: the helpers' odometry
        self.episode_return = 0.0
        self.steps = 0  # environment steps, all episodes
        self.episodes = 0  # episodes ended

    def begin(self, seed: int, options: dict | None = None) -> np.ndarray:
        """Reset the environment (``options``: world and pair) and start a new trajectory. A
        world distribution's key as the world draws this episode's world (``WorldDraws``: never a
        held-out seed); its scenes stay built in the environment's scene cache."""
        options = next_world_options(self.env, self.worlds, options)
        self.raw, self.info = self.env.reset(seed=seed, options=options)
        if self.memory is not None:
            self.memory.reset()
        self.obs = self._network_view(self.raw, self.info)
        if self.helpers is not None:
            self.helpers.begin(0, self.env.world, self.env.pair, self.steps)
        self.writer.first(self.obs)
        self.episode_return = 0.0
        return self.obs

    def step(self) -> EpisodeEnd | None:
        """One environment step with the behaviour policy; the transition goes to the writer.
        Returns the episode's end when this step ended it, else None."""
        if self.obs is None:
            raise RuntimeError("call begin() before step()")
        action = self.policy(self.obs)
        cost = 0.0
        if self.helpers is not None:  # the executed command is the one the transition keeps
            action, _, cost = self.helpers.act(0, action, self.raw, self.info)
        raw, reward, terminated, truncated, info = self.env.step(action)
        obs = self._network_view(raw, info)
        reward += cost
        self.writer.step(action, reward, obs, terminated, truncated)
        self.steps += 1
        self.episode_return += reward
        self.obs, self.raw, self.info = obs, raw, info
        if terminated or truncated:
            self.episodes += 1
            self.obs = self.raw = None
            end = EpisodeEnd(info, self.episode_return, bool(truncated and not terminated),
                             episode_control_steps(self.helpers, 0, info))
            self.worlds.record(end.success)  # the level sampler of a drawn world learns the outcome
            return end
        return None

    def _network_view(self, raw: np.ndarray, info: dict) -> np.ndarray:
        return raw if self.memory is None else self.memory(raw, info)

    def flush(self) -> FrameBatch:
        """Frames and transitions written since the last flush."""
        return self.writer.flush()

    def close(self) -> None:
        self.env.close()
