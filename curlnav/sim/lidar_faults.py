"""Errors of a LiDAR and its segmenter that persist for an episode, as real ones do.

A frame-by-frame error (``corrupt_scan``) lasts one scan, and a vote over the last scans removes
it. Real errors stick to the surface or the object: a segmenter calls the same pillar movable in
every frame; glass and black surfaces return nothing from the same angles; a shiny surface gives
the same phantom; a LiDAR mounted a little off turns every scan the same way; the robot's own arm
hides the same beams. ``LidarFaults`` draws one episode's such errors and applies them to the true
scan, before the frame-by-frame noise (``curlnav.sim.sensors``).

Surfaces are the map cut into blocks of ``BLOCK_M`` (a wall segment or a pillar); each block draws,
from a hash of its cell and the episode's seed (no per-step draws: the same block errs the same
way at every step, from any pose), at most one of:

- ``block_label_error``: its returns are labelled movable (a segmenter errs on whole objects);
- ``dark_blocks``: it returns nothing at any angle (black, absorbing: the beam reads max range);
- ``glass_blocks``: it returns only within ``GLASS_RETURN_ANGLE`` of its normal (glass);
- ``phantom_blocks``: its returns read short by a fixed distance in ``PHANTOM_OFFSET_M`` (a
  persistent phantom in front of a reflective surface), labelled static.

Movable objects (balls, boxes, doors) each draw ``object_label_error``: missed by the segmenter
(labelled static) for the whole episode. The LiDAR's mount is off by a per-episode yaw
(1-sigma ``mount_yaw``, rad) and scan-plane height (1-sigma ``mount_height``, m), which the
environment applies when it casts the scan. With ``arm_occlusion`` (1: the whole arm) the arm, once
extended past the bumper, hides the beams within ``arm_occlusion * atan((arm_width / 2) /
(base_length / 2))`` of straight ahead (a driver's self-filter drops its returns: no return, label 0).

The incidence angle of a static return is taken from its neighbours' hit points (the surface's
tangent); where a neighbour is on another surface it counts as normal incidence.

Sources of the magnitudes: docs/guide/environment.md, "Errors that persist".
"""

from __future__ import annotations

import math

import numpy as np

from .config import PERSISTENT_FIELDS, RobotConfig, SensorNoiseConfig

BLOCK_M = 0.5  # m, the side of a surface block that errs as one
GLASS_RETURN_ANGLE = math.radians(20.0)  # glass returns only this near its normal
PHANTOM_OFFSET_M = (0.2, 1.0)  # m, how much shorter a phantom block's returns read (per block, uniform)
_SAME_SURFACE_M = 0.15  # m, neighbours' hit points within this of the beam's own lie on its surface
_INSIDE_M = 0.01  # m past a static hit point: inside the wall cell it hit (its block)
_ARM_EXTENDED_M = 0.01  # m of arm displacement past which the stick is beyond the bumper


def unit_hash(keys: np.ndarray, seed: int, channel: int) -> np.ndarray:
    """A uniform value in [0, 1) for each row of integer ``keys`` (shape ``(n, k)``), fixed by
    ``seed`` and ``channel``: splitmix64 over the row."""
    mask = np.uint64(0xFFFFFFFFFFFFFFFF)
    h = np.full(len(keys), (seed * 0x9E3779B97F4A7C15 + channel * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF,
                dtype=np.uint64)
    with np.errstate(over="ignore"):
        for column in np.asarray(keys, dtype=np.int64).reshape(len(keys), -1).T:
            h ^= column.astype(np.uint64)
            h = (h + np.uint64(0x9E3779B97F4A7C15)) & mask
            h = ((h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)) & mask
            h = ((h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)) & mask
            h ^= h >> np.uint64(31)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def incidence_cosine(origin: tuple[float, float], hits: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each beam and its surface's normal, shape ``(beams,)``: the
    surface's tangent through the beam's hit point and its neighbours' (``hits``: m, map frame,
    ``(beams, 2)``) that lie on the same surface (``surface``: the beam ended on a static surface;
    a neighbour within ``_SAME_SURFACE_M`` plus 5 % of the range); 1 (head-on) where neither does."""
    hits = np.asarray(hits, dtype=np.float64)
    n = len(hits)
    direction = hits - np.asarray(origin, dtype=np.float64)
    length = np.linalg.norm(direction, axis=1)
    direction = direction / np.maximum(length, 1e-9)[:, None]
    near = _SAME_SURFACE_M + 0.05 * length
    gap = np.linalg.norm(np.diff(hits, axis=0), axis=1)  # between beam i and i + 1
    joined = surface[:-1] & surface[1:] & (gap < np.minimum(near[:-1], near[1:]))
    has_before = np.concatenate(([False], joined))
    has_after = np.concatenate((joined, [False]))
    before = np.where(has_before[:, None], np.roll(hits, 1, axis=0), hits)
    after = np.where(has_after[:, None], np.roll(hits, -1, axis=0), hits)
    tangent = after - before
    span = np.linalg.norm(tangent, axis=1)
    # the normal is perpendicular to the tangent: |cos(beam, normal)| = |sin(beam, tangent)|
    cross = np.abs(direction[:, 0] * tangent[:, 1] - direction[:, 1] * tangent[:, 0]) / np.maximum(span, 1e-9)
    return np.where(surface & (span > 1e-9) & (n > 1), np.clip(cross, 0.0, 1.0), 1.0)


class LidarFaults:
    """One episode's persistent errors (see the module docstring). Draws from ``rng`` at
    construction only: a seed and two normals."""

    def __init__(self, noise: SensorNoiseConfig, rng: np.random.Generator, robot: RobotConfig,
                 beam_angles: np.ndarray, max_range: float) -> None:
        """``beam_angles``: rad, the beams' nominal directions from the heading, ``(beams,)``;
        ``max_range``: m, what a beam with no return reads."""
        self.noise = noise
        self.seed = int(rng.integers(2 ** 62))
        z = rng.standard_normal(2)
        self.mount_yaw = float(z[0] * noise.mount_yaw)  # rad
        self.mount_height = float(np.clip(z[1] * noise.mount_height, -0.2, 0.2))  # m
        self.max_range = max_range
        occluded = robot.arm and noise.arm_occlusion > 0
        half = noise.arm_occlusion * math.atan2(robot.arm_width / 2, robot.base_length / 2) if occluded else -1.0
        self.arm_beams = np.abs(np.asarray(beam_angles)) <= half  # beams the extended arm hides

    @staticmethod
    def wanted(noise: SensorNoiseConfig) -> bool:
        """Whether ``noise`` sets any error that persists (else the episode draws nothing for them)."""
        return any(getattr(noise, name) > 0 for name in PERSISTENT_FIELDS)

    def apply(self, ranges: np.ndarray, labels: np.ndarray, hits: np.ndarray, bodies: np.ndarray,
              origin: tuple[float, float], arm_displacement: float) -> tuple[np.ndarray, np.ndarray]:
        """The scan as this LiDAR and segmenter give it: ``ranges`` (m) and ``labels`` (0/1), each
        ``(beams,)``, from the true ones, the beams' end points ``hits`` (m, map frame, ``(beams, 2)``),
        the movable body each beam hit (``bodies``, -1: a static surface or nothing), the LiDAR's
        ``origin`` (m, map frame) and the arm's displacement (m)."""
        noise = self.noise
        r = np.asarray(ranges, dtype=np.float64).copy()
        out_labels = np.asarray(labels, dtype=np.float64).copy()
        returned = r < self.max_range
        bodies = np.asarray(bodies)
        movable = returned & (bodies >= 0)
        static = returned & ~movable
        if movable.any() and noise.object_label_error > 0:
            missed = unit_hash(bodies[movable][:, None], self.seed, 1) < noise.object_label_error
            out_labels[np.flatnonzero(movable)[missed]] = 0.0
        if static.any():
            idx = np.flatnonzero(static)
            direction = hits[idx] - np.asarray(origin, dtype=np.float64)
            direction /= np.maximum(np.linalg.norm(direction, axis=1), 1e-9)[:, None]
            blocks = np.floor((hits[idx] + _INSIDE_M * direction) / BLOCK_M).astype(np.int64)
            mislabelled = unit_hash(blocks, self.seed, 2) < noise.block_label_error
            out_labels[idx[mislabelled]] = 1.0
            kind = unit_hash(blocks, self.seed, 3)  # one surface kind per block
            dark = kind < noise.dark_blocks
            glass = (kind >= noise.dark_blocks) & (kind < noise.dark_blocks + noise.glass_blocks)
            phantom = (kind >= noise.dark_blocks + noise.glass_blocks) & (
                kind < noise.dark_blocks + noise.glass_blocks + noise.phantom_blocks)
            if glass.any():
                cosine = incidence_cosine(origin, hits, static)[idx]
                glass &= cosine < math.cos(GLASS_RETURN_ANGLE)
            if phantom.any():
                low, high = PHANTOM_OFFSET_M
                offset = low + (high - low) * unit_hash(blocks[phantom], self.seed, 4)
                r[idx[phantom]] = np.maximum(r[idx[phantom]] - offset, 0.05)
                out_labels[idx[phantom]] = 0.0
            lost = idx[dark | glass]
            r[lost], out_labels[lost] = self.max_range, 0.0
        if arm_displacement > _ARM_EXTENDED_M and self.arm_beams.any():
            r[self.arm_beams], out_labels[self.arm_beams] = self.max_range, 0.0
        return r.astype(np.float32), out_labels.astype(np.float32)
