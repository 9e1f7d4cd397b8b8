"""The network's memory: recent scans kept in the robot's odometry frame, read as a ring.

A frame stack of four scans (0.8 s) forgets a dead end as soon as the robot turns its LiDAR
away from it, so a network that turns round in a U-shaped wall turns back into it (issue 53:
the network alone 0 % on such a map, the rescue, which keeps a scan map, 100 %). ``ScanMemory``
gives the network what the rescue knows, in a form an MLP reads cheaply:

- every ``memory_stride``-th scan, the returns of beams labelled static (``label < 0.5``) that
  hit something (``range < max_range``) are kept as points in the **odometry frame**, the
  robot's own pose estimate (``info["odometry"]`` in the simulator, ``/odom`` on a robot), so
  the memory drifts as the robot's odometry does;
- a point is kept ``memory_steps`` control steps (30 s at 5 Hz by default), then forgotten:
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

from curlnav.layout import ObservationLayout, beam_angles

__all__ = ["ScanMemory", "MemoryObserver", "RememberingPolicy", "newest_scan", "with_ring", "policy_layout", "remembering"]

#: keep every second beam's return as a point: 0.5 deg at 241 beams over 240 deg, finer than the
#: ring's sectors (5 deg at 72), and half the points to transform at each step
POINT_BEAM_STEP = 2


class ScanMemory:
    """Remembered static returns of one robot, as the module docstring says. ``add`` a scan
    each control step (the memory keeps every ``memory_stride``-th), ``ring`` to read it."""

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
        slots = max(1, math.ceil(layout.memory_steps / layout.memory_stride))
        self._x = np.full((slots, len(self._keep)), np.nan)
        self._y = np.full((slots, len(self._keep)), np.nan)
        self._steps = 0

    def reset(self) -> None:
        """Forget everything (a new episode)."""
        self._x.fill(np.nan)
        self._y.fill(np.nan)
        self._steps = 0

    def add(self, ranges: np.ndarray, labels: np.ndarray, pose: tuple[float, float, float]) -> None:
        """One control step's scan (``ranges`` (beams,) m, ``labels`` (beams,), 1 = movable),
        seen from ``pose`` (x m, y m, yaw rad in the odometry frame)."""
        step = self._steps
        self._steps += 1
        if step % self.stride:
            return
        slot = (step // self.stride) % len(self._x)
        r = np.asarray(ranges, np.float64)[self._keep]
        hit = np.isfinite(r) & (r < self.layout.max_range - 1e-3) & (np.asarray(labels)[self._keep] < 0.5)
        x, y, yaw = pose
        a = self._angles + yaw
        self._x[slot] = np.where(hit, x + r * np.cos(a), np.nan)
        self._y[slot] = np.where(hit, y + r * np.sin(a), np.nan)

    def ring(self, pose: tuple[float, float, float]) -> np.ndarray:
        """``(memory_beams,)`` float32: the distance (m) to the nearest remembered point in each
        sector round ``pose``, at most ``memory_range``."""
        out = np.full(self.sectors, self.range_m)
        held = np.isfinite(self._x)
        if not held.any():
            return out.astype(np.float32)
        x, y, yaw = pose
        dx, dy = self._x[held] - x, self._y[held] - y
        c, s = math.cos(yaw), math.sin(yaw)
        ahead, left = c * dx + s * dy, -s * dx + c * dy
        distance = np.hypot(ahead, left)
        near = distance < self.range_m
        bearing = np.arctan2(left[near], ahead[near])
        sector = np.floor((bearing + math.pi + self._sector_width / 2) / self._sector_width).astype(np.int64) % self.sectors
        np.minimum.at(out, sector, distance[near])
        return out.astype(np.float32)

    def update(self, observation: np.ndarray, pose: tuple[float, float, float]) -> np.ndarray:
        """``add`` the newest scan of ``observation`` (the environment's, without a ring) seen
        from ``pose`` and return the ``ring`` round it."""
        ranges, labels = newest_scan(self.layout, observation)
        self.add(ranges, labels, pose)
        return self.ring(pose)


def newest_scan(layout: ObservationLayout, observation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The newest ranges and labels of an observation with or without its ring."""
    b = layout.beams
    r_end = layout.range_frames * b
    l_end = r_end + layout.label_frames * b
    labels = observation[l_end - b:l_end] if layout.label_frames else np.zeros(b, np.float32)
    return observation[r_end - b:r_end], labels


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
        pose = info.get("odometry") or info.get("pose")
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
