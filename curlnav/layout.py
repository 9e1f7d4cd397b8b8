"""The observation layout shared by the environment, the replay and the networks.

An observation is ``[ranges (range_frames x beams), labels (label_frames x beams),
ring (memory_beams), goal (goal_frames x 3)]``, oldest frame first in each block (see
``curlnav.sim.env``). The ring is the network memory's (``curlnav.memory``), only in a layout with
one (``memory_beams`` > 0): the policy's side adds it to the environment's observation. One env
step adds one *frame*: the newest ranges, labels and goal. The replay stores frames once and
rebuilds stacked observations from them, so no frame is stored four (or ten) times.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

MAX_BEAMS = 1 << 16  # beams of one scan
MAX_FRAMES = 256  # range, label or goal frames of one observation
MAX_MEMORY_BEAMS = 4096  # sectors of the memory's ring
MAX_MEMORY_STEPS = 100_000  # control steps a return is remembered
MAX_MEMORY_RANGE = 100.0  # m
MEMORY_FIELDS = ("memory_beams", "memory_range", "memory_steps", "memory_stride")


def beam_angles(fov_rad: float, beams: int) -> np.ndarray:
    """``(beams,)`` LiDAR beam angles (rad) evenly over ``fov_rad`` centred ahead, beam 0 on the
    right (the most negative); one beam looks straight ahead. Every part that reads a scan (the
    simulator's LiDAR, its sensor model, the navigation stack's roles, the ROS 2 node) uses these."""
    return np.linspace(-fov_rad / 2, fov_rad / 2, beams) if beams > 1 else np.zeros(1)


def goal_frame(x: float, y: float, yaw: float, gx: float, gy: float) -> np.ndarray:
    """One goal frame, ``[sign(dx) log(1+|dx|), sign(dy) log(1+|dy|), atan2(dy, dx)]`` (float32),
    of the point ``(gx, gy)`` seen from the pose ``(x, y, yaw)`` (m, rad; ``dx`` ahead, ``dy`` to
    the left): the environment's, the ROS 2 node's and every helper that rewrites the goal."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = c * (gx - x) + s * (gy - y), -s * (gx - x) + c * (gy - y)
    return np.array([math.copysign(math.log1p(abs(dx)), dx), math.copysign(math.log1p(abs(dy)), dy),
                     math.atan2(dy, dx)], dtype=np.float32)


@dataclass(frozen=True)
class ObservationLayout:
    beams: int = 241
    range_frames: int = 4
    label_frames: int = 4
    goal_frames: int = 10
    max_range: float = 10.0  # m
    #: the network's memory (``curlnav.memory``): sectors of its ring (0: no memory, the paper's
    #: observation), the ring's reach (m), how long a return is remembered (control steps) and
    #: every how many steps a scan is kept
    memory_beams: int = 0
    memory_range: float = 8.0  # m
    memory_steps: int = 150
    memory_stride: int = 3

    def __post_init__(self) -> None:
        """Bounded, so a layout read from a checkpoint or a replay folder cannot size a network
        or a buffer of billions (issue 35); ``ValueError`` naming the field."""
        for name, low, high in (("beams", 1, MAX_BEAMS), ("range_frames", 1, MAX_FRAMES),
                                ("label_frames", 0, MAX_FRAMES), ("goal_frames", 1, MAX_FRAMES),
                                ("memory_beams", 0, MAX_MEMORY_BEAMS), ("memory_steps", 1, MAX_MEMORY_STEPS),
                                ("memory_stride", 1, MAX_MEMORY_STEPS)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
                raise ValueError(f"layout.{name} must be a whole number {low}-{high}, got {str(value)[:40]!r}")
        ok = isinstance(self.max_range, (int, float)) and not isinstance(self.max_range, bool)
        if not (ok and math.isfinite(self.max_range) and self.max_range > 0):
            raise ValueError(f"layout.max_range must be a positive distance (m), got {str(self.max_range)[:40]!r}")
        ok = isinstance(self.memory_range, (int, float)) and not isinstance(self.memory_range, bool)
        if not (ok and math.isfinite(self.memory_range) and 0 < self.memory_range <= MAX_MEMORY_RANGE):
            raise ValueError(f"layout.memory_range must be a distance above 0 and at most {MAX_MEMORY_RANGE:g} m, "
                             f"got {str(self.memory_range)[:40]!r}")

    @staticmethod
    def from_env_config(cfg) -> ObservationLayout:
        return ObservationLayout(cfg.lidar_beams, cfg.range_frames, cfg.label_frames, cfg.goal_frames,
                                 cfg.lidar_max_range)

    @staticmethod
    def of(env_config, memory=None) -> ObservationLayout:
        """The layout a network reads: ``env_config``'s LiDAR and frames, plus the ring of
        ``memory`` (a ``MemoryConfig``, or None: no memory)."""
        layout = ObservationLayout.from_env_config(env_config)
        if memory is None or not memory.beams:
            return layout
        return replace(layout, memory_beams=memory.beams, memory_range=memory.range_m, memory_steps=memory.steps,
                       memory_stride=memory.stride)

    @property
    def size(self) -> int:
        return (self.range_frames + self.label_frames) * self.beams + self.memory_beams + 3 * self.goal_frames

    def ring_of(self, obs: np.ndarray) -> np.ndarray:
        """The memory's ring ``(..., memory_beams)`` of (batched) observations with one."""
        start = (self.range_frames + self.label_frames) * self.beams
        return obs[..., start:start + self.memory_beams]

    @property
    def history(self) -> int:
        """How many frames one observation spans."""
        return max(self.range_frames, self.label_frames, self.goal_frames)

    def newest_frame(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(ranges (beams,), labels (beams,), goal (3,))`` of the newest frame in ``obs``."""
        b = self.beams
        r_end = self.range_frames * b
        l_end = r_end + self.label_frames * b
        return obs[r_end - b:r_end], obs[l_end - b:l_end], obs[-3:]

    def split(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batched ``obs (B, size)`` into ranges ``(B, range_frames, beams)``, labels
        ``(B, label_frames, beams)`` and goals ``(B, goal_frames * 3)`` (the memory's ring:
        ``ring_of``)."""
        b = self.beams
        r_end = self.range_frames * b
        l_end = r_end + self.label_frames * b
        lead = obs.shape[:-1]
        return (obs[..., :r_end].reshape(*lead, self.range_frames, b),
                obs[..., r_end:l_end].reshape(*lead, self.label_frames, b),
                obs[..., l_end + self.memory_beams:])

    def to_dict(self) -> dict:
        """The fields; the memory's only where the layout has one, so that the layouts written
        before it (artefacts, checkpoints, replay files) read back equal."""
        out = asdict(self)
        if not self.memory_beams:
            for name in MEMORY_FIELDS:
                out.pop(name)
        return out
