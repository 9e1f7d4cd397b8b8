"""What the stages in front of an agent share (``+track``, ``+scan-match``): each takes the
observation and odometry first, rewrites the observation (labels, goal frames) and hands it on.

``FrontStage.act(observation, info)`` calls ``observation(observation, info)`` (the subclass's
rewrite) and then the agent behind: its ``act(observation, info)`` where it has one (with the info
of ``inner_info``), else the plain policy ``policy(observation)``. The beam geometry of the scan
(``beam_cos``, ``beam_sin``: beam 0 on the right) and a window of odometry poses one longer than
the observation's latency (``poses``: the oldest is where the newest scan was measured) are kept
for the subclasses.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np

from curlnav.layout import ObservationLayout, beam_angles
from curlnav.sim import EnvConfig, StartGoal, World


class FrontStage:
    """The shared part of a stage in front of ``policy`` (``obs -> action`` or an ``EpisodeAgent``)."""

    suffix = ""  # the agent argument's suffix naming the stage (its default label: the policy's plus it)

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], env_config: EnvConfig | None = None,
                 label: str | None = None) -> None:
        self.env_config = env_config or EnvConfig()
        self.policy = policy
        self.layout = ObservationLayout.from_env_config(self.env_config)
        self.label = label or f"{getattr(policy, 'label', 'policy')}{self.suffix}"
        fov, beams = self.env_config.lidar_fov, self.env_config.lidar_beams
        angles = beam_angles(fov, beams)  # rad, beam 0 on the right
        self.beam_cos, self.beam_sin = np.cos(angles), np.sin(angles)
        self.max_range = self.env_config.lidar_max_range  # m, the reading of a beam that returns nothing
        latency = getattr(getattr(self.env_config, "sensor_noise", None), "latency_steps", 0) or 0
        self.poses: deque[tuple[float, float, float]] = deque(maxlen=int(latency) + 1)  # odometry, oldest first
        self._clear()

    def _clear(self) -> None:
        """The episode's state, as at its start (subclasses clear theirs, then call this)."""
        self.poses.clear()

    def reset(self, world: World | None, pair: StartGoal | None) -> None:
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)
        self._clear()

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise TypeError(f"{type(self).__name__} needs odometry: call act(observation, info)")

    def observation(self, observation: np.ndarray, info: dict) -> np.ndarray:
        """The observation the agent behind is shown (call once per control step)."""
        raise NotImplementedError

    def inner_info(self, info: dict) -> dict:
        """The info the agent behind is given (the same, unless the stage knows better)."""
        return info

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        shown = self.observation(observation, info)
        inner = getattr(self.policy, "act", None)
        if inner is None:
            return np.asarray(self.policy(shown), dtype=np.float32)
        return np.asarray(inner(shown, self.inner_info(info)), dtype=np.float32)
