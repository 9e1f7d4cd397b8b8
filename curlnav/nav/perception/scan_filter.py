"""A short memory of the static obstacles the map-less baselines see, as real stacks keep one.

A robot's local planner never checks its paths against one raw scan: Nav2's costmap obstacle
layer marks the cells its scans end in and clears, by ray-tracing, the cells its beams pass
through, in a rolling window of the odometry frame; ``laser_filters`` drops isolated returns
(its speckle filter) before that. Without it, one spurious short return blocks every path and
one missing beam opens a wall. ``ScanMemory`` does the same for ``tare-l`` and ``dwa``:

- **spatial support** (after ``laser_filters``' speckle filter): a static return of the newest
  scan is taken at once when another static return of a neighbouring beam (within
  ``window_beams``) lies no further than ``support_m`` (or ``support_beams`` beam spacings at
  its range) from it, as on a wall or a leg seen by two beams, or when it is no spike: not
  nearer, by that much, than the beams on both sides of it (a spurious return, a mixed pixel,
  lies in front of what is around it; a wall seen at a grazing angle or a corner does not);
- **temporal voting**: any static return is taken when its cell (``cell_m``, odometry frame)
  or a neighbouring one was hit in at least ``votes`` of the last ``scans`` scans: a thin leg
  seen by one beam counts from its second scan, a spurious mid-air return never repeats;
- **marking and clearing** (Nav2's obstacle layer): the confirmed returns (supported or voted
  for) of the last ``scans`` scans are remembered in the odometry frame and handed back, moved into the robot
  frame, until a beam of the newest scan passes ``clear_margin_m`` beyond one (a return
  further along the same direction, of any label: the space is free) or the memory ages out;
  where the newest scan measured a remembered return again, its own return stands alone (the
  memory fills only what the newest scan missed, so range noise does not thicken the walls).
  A beam that returns nothing clears nothing (Nav2's ``inf_is_valid: false``): a dropout must
  not open a wall. A beam labelled movable marks nothing but clears what it passes;
- **label voting**: a return counts as static only where the last ``scans`` scans (for the
  newest scan's returns: the ``scans - 1`` before it) labelled its cell of ``label_cell_m`` (or a
  neighbouring one: a ball's returns move with range noise and as it is pushed, 0.2 m a step at
  full speed) static at least as often as movable. A segmenter errs on whole objects at a time: a wall it labels
  movable for a moment stays remembered, and a ball it misses for a moment does not become a wall
  the planners go round, or the shield stops at while it is pushed (they push balls);
- **labels doubted near the base** (with a push check, ``ScanMemory(push=...)``: the shield's
  memory): a return labelled movable within the push check's ``near_m`` counts as static unless
  the robot may push it (``curlnav.nav.safety.push_check``); a segmenter that calls a pillar movable
  in every frame does not hide it. What the memory kept of an object while it was doubted (a ball
  seen before it came within the arm's reach) is dropped where the object is pushable now
  (``PushCheck.follows``). Without a push check (the map-less baselines ``tare-l`` and ``dwa``,
  which push with the base) every label is believed.

On clean scans every return of the newest scan is kept (a lone return of a thin object a step
later), except a static one within about 0.3 m of where a ball was seen in the scans before it,
until it has been seen static as often (up to ``scans - 1`` scans: a wall revealed beside a ball
the robot passes); and the memory adds what the newest scan cannot see: the space behind the robot, and
walls hidden behind a movable object for a moment. Odometry is used only over ``scans`` control
periods (1 s at 5 Hz), so its drift does not matter.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from curlnav.nav.geometry import NEIGHBOUR_OFFSETS, cell_keys, from_frame, to_frame


@dataclass(frozen=True)
class ScanFilterConfig:
    """The scan memory's settings (m, beams, scans). Defaults: 5 scans (1 s at 5 Hz), 2 votes."""

    scans: int = 5  # the memory: the last this many scans
    votes: int = 2  # a return without spatial support counts once its cell is hit in this many of them
    cell_m: float = 0.05  # voting cells (odometry frame); a vote counts for the cell and its 8 neighbours
    window_beams: int = 2  # spatial support: a static return of a beam at most this many beams away ...
    support_m: float = 0.2  # ... within this distance ...
    support_beams: float = 2.5  # ... or this many beam spacings at the return's range (oblique walls)
    clear_margin_m: float = 0.2  # a newest beam reaching this far beyond a remembered return clears it
    range_m: float = 2.0  # returns further than this are not remembered (the nearer ones are what a path can hit first)
    #: labels are voted on in cells this size and their 8 neighbours (odometry frame): a ball pushed at
    #: full speed moves 0.2 m a control step
    label_cell_m: float = 0.15

    def __post_init__(self) -> None:
        if not (isinstance(self.scans, int) and isinstance(self.votes, int) and 1 <= self.votes <= self.scans):
            raise ValueError(f"scan filter: votes ({self.votes!r}) must be a whole number 1..scans ({self.scans!r})")
        for name in ("cell_m", "support_m", "support_beams", "clear_margin_m", "range_m", "label_cell_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"scan filter: {name} must be a positive number, got {value!r}")


class ScanMemory:
    """The filter of the module docstring for one scanner: ``update(ranges, labels, pose)`` once
    per control step returns the static obstacle points to plan against (robot frame, m).

    ``beam_angles``: ``(beams,)`` rad, beam 0 on the right; ``max_range``: m, the reading of a
    beam that returns nothing; ``push``: a ``curlnav.nav.safety.push_check.PushCheck`` that says which
    movable labels near the base to believe (None: all of them)."""

    def __init__(self, beam_angles: np.ndarray, max_range: float, config: ScanFilterConfig | None = None,
                 push=None) -> None:
        self.config = config or ScanFilterConfig()
        self.push = push
        self.beam_angles = np.asarray(beam_angles, dtype=np.float64)
        self.max_range = float(max_range)
        self._spacing = float(np.abs(np.diff(self.beam_angles)).mean()) if len(self.beam_angles) > 1 else math.pi
        self._cos, self._sin = np.cos(self.beam_angles), np.sin(self.beam_angles)
        # per scan: its static returns within range_m (odometry frame, m), their cells, which had
        # spatial support, and the label cells (label_cell_m) of its static and of its movable returns within range_m
        self._scans: deque[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = \
            deque(maxlen=self.config.scans)
        self._doubted: deque[np.ndarray] = deque(maxlen=self.config.scans)  # per scan: which static returns were labelled movable

    def reset(self) -> None:
        """Forget every scan (a new episode or goal: the odometry may have restarted)."""
        self._scans.clear()
        self._doubted.clear()
        if self.push is not None:
            self.push.reset()

    def keys(self, points: np.ndarray) -> np.ndarray:
        """The voting cell of each ``(n, 2)`` odometry-frame point (m), as one int64 key."""
        return cell_keys(points, self.config.cell_m)

    def supported(self, ranges: np.ndarray, static: np.ndarray) -> np.ndarray:
        """``(beams,)`` bool: static returns with a static return of a beam within ``window_beams``
        nearer to them than ``support_m`` or ``support_beams`` beam spacings at their range."""
        cfg = self.config
        x = np.where(static, ranges * self._cos, np.nan)
        y = np.where(static, ranges * self._sin, np.nan)
        reach = np.maximum(cfg.support_m, cfg.support_beams * self._spacing * ranges)
        out = np.zeros(len(ranges), dtype=bool)
        for k in range(1, cfg.window_beams + 1):
            d = np.hypot(x[k:] - x[:-k], y[k:] - y[:-k])  # NaN where either is not a static return
            near = d <= np.maximum(reach[k:], reach[:-k])
            out[k:] |= near
            out[:-k] |= near
        return out & static

    def spikes(self, ranges: np.ndarray) -> np.ndarray:
        """``(beams,)`` bool: returns nearer than the beams on both sides of them (on one side at
        the ends of the scan) by more than ``support_m`` or ``support_beams`` beam spacings."""
        cfg = self.config
        reach = np.maximum(cfg.support_m, cfg.support_beams * self._spacing * ranges)
        padded = np.concatenate([[np.inf], ranges, [np.inf]])
        return (ranges + reach < padded[:-2]) & (ranges + reach < padded[2:])

    def update(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """Take the newest scan (``ranges`` m, ``labels`` 1.0 movable, each ``(beams,)``) seen
        from the odometry ``pose`` (x, y, yaw; m, rad); return ``(n, 2)`` robot-frame points (m)
        of the static obstacles to plan against: the newest scan's confirmed returns first, then
        the remembered ones it did not clear."""
        cfg = self.config
        ranges = np.asarray(ranges, dtype=np.float64)
        labels = np.asarray(labels)
        returned = ranges < self.max_range - 1e-3
        doubted = np.zeros(len(ranges), dtype=bool)
        if self.push is not None:  # a movable label near the base is believed only where the robot may push it
            doubted = returned & (labels >= 0.5) & ~self.push.update(ranges, labels, pose)
            labels = np.where(doubted, 0.0, labels)
        static = returned & (labels < 0.5)
        near = static & (ranges <= cfg.range_m)
        local = np.stack([ranges * self._cos, ranges * self._sin], axis=1)
        points = to_frame(local[near], pose)
        keys = self.keys(points)
        movable = returned & ~static & (ranges <= cfg.range_m)
        support = self.supported(ranges, static) | (static & ~self.spikes(ranges))
        self._scans.append((points, keys, support[near], cell_keys(points, cfg.label_cell_m),
                            cell_keys(to_frame(local[movable], pose), cfg.label_cell_m)))
        self._doubted.append(doubted[near])

        def counter(key_sets, neighbours=NEIGHBOUR_OFFSETS):
            """votes(keys): in how many of the remembered scans each cell (or a neighbour) was hit."""
            spread = [np.unique((k[:, None] + neighbours[None, :]).ravel()) for k in key_sets]
            cells, counts = np.unique(np.concatenate([np.zeros(0, np.int64), *spread]), return_counts=True)

            def votes(k: np.ndarray) -> np.ndarray:
                if len(cells) == 0:
                    return np.zeros(len(k), dtype=np.int64)
                at = np.clip(np.searchsorted(cells, k), 0, len(cells) - 1)
                return np.where(cells[at] == k, counts[at], 0)
            return votes

        votes = counter([k for _, k, _, _, _ in self._scans])
        # labels are voted on in coarser cells and their neighbours, both ways (a ball's returns move
        # with range noise and as it is pushed); the newest scan's own labels are what is voted on, so
        # its returns are judged by the scans before it: a wall touching a ball, static in every scan,
        # stays static; a ball the segmenter missed in this scan, movable round there before, is no
        # obstacle; a return nothing was seen near before is static
        def label_votes(scans) -> tuple:
            return counter([s for _, _, _, s, _ in scans]), counter([m for _, _, _, _, m in scans])

        def static_cell(points: np.ndarray, scans) -> np.ndarray:
            static_votes, movable_votes = label_votes(scans)
            k = cell_keys(points, cfg.label_cell_m)
            return static_votes(k) >= movable_votes(k)

        # the newest scan: supported returns at once, the others once their cell is voted for;
        # not where the segmenter said movable more often than static
        everywhere = to_frame(local, pose)
        all_keys = self.keys(everywhere)
        taken = static & (support | (votes(all_keys) >= cfg.votes)) & static_cell(everywhere, list(self._scans)[:-1])
        newest = local[taken]
        if len(self._scans) == 1:
            return newest
        # remembered returns: confirmed (supported in their scan or voted for), not in a cell the
        # newest scan marks; one per cell, the newest
        older = list(self._scans)[-2::-1]
        old_points = np.concatenate([p for p, _, _, _, _ in older])
        old_keys = np.concatenate([k for _, k, _, _, _ in older])
        confirmed = np.concatenate([c for _, _, c, _, _ in older]) | (votes(old_keys) >= cfg.votes)
        keep = confirmed & static_cell(old_points, self._scans) & ~np.isin(old_keys, keys[taken[near]])
        if self.push is not None:  # kept while doubted, pushable now: what the memory kept of it is no wall
            was_doubted = np.concatenate(list(self._doubted)[-2::-1])
            keep[was_doubted] &= ~self.push.follows(old_points[was_doubted])
        _, first = np.unique(old_keys[keep], return_index=True)
        kept = from_frame(old_points[keep][np.sort(first)], pose)
        # cleared: a newest beam in the same direction returns clear_margin_m beyond it
        d = np.hypot(kept[:, 0], kept[:, 1])
        beam = np.rint((np.arctan2(kept[:, 1], kept[:, 0]) - self.beam_angles[0]) / self._spacing).astype(np.int64)
        seen = (beam >= 0) & (beam < len(ranges))
        beam = np.clip(beam, 0, len(ranges) - 1)
        cleared = seen & returned[beam] & (ranges[beam] > d + cfg.clear_margin_m)
        # superseded: the newest scan measured it again (a static return taken near it on that
        # beam); the memory fills only what the newest scan missed, so noise does not thicken walls
        superseded = seen & taken[beam] & (np.abs(ranges[beam] - d) <= cfg.clear_margin_m)
        kept = kept[~cleared & ~superseded & (d <= cfg.range_m)]
        return np.concatenate([newest, kept])
