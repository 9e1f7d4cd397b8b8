"""Movable labels voted over the last scans, as a robot's object tracker keeps them.

A movable-object segmenter (a point-cloud network, or a camera detector projected onto the
scan) errs a frame at a time: it labels a stretch of wall movable for one frame, or misses a
ball for one. Nothing on a robot consumes its raw per-frame output: detections are tracked over
frames, and an object counts once it has been seen more than once. A policy that reads raw
labels may take a wall it was just told is movable for something to push.

``LabelFilteredPolicy`` sits in front of everything else of an agent (the suffix ``+track``): each
control step it takes the newest scan of the observation, moves its returns into the odometry
frame (from the pose it was seen at: the observation may be late by ``latency_steps``), and
votes on each beam labelled movable over the last ``scans`` scans, this one included: for
movable, the scans that labelled a return movable in its cell or a neighbouring one (``cell_m``:
a ball pushed at full speed moves 0.2 m a control step); against, the scans that labelled a
return static in its own cell. The beam stays movable when the votes for outnumber those
against. A stretch of wall labelled movable for one frame has been seen as wall before and is
dropped; a ball labelled movable frame after frame stays, and so does an object the scans have
not seen before (nothing votes against it: no delay when a ball comes into view). The
observation's label frames are replaced by the voted labels of the same steps, oldest first;
ranges and goal are kept. The rescue, the shield and the policy behind it all see them.

Odometry is used over ``scans`` control periods only (0.6 s at 5 Hz): its drift does not matter.
On exact labels a movable beam is dropped only in the first scan a movable object appears in.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from curlnav.nav.geometry import NEIGHBOUR_OFFSETS, cell_keys, odometry, to_frame
from curlnav.nav.perception.stage import FrontStage
from curlnav.nav.registry import TRACK_SUFFIX
from curlnav.sim import EnvConfig


@dataclass(frozen=True)
class LabelFilterConfig:
    """The vote (scans, m). Defaults: the last 3 scans (0.6 s at 5 Hz), cells of 0.15 m."""

    scans: int = 3  # the last this many scans, the newest included
    cell_m: float = 0.15  # voting cells in the odometry frame; a movable label counts for its cell and the 8 around it

    def __post_init__(self) -> None:
        if not (isinstance(self.scans, int) and not isinstance(self.scans, bool) and 1 <= self.scans <= 50):
            raise ValueError(f"label filter: scans must be a whole number 1-50, got {self.scans!r}")
        if not (isinstance(self.cell_m, (int, float)) and math.isfinite(self.cell_m) and self.cell_m > 0):
            raise ValueError(f"label filter: cell_m must be a positive number of metres, got {self.cell_m!r}")


class LabelFilteredPolicy(FrontStage):
    """``policy`` (``obs -> action`` or an ``EpisodeAgent``) fed observations whose movable labels
    were voted over the last scans (module docstring): ``act(observation, info) -> action``.
    ``dropped`` counts the movable beams the vote removed in the current episode, ``labelled`` the
    movable beams it was shown."""

    control_role = "label-vote"  # its registry entry: the part of a stack credited with its commands (``roles.chooser``)

    suffix = TRACK_SUFFIX

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], env_config: EnvConfig | None = None,
                 config: LabelFilterConfig | None = None, label: str | None = None) -> None:
        self.config = config or LabelFilterConfig()
        # per scan: the cells of its movable returns and their neighbours, the cells of its static returns
        self._cells: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=self.config.scans)
        self._frames: deque[np.ndarray] = deque()  # filtered labels, oldest first
        super().__init__(policy, env_config, label)
        self._frames = deque(maxlen=self.layout.label_frames)

    def _clear(self) -> None:
        self._cells.clear()
        self._frames.clear()
        self.dropped = self.labelled = 0
        super()._clear()

    def filter(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """The voted labels (``(beams,)`` float32, 1.0 movable) of the newest scan (``ranges`` m,
        ``labels``) seen from the odometry ``pose`` (x, y, yaw; m, rad). Call once per scan."""
        returned = ranges < self.max_range - 1e-3
        movable = (labels > 0.5) & returned
        r = ranges.astype(np.float64)
        points = to_frame(np.stack([r * self.beam_cos, r * self.beam_sin], axis=1), pose)
        keys = cell_keys(points, self.config.cell_m)
        self._cells.append((np.unique((keys[movable][:, None] + NEIGHBOUR_OFFSETS[None, :]).ravel()),
                            np.unique(keys[returned & ~movable])))
        mine = keys[movable]
        votes = np.zeros(len(mine), dtype=np.int64)
        for movable_cells, static_cells in self._cells:
            votes += np.isin(mine, movable_cells).astype(np.int64) - np.isin(mine, static_cells)
        keep = votes > 0
        out = np.zeros(len(ranges), dtype=np.float32)
        out[np.flatnonzero(movable)[keep]] = 1.0
        self.labelled += len(mine)
        self.dropped += int((~keep).sum())
        return out

    def observation(self, observation: np.ndarray, info: dict) -> np.ndarray:
        """``observation`` with its label frames replaced by the voted labels of the same steps."""
        obs = np.asarray(observation, dtype=np.float32)
        self.poses.append(odometry(info))
        ranges, labels, _ = self.layout.newest_frame(obs)
        voted = self.filter(ranges, labels, self.poses[0])
        if not self._frames:  # the episode's first observation repeats its first frame
            self._frames.extend([voted] * (self.layout.label_frames - 1))
        self._frames.append(voted)
        b = self.layout.beams
        start = self.layout.range_frames * b
        out = obs.copy()
        out[start:start + self.layout.label_frames * b] = np.concatenate(self._frames)
        return out
