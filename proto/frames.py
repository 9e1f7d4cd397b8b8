"""``FrameBatch``: frames and n-step transitions as they travel from a writer to a replay table
(in one process, or inside a ``TransitionBatch`` message). Wire-level data: it imports nothing
of the services."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FrameBatch:
    """Frames and transitions ready to insert. Arrays, first axis = items.

    frames: ``local_id`` (int64), ``prev_id`` (int64), ``ranges`` (float16, m, (F, beams)),
    ``labels`` (uint8, (F, beams)), ``goal`` (float32, (F, 3)), ``memory`` (float16, m, (F, M):
    the network memory's ring of each frame, ``curlnav.memory``; M = 0 without memory).
    transitions: ``obs_id``, ``next_id`` (int64, writer ids), ``action`` (float32, (T, 3)),
    ``reward`` (float32), ``discount`` (float32).
    """

    local_id: np.ndarray
    prev_id: np.ndarray
    ranges: np.ndarray
    labels: np.ndarray
    goal: np.ndarray
    obs_id: np.ndarray
    next_id: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    memory: np.ndarray | None = None  # None: no memory, (F, 0)

    def __post_init__(self) -> None:
        if self.memory is None:
            self.memory = np.zeros((len(self.local_id), 0), np.float16)

    @property
    def num_frames(self) -> int:
        return len(self.local_id)

    @property
    def num_transitions(self) -> int:
        return len(self.obs_id)

    @staticmethod
    def empty(beams: int, action_size: int = 3, memory_beams: int = 0) -> FrameBatch:
        return FrameBatch(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, beams), np.float16),
                          np.zeros((0, beams), np.uint8), np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                          np.zeros(0, np.int64), np.zeros((0, action_size), np.float32), np.zeros(0, np.float32),
                          np.zeros(0, np.float32), np.zeros((0, memory_beams), np.float16))
