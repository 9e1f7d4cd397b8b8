"""Turn an actor's step stream into frames and n-step transitions.

For a transition starting at step t with m = min(n, steps left in the episode):

    reward   = sum_{k<m} gamma^k r_{t+k}
    discount = 0            if the episode *terminated* within those m steps (no bootstrap)
             = gamma^m      otherwise (n steps taken, or the episode was *truncated*: a timeout
                            is not a terminal state, so the target still bootstraps from it)
    next     = the frame at t+m

Frames carry the writer's own ids (``local_id``) and the id of the previous frame of the same
episode (``prev_id``, equal to ``local_id`` at an episode's first frame); the replay table maps
them to its own ids, so several writers can feed one table, in one process or over the wire.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from curlnav.layout import ObservationLayout
from curlnav.proto.frames import FrameBatch


class NStepWriter:
    """Accumulates one actor's steps; ``flush()`` returns the frames and transitions made so far."""

    def __init__(self, layout: ObservationLayout, n_step: int = 5, discount: float = 0.99) -> None:
        if n_step < 1:
            raise ValueError("n_step must be at least 1")
        if not 0.0 < discount <= 1.0:
            raise ValueError("discount must be in (0, 1]")
        self.layout = layout
        self.n_step = n_step
        self.discount = discount
        self._next_id = 0
        self.take_id = self._own_id  # where frame ids come from (writers that share an id space replace it)
        self._prev_id: int | None = None
        self._pending: deque[tuple[int, np.ndarray, float]] = deque()  # (frame id, action, reward)
        self._frames: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._transitions: list[tuple[int, int, np.ndarray, float, float]] = []

    def _add_frame(self, obs: np.ndarray, first: bool) -> int:
        ranges, labels, goal = self.layout.newest_frame(np.asarray(obs))
        frame_id = self.take_id()
        prev = frame_id if first or self._prev_id is None else self._prev_id
        ring = self.layout.ring_of(np.asarray(obs))
        self._frames.append((frame_id, prev, ranges.astype(np.float16), labels.astype(np.uint8),
                             goal.astype(np.float32), ring.astype(np.float16)))
        self._prev_id = frame_id
        return frame_id

    def _own_id(self) -> int:
        frame_id = self._next_id
        self._next_id += 1
        return frame_id

    def first(self, obs: np.ndarray) -> None:
        """Start an episode with its reset observation. Unfinished steps of the last one are dropped."""
        self._pending.clear()
        self._add_frame(obs, first=True)

    def step(self, action: np.ndarray, reward: float, next_obs: np.ndarray, terminated: bool,
             truncated: bool) -> None:
        """Record ``action`` taken at the current frame, its ``reward`` and the next observation."""
        if self._prev_id is None:
            raise RuntimeError("call first(obs) before step()")
        obs_id = self._prev_id
        next_id = self._add_frame(next_obs, first=False)
        self._pending.append((obs_id, np.asarray(action, dtype=np.float32), float(reward)))
        if terminated or truncated:
            while self._pending:
                self._emit(next_id, terminated)
            self._prev_id = None
        elif len(self._pending) == self.n_step:
            self._emit(next_id, False)

    def _emit(self, next_id: int, terminated: bool) -> None:
        ret, g = 0.0, 1.0
        for _, _, r in self._pending:
            ret += g * r
            g *= self.discount
        obs_id, action, _ = self._pending.popleft()
        self._transitions.append((obs_id, next_id, action, ret, 0.0 if terminated else g))

    def flush(self) -> FrameBatch:
        frames, transitions = self._frames, self._transitions
        self._frames, self._transitions = [], []
        if not frames and not transitions:
            return FrameBatch.empty(self.layout.beams, memory_beams=self.layout.memory_beams)
        beams = self.layout.beams

        def col(items, i, dtype, shape=()):
            if not items:
                return np.zeros((0, *shape), dtype)
            return np.asarray([item[i] for item in items], dtype=dtype)

        return FrameBatch(
            local_id=col(frames, 0, np.int64), prev_id=col(frames, 1, np.int64),
            ranges=col(frames, 2, np.float16, (beams,)), labels=col(frames, 3, np.uint8, (beams,)),
            goal=col(frames, 4, np.float32, (3,)),
            obs_id=col(transitions, 0, np.int64), next_id=col(transitions, 1, np.int64),
            action=col(transitions, 2, np.float32, (3,)), reward=col(transitions, 3, np.float32),
            discount=col(transitions, 4, np.float32),
            memory=col(frames, 5, np.float16, (self.layout.memory_beams,)),
        )
