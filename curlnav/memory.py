"""The network's memory: recent scans kept in the robot's odometry frame, read as a ring.

A frame stack of four scans (0.8 s) forgets a dead end as soon as the robot turns its LiDAR
away from it, so a network that turns round in a U-shaped wall turns back into it (issue 53:
the network alone 0 % on such a map, the rescue, which keeps a scan map, 100 %). ``ScanMemory``
gives the network what the rescue knows, in a form an MLP reads cheaply:

- every ``memory_stride``-th scan, the returns of beams labelled static (``label < 0.5``) that
  hit something (``range < max_range``) are kept as points in the **odometry frame**, the
  robot's own pose estimate (``info["odometry"]`` in the simulator, ``/odom`` on a robot), so
  the memory drifts as the robot's odometry does; one point per 0.1 m cell (``CELL_M``), the
  newest return seen there, so a wall seen again and again costs no more than one seen once;
- a cell not seen for ``memory_steps`` control steps (30 s at 5 Hz by default) is forgotten:
  old points carry old drift, and obstacles move;
- the memory is read as a **ring** of ``memory_beams`` sectors round the robot, 360 deg (the
  LiDAR covers 240): each sector's value is the distance (m) from the robot to the nearest
  remembered point in it, ``memory_range`` where there is none. Sector ``i`` is centred on the
  bearing ``-pi + i * 2 pi / memory_beams`` in the robot frame (x ahead, y left): sector 0 looks
  straight back, sector ``memory_beams / 2`` straight ahead.

Returns labelled movable are left out: a ball the arm pushes away must not stay behind as a
wall. The live scan, which the network also sees, shows them. The ring sits in the observation
between the label frames and the goal frames (``ObservationLayout``); the simulator does not
compute it: the policy's side does (the actor while it trains, the evaluation's controller, the
robot's node), from what the robot senses, so that it is the same everywhere the network runs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from curlnav.layout import ObservationLayout, beam_angles

__all__ = ["ScanMemory", "MemoryObserver", "RememberingPolicy", "newest_scan", "with_ring", "policy_layout", "remembering"]

#: entries of a memory's hash table at first (a power of two; it doubles when it must)
TABLE_START = 4096
#: where ``MemoryObserver`` takes the pose of the observation's newest scan, first found first: the
#: simulator's odometry at the time of that scan (``latency_steps`` old under sensor noise), its
#: odometry now, the ROS 2 node's ``/odom`` pose
POSE_KEYS = ("observed_odometry", "odometry", "pose")
#: the memory keeps one return per cell of this size (m): the newest seen there
CELL_M = 0.1
#: keep every second beam's return as a point: 2 deg apart at 241 beams over 240 deg (0.1 m at 3 m),
#: and half the points to merge at each kept scan
POINT_BEAM_STEP = 2


class ScanMemory:
    """Remembered static returns of one robot, as the module docstring says. ``add`` a scan
    each control step (the memory keeps every ``memory_stride``-th), ``ring`` to read it.

    The cells live in an open-addressing hash table (numba kernels: ``_remember``, ``_read_ring``),
    so a scan is merged and the ring read in a few microseconds whatever the number of cells; a
    forgotten cell stays in the table until it is rebuilt with the remembered ones only, when it
    is half full."""

    def __init__(self, layout: ObservationLayout, lidar_fov_rad: float) -> None:
        if layout.memory_beams < 1:
            raise ValueError("this layout has no memory (memory_beams 0)")
        self.layout = layout
        self.sectors = layout.memory_beams
        self.range_m = float(layout.memory_range)
        self.stride = layout.memory_stride
        self._sector_width = 2 * math.pi / self.sectors
        self._keep = np.arange(0, layout.beams, POINT_BEAM_STEP)
        self._angles = beam_angles(lidar_fov_rad, layout.beams)[self._keep]
        self._table(TABLE_START)
        self._steps = 0

    def _table(self, capacity: int) -> None:
        """An empty table of ``capacity`` entries (a power of two)."""
        self._ix = np.zeros(capacity, np.int64)  # cell indices (x, y) of each entry ...
        self._iy = np.zeros(capacity, np.int64)
        self._x = np.zeros(capacity)  # ... the newest return seen in it (m, odometry frame) ...
        self._y = np.zeros(capacity)
        self._seen = np.full(capacity, -1, np.int64)  # ... and the step it was seen; -1: an empty entry
        self._used = 0

    def reset(self) -> None:
        """Forget everything (a new episode)."""
        self._seen.fill(-1)
        self._used = 0
        self._steps = 0

    @property
    def _first_kept(self) -> int:
        """The earliest step whose returns are still remembered (after ``add`` of the step
        ``_steps - 1``)."""
        return self._steps - self.layout.memory_steps

    @property
    def cells(self) -> int:
        """How many cells the memory remembers."""
        return int((self._seen >= max(self._first_kept, 0)).sum())

    def add(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> None:
        """One control step's scan (``ranges`` (beams,) m, ``labels`` (beams,), 1 = movable),
        seen from ``pose`` (x m, y m, yaw rad in the odometry frame). A cell is remembered for
        ``memory_steps`` steps after it was last seen."""
        step = self._steps
        self._steps += 1
        if step % self.stride:
            return
        r = np.asarray(ranges, np.float64)[self._keep]
        hit = np.isfinite(r) & (r < self.layout.max_range - 1e-3) & (np.asarray(labels)[self._keep] < 0.5)
        if not hit.any():
            return
        x, y, yaw = pose
        a = self._angles[hit] + yaw
        px, py = x + r[hit] * np.cos(a), y + r[hit] * np.sin(a)
        if 2 * (self._used + len(px)) > len(self._seen):
            self._rebuild(len(px))
        self._used += _remember(self._ix, self._iy, self._x, self._y, self._seen, np.floor(px / CELL_M).astype(np.int64),
                                np.floor(py / CELL_M).astype(np.int64), px, py, np.full(len(px), step, np.int64))

    def _rebuild(self, coming: int) -> None:
        """The table again with the remembered cells only, twice as large (or more) when they
        and the ``coming`` ones would fill more than a quarter of it (so that rebuilds stay rare)."""
        kept = np.flatnonzero(self._seen >= max(self._first_kept, 0))
        old = self._ix[kept], self._iy[kept], self._x[kept], self._y[kept], self._seen[kept]
        capacity = len(self._seen)
        while 4 * (len(kept) + coming) > capacity:
            capacity *= 2
        self._table(capacity)
        self._used = _remember(self._ix, self._iy, self._x, self._y, self._seen, *old)

    def ring(self, pose: tuple[float, float, float]) -> np.ndarray:
        """``(memory_beams,)`` float32: the distance (m) to the nearest remembered point in each
        sector round ``pose``, at most ``memory_range``."""
        out = np.full(self.sectors, self.range_m * self.range_m)
        x, y, yaw = pose
        _read_ring(self._x, self._y, self._seen, max(self._first_kept, 0), float(x), float(y), math.cos(yaw),
                   math.sin(yaw), self._sector_width, out)
        return np.sqrt(out).astype(np.float32)

    def update(self, observation: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``add`` the newest scan of ``observation`` (the environment's, without a ring) seen
        from ``pose`` and return the ``ring`` round it."""
        ranges, labels = newest_scan(self.layout, observation)
        self.add(ranges, labels, pose)
        return self.ring(pose)


@njit(cache=True)
def _remember(cell_ix, cell_iy, cell_x, cell_y, cell_seen, ix, iy, px, py, steps):  # pragma: no cover (numba)
    """Merge the points ``(px, py)`` of cells ``(ix, iy)`` seen at ``steps`` (one each, in the
    order seen) into the table (linear probing; its size a power of two, at most half full);
    returns the entries it filled."""
    mask = cell_seen.shape[0] - 1
    filled = 0
    for i in range(ix.shape[0]):
        h = ((ix[i] * 73856093) ^ (iy[i] * 19349663)) & mask
        while cell_seen[h] >= 0 and (cell_ix[h] != ix[i] or cell_iy[h] != iy[i]):
            h = (h + 1) & mask
        if cell_seen[h] < 0:
            cell_ix[h] = ix[i]
            cell_iy[h] = iy[i]
            filled += 1
        cell_x[h] = px[i]
        cell_y[h] = py[i]
        cell_seen[h] = steps[i]
    return filled


@njit(cache=True)
def _read_ring(cell_x, cell_y, cell_seen, first_kept, x, y, c, s, width, out):  # pragma: no cover (numba)
    """``out`` (sectors,), filled with the reach squared: the squared distance of the nearest
    entry seen at ``first_kept`` or later in each sector round the pose ``(x, y)`` (heading
    cosine ``c``, sine ``s``), where nearer than the reach."""
    sectors = out.shape[0]
    reach_squared = out[0]
    for h in range(cell_seen.shape[0]):
        if cell_seen[h] < first_kept:
            continue
        dx = cell_x[h] - x
        dy = cell_y[h] - y
        ahead = c * dx + s * dy
        left = -s * dx + c * dy
        squared = ahead * ahead + left * left
        if squared >= reach_squared:  # beyond the ring's reach: no atan2 for it
            continue
        k = int(math.floor((math.atan2(left, ahead) + math.pi + width / 2) / width)) % sectors
        if squared < out[k]:
            out[k] = squared


def newest_scan(layout: ObservationLayout, observation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The newest ranges and labels of an observation with or without its ring
    (``ObservationLayout.newest_frame``; all static where the layout has no label frames)."""
    ranges, labels, _ = layout.newest_frame(observation)
    return ranges, labels if layout.label_frames else np.zeros(layout.beams, np.float32)


def with_ring(layout: ObservationLayout, observation: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """The environment's ``observation`` (``layout.size - memory_beams`` values) with ``ring``
    put in its place, between the label frames and the goal frames: ``layout.size`` values."""
    split = (layout.range_frames + layout.label_frames) * layout.beams
    return np.concatenate([observation[:split], np.asarray(ring, np.float32), observation[split:]]).astype(
        np.float32, copy=False)


class MemoryObserver:
    """One environment's memory: turns each observation the environment gives (with the step's
    ``info["odometry"]``) into the observation the network reads (the same, for a layout without
    memory)."""

    def __init__(self, layout: ObservationLayout, lidar_fov_rad: float) -> None:
        self.layout = layout
        self.memory = ScanMemory(layout, lidar_fov_rad) if layout.memory_beams else None

    def reset(self) -> None:
        if self.memory is not None:
            self.memory.reset()

    def __call__(self, observation: np.ndarray, info: dict) -> np.ndarray:
        if self.memory is None:
            return observation
        observation = np.asarray(observation, np.float32)
        if observation.shape[-1] == self.layout.size:  # already has its ring (a stage passed it on)
            return observation
        pose = next((info[k] for k in POSE_KEYS if info.get(k) is not None), None)
        if pose is None:
            raise ValueError("a policy with memory needs the robot's odometry (info['odometry']) at every step")
        return with_ring(self.layout, observation, self.memory.update(observation, tuple(pose)))


class RememberingPolicy:
    """A policy whose network reads a memory (``layout.memory_beams`` > 0) as an agent of the
    navigation stack: ``reset`` forgets, ``act(observation, info)`` adds the ring round
    ``info["odometry"]`` to the environment's observation and asks the policy. ``metadata`` (and
    ``observation_size``, ``version``) are the wrapped policy's; it chooses no command of its own
    (no ``control_role``: its steps are the network's)."""

    def __init__(self, policy, layout: ObservationLayout, lidar_fov_rad: float) -> None:
        self.policy = policy
        self.layout = layout
        self.observer = MemoryObserver(layout, lidar_fov_rad)
        self.metadata = getattr(policy, "metadata", None)
        self.label = getattr(policy, "label", None) or "policy"

    @property
    def observation_size(self):
        return getattr(self.policy, "observation_size", None)

    @property
    def version(self):
        return getattr(self.policy, "version", None)

    def reset(self, world=None, pair=None) -> None:
        self.observer.reset()
        inner = getattr(self.policy, "reset", None)
        if callable(inner):
            inner(world, pair)

    def act(self, observation: np.ndarray, info: dict) -> np.ndarray:
        return self.policy(self.observer(observation, info))

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        raise ValueError("this policy's network reads a memory of the robot's odometry: call act(observation, info)")


def policy_layout(policy) -> ObservationLayout | None:
    """The observation layout a policy's ``metadata`` records (an artefact's, a checkpoint's), or
    None where it records none."""
    meta = getattr(policy, "metadata", None)
    observation = meta.get("observation") if isinstance(meta, dict) else None
    layout = observation.get("layout") if isinstance(observation, dict) else None
    return ObservationLayout(**layout) if isinstance(layout, dict) else None


def remembering(policy, lidar_fov_rad: float):
    """``policy`` as ``RememberingPolicy`` where its network reads a memory, else itself. The
    field of view is the policy's own (``observation.lidar_fov_rad``) where it records one."""
    layout = policy_layout(policy)
    if layout is None or not layout.memory_beams or isinstance(policy, RememberingPolicy):
        return policy
    fov = policy.metadata["observation"].get("lidar_fov_rad", lidar_fov_rad)
    return RememberingPolicy(policy, layout, float(fov))
