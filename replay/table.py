"""``ReplayTable``: n-step transitions over de-duplicated frames, FIFO, uniform or prioritised,
rate-limited, saved to and restored from disk without pickle.

Storage. Each env step's frame (241 ranges as float16, 241 labels as uint8, the goal frame as
3 float32, and the id of the previous frame of its episode) is stored once; an observation is
rebuilt by following the previous-frame links (4 range and label frames, 10 goal frames), so
no frame is stored four or ten times. Ranges are rounded to float16 (at most 4 mm at 10 m).
A transition holds two frame ids, its action, n-step reward and discount, a key, a priority.

Bytes per transition, with the default 1.25 frames of capacity per transition:
``1.25 * (241*2 + 241 + 3*4 + 8) + (8 + 8 + 3*4 + 4 + 4 + 8 + 8 + 4) = 985`` bytes, against
``2 * 1958 * 4 = 15,664`` bytes for storing the stacked float32 observation and next observation.

Eviction. Transitions leave first-in first-out when the table is full. Frames live in a ring
of ``frame_capacity``; when a frame a transition needs is overwritten, that transition is
evicted too (at the head, where the oldest frames are; rarely elsewhere, lazily at sampling).

Drops. A transition that names a frame the table cannot give it is not stored, and counted in
``dropped`` by reason (a transition inserted is stored or dropped, never neither):
``unknown_frame``, a writer id the table no longer remembers for that writer (it remembers the
last ``2 x insert_batch + history + 64`` of each); ``frame_overwritten``, a frame it remembers
but whose slot in the ring another writer has filled since (a writer silent for a whole ring).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from curlnav.layout import ObservationLayout
from curlnav.proto.messages import SampledBatch

from .nstep import FrameBatch

TRANSITION_BYTES_FIXED = 8 + 8 + 3 * 4 + 4 + 4 + 8 + 8 + 4
REPLAY_FILE_VERSION = 2  # 1: every slot of the rings; 2: only the frames and transitions held


class ReplayInputError(ValueError):
    """An insert was refused; ``reason`` is a short machine-readable cause for counters."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class RateLimiterTimeout(TimeoutError):
    """A blocking insert or sample waited longer than its timeout (Reverb's DeadlineExceeded)."""


class SampleToInsertRatio:
    """Keeps ``samples / inserts`` near ``samples_per_insert``, as Reverb's limiter of that name.

    Items, not calls, are counted. Below ``min_size_to_sample`` items in the table, inserts
    always pass and samples wait. From then on, with ``error = inserts * samples_per_insert -
    samples``, a call is allowed only if it keeps ``error`` inside
    ``[min_size_to_sample * spi - error_buffer, min_size_to_sample * spi + error_buffer]``.

    No deadlock: when neither an insert of ``insert`` items nor a sample of ``batch`` items is
    allowed, ``error > hi - spi * insert`` and ``error < lo + batch``, impossible when
    ``2 * error_buffer >= spi * insert + batch``; ``check_batch`` enforces that.

    Restore: the counters are not restored as saved (Reverb's known trap: a restored limiter can
    block sampling forever); ``recentre(size)`` sets ``error`` to the middle of the window.
    """

    def __init__(self, samples_per_insert: float, min_size_to_sample: int, error_buffer: float) -> None:
        if samples_per_insert <= 0 or not math.isfinite(samples_per_insert):
            raise ValueError("samples_per_insert must be positive")
        if min_size_to_sample < 1:
            raise ValueError("min_size_to_sample must be at least 1")
        if error_buffer < samples_per_insert:
            raise ValueError(f"error_buffer ({error_buffer}) must be at least samples_per_insert ({samples_per_insert})")
        self.samples_per_insert = float(samples_per_insert)
        self.min_size_to_sample = int(min_size_to_sample)
        self.error_buffer = float(error_buffer)
        self.inserts = 0
        self.samples = 0

    @staticmethod
    def unlimited(min_size_to_sample: int = 1) -> SampleToInsertRatio:
        return SampleToInsertRatio(1.0, min_size_to_sample, 1e18)

    @property
    def window(self) -> tuple[float, float]:
        centre = self.min_size_to_sample * self.samples_per_insert
        return centre - self.error_buffer, centre + self.error_buffer

    @property
    def error(self) -> float:
        return self.inserts * self.samples_per_insert - self.samples

    def check_batch(self, batch: int, insert: int = 1) -> None:
        """Raise unless samples of ``batch`` items and inserts of up to ``insert`` items can never
        both be refused."""
        if 2 * self.error_buffer < self.samples_per_insert * insert + batch:
            raise ValueError(f"error_buffer {self.error_buffer} too small for samples of {batch} beside inserts of "
                             f"{insert} at {self.samples_per_insert} samples per insert: inserts and samples could "
                             f"both block")

    def can_insert(self, size: int, n: int = 1) -> bool:
        if size < self.min_size_to_sample:
            return True
        return (self.inserts + n) * self.samples_per_insert - self.samples <= self.window[1]

    def can_sample(self, size: int, n: int) -> bool:
        if size < self.min_size_to_sample:
            return False
        return self.inserts * self.samples_per_insert - (self.samples + n) >= self.window[0]

    def recentre(self, size: int) -> None:
        self.inserts = size
        self.samples = int(size * self.samples_per_insert - self.min_size_to_sample * self.samples_per_insert)


@dataclass
class ReplaySample:
    """A sampled batch. ``obs`` and ``next_obs`` (float32, (B, layout.size)), ``action`` (B, 3),
    ``reward`` and ``discount`` (B,), ``keys`` (int64), ``probabilities`` (of being drawn),
    ``priorities``, ``times_sampled``."""

    keys: np.ndarray
    probabilities: np.ndarray
    priorities: np.ndarray
    times_sampled: np.ndarray
    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    next_obs: np.ndarray


def stack_frames(ranges: np.ndarray, labels: np.ndarray, goal: np.ndarray, memory: np.ndarray | None = None) -> np.ndarray:
    """Frames ((B, R, beams), (B, L, beams), (B, G, 3), the memory's ring (B, M) or None) into
    stacked float32 observations (B, size)."""
    return SampledBatch.stack(ranges, labels, goal, memory)  # one stacking, beside the wire schema


class ReplayTable:
    """See the module docstring. Thread-safe; ``insert`` and ``sample`` may block on the limiter."""

    def __init__(self, layout: ObservationLayout, max_size: int, rate_limiter: SampleToInsertRatio | None = None,
                 sampler: str = "uniform", priority_exponent: float = 0.6, frame_capacity: int | None = None,
                 seed: int = 0, action_size: int = 3, insert_batch: int = 64) -> None:
        if max_size < 1:
            raise ValueError("max_size must be at least 1")
        if sampler not in ("uniform", "prioritized"):
            raise ValueError(f"sampler must be 'uniform' or 'prioritized', got {sampler!r}")
        self.layout = layout
        self.max_size = int(max_size)
        self.sampler = sampler
        self.priority_exponent = float(priority_exponent)
        self.rate_limiter = rate_limiter or SampleToInsertRatio.unlimited()
        self.frame_capacity = int(frame_capacity or (self.max_size + self.max_size // 4 + 4 * 1024))
        self.action_size = action_size
        self._rng = np.random.default_rng(seed)
        self._cond = threading.Condition()
        beams = layout.beams
        fc = self.frame_capacity
        self._f_ranges = np.zeros((fc, beams), np.float16)
        self._f_labels = np.zeros((fc, beams), np.uint8)
        self._f_goal = np.zeros((fc, 3), np.float32)
        self._f_memory = np.zeros((fc, layout.memory_beams), np.float16)  # the ring of each frame (m)
        self._f_prev = np.zeros(fc, np.int64)
        self._next_frame = 0  # global id of the next frame
        n = self.max_size
        self._t_obs = np.zeros(n, np.int64)
        self._t_next = np.zeros(n, np.int64)
        self._t_action = np.zeros((n, action_size), np.float32)
        self._t_reward = np.zeros(n, np.float32)
        self._t_discount = np.zeros(n, np.float32)
        self._t_priority = np.zeros(n, np.float64)
        self._t_sampled = np.zeros(n, np.int64)
        self._first_key = 0  # key of the oldest live transition
        self._next_key = 0  # key of the next transition; slot = key % max_size
        self._max_priority = 1.0
        self._streams: dict[str, OrderedDict[int, int]] = {}
        # writer-local frame ids remembered per stream (an actor): a transition names frames up to
        # n-step steps back in each of the actor's environments, interleaved; with K environments
        # that is K x (n + 1) frames plus a batch, K x n below insert_batch (the config's check):
        # at most 2 x insert_batch + 64 frames back. 74 had been enough for one environment and
        # dropped transitions as unknown_frame with 8 (issue 31).
        self._stream_window = layout.history + 64 + 2 * int(insert_batch)
        self.rejected: dict[str, int] = {}  # inserts refused (nothing of them stored), by reason
        self.dropped: dict[str, int] = {}  # transitions of inserts not stored, by reason (module docstring)
        self.total_inserted = 0
        self.total_sampled = 0

    # -- properties ------------------------------------------------------------------------
    @property
    def size(self) -> int:
        return self._next_key - self._first_key

    @property
    def bytes_per_transition(self) -> float:
        beams = self.layout.beams
        frame = beams * 2 + beams + 3 * 4 + 8 + 2 * self.layout.memory_beams
        return self.frame_capacity / self.max_size * frame + TRANSITION_BYTES_FIXED + self.action_size * 4 - 12

    def info(self) -> dict:
        with self._cond:
            return {"size": self.size, "max_size": self.max_size, "total_inserted": self.total_inserted,
                    "total_sampled": self.total_sampled, "frames": min(self._next_frame, self.frame_capacity),
                    "rejected": dict(self.rejected), "dropped": dict(self.dropped), "sampler": self.sampler,
                    "bytes_per_transition": round(self.bytes_per_transition, 1),
                    "rate_limiter": {"inserts": self.rate_limiter.inserts, "samples": self.rate_limiter.samples,
                                     "samples_per_insert": self.rate_limiter.samples_per_insert,
                                     "min_size_to_sample": self.rate_limiter.min_size_to_sample}}

    # -- insert ----------------------------------------------------------------------------
    def _reject(self, reason: str, message: str) -> ReplayInputError:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return ReplayInputError(reason, message)

    def validate(self, batch: FrameBatch) -> None:
        """Raise ``ReplayInputError`` (and count it) unless ``batch`` has the table's shapes and
        only finite values."""
        beams = self.layout.beams
        f, t = batch.num_frames, batch.num_transitions
        shapes = {"prev_id": (f,), "ranges": (f, beams), "labels": (f, beams), "goal": (f, 3),
                  "memory": (f, self.layout.memory_beams),
                  "next_id": (t,), "action": (t, self.action_size), "reward": (t,), "discount": (t,)}
        for name, shape in shapes.items():
            value = getattr(batch, name)
            if not isinstance(value, np.ndarray) or value.shape != shape:
                got = getattr(value, "shape", type(value).__name__)
                raise self._reject("shape", f"{name} has shape {got}, expected {shape}")
        for name in ("ranges", "goal", "memory", "action", "reward", "discount"):
            if not np.all(np.isfinite(getattr(batch, name).astype(np.float64))):
                raise self._reject("non_finite", f"{name} contains NaN or infinity")
        if t and (np.any(batch.discount < 0) or np.any(batch.discount > 1)):
            raise self._reject("range", "discount outside [0, 1]")

    def insert(self, batch: FrameBatch, stream: str = "0", timeout: float | None = None, force: bool = False) -> int:
        """Add frames and transitions from one writer ``stream``; returns transitions added.

        Blocks while the rate limiter refuses inserts (``timeout`` seconds at most, then
        ``RateLimiterTimeout``; ``timeout=0`` never waits; ``force`` skips the limiter, for data
        already accepted upstream, at shutdown). Transitions that refer to frames
        the table does not hold are not stored: counted in ``dropped`` (``unknown_frame``,
        ``frame_overwritten``; the module docstring).
        """
        with self._cond:
            self.validate(batch)
            t = batch.num_transitions
            if t and not force:
                self._wait(lambda: self.rate_limiter.can_insert(self.size, t), timeout, "insert")
            ids = self._streams.setdefault(stream, OrderedDict())
            fc = self.frame_capacity
            for i in range(batch.num_frames):
                gid = self._next_frame
                self._next_frame += 1
                slot = gid % fc
                self._f_ranges[slot] = batch.ranges[i]
                self._f_labels[slot] = batch.labels[i]
                self._f_goal[slot] = batch.goal[i]
                self._f_memory[slot] = batch.memory[i]
                local = int(batch.local_id[i])
                self._f_prev[slot] = ids.get(int(batch.prev_id[i]), gid)
                ids[local] = gid
                if len(ids) > self._stream_window:
                    ids.popitem(last=False)
            self._evict_stale_head()
            added = 0
            oldest = self._oldest_frame()
            for i in range(t):
                obs = ids.get(int(batch.obs_id[i]))
                nxt = ids.get(int(batch.next_id[i]))
                reason = ("unknown_frame" if obs is None or nxt is None else
                          "frame_overwritten" if min(obs, nxt) < oldest else None)
                if reason is not None:
                    self.dropped[reason] = self.dropped.get(reason, 0) + 1
                    continue
                if self.size == self.max_size:
                    self._first_key += 1
                slot = self._next_key % self.max_size
                self._t_obs[slot] = obs
                self._t_next[slot] = nxt
                self._t_action[slot] = batch.action[i]
                self._t_reward[slot] = batch.reward[i]
                self._t_discount[slot] = batch.discount[i]
                self._t_priority[slot] = self._max_priority
                self._t_sampled[slot] = 0
                self._next_key += 1
                added += 1
            self.rate_limiter.inserts += added
            self.total_inserted += added
            self._cond.notify_all()
            return added

    def _oldest_frame(self) -> int:
        return max(0, self._next_frame - self.frame_capacity)

    def _evict_stale_head(self) -> None:
        oldest = self._oldest_frame()
        while self.size and self._t_obs[self._first_key % self.max_size] < oldest:
            self._first_key += 1

    def _wait(self, allowed, timeout: float | None, what: str) -> None:
        if allowed():
            return
        deadline = None if timeout is None else time.monotonic() + timeout
        while not allowed():
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise RateLimiterTimeout(f"rate limiter blocked {what} for {timeout} s "
                                         f"(size {self.size}, error {self.rate_limiter.error:.0f}, "
                                         f"window {self.rate_limiter.window})")
            self._cond.wait(remaining)

    # -- sample ----------------------------------------------------------------------------
    def can_sample(self, batch_size: int) -> bool:
        with self._cond:
            return self.rate_limiter.can_sample(self.size, batch_size)

    def can_insert(self, n: int = 1) -> bool:
        with self._cond:
            return self.rate_limiter.can_insert(self.size, n)

    def sample(self, batch_size: int, timeout: float | None = None) -> ReplaySample:
        """Draw ``batch_size`` transitions (with replacement); blocks on the rate limiter."""
        f = self.sample_frames(batch_size, timeout)
        return ReplaySample(keys=f["keys"], probabilities=f["probabilities"].astype(np.float64),
                           priorities=f["priorities"], times_sampled=f["times_sampled"],
                           obs=stack_frames(f["obs_ranges"], f["obs_labels"], f["obs_goal"], f.get("obs_memory")),
                           action=f["action"], reward=f["reward"], discount=f["discount"],
                           next_obs=stack_frames(f["next_ranges"], f["next_labels"], f["next_goal"], f.get("next_memory")))

    def frame_shapes(self, batch_size: int) -> dict[str, tuple[str, tuple[int, ...]]]:
        """``name -> (dtype, shape)`` of what ``sample_frames`` fills (``SampledBatch.schema``)."""
        return SampledBatch.schema(batch_size, self.layout, self.action_size)

    def sample_frames(self, batch_size: int, timeout: float | None = None,
                      out: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Draw ``batch_size`` transitions and gather them as frames, one vectorised gather per
        array, straight into ``out`` (arrays of ``frame_shapes``: the views of a message being
        built) or into new arrays. Also returns ``priorities`` and ``times_sampled``.

        The observation of an item is the history of its frame (``layout.history`` frames,
        oldest first, the episode's first frame repeated before it), as the environment
        stacked it; ranges, labels and goals take the newest ``range_frames``,
        ``label_frames`` and ``goal_frames`` of that history."""
        shapes = self.frame_shapes(batch_size)
        if out is None:
            out = {name: np.empty(shape, dtype) for name, (dtype, shape) in shapes.items()}
        with self._cond:
            self._wait(lambda: self.rate_limiter.can_sample(self.size, batch_size), timeout, "sample")
            slots = self._draw(batch_size)
            oldest = self._oldest_frame()
            stale = self._t_obs[slots] < oldest
            for _ in range(10):
                if not stale.any():
                    break
                self._t_priority[slots[stale]] = 0.0  # never drawn again by the prioritised sampler
                slots[stale] = self._draw(int(stale.sum()))
                stale = self._t_obs[slots] < oldest
            out["probabilities"][...] = self._probabilities(slots)
            self._t_sampled[slots] += 1
            self.rate_limiter.samples += batch_size
            self.total_sampled += batch_size
            for prefix, ids in (("obs_", self._t_obs[slots]), ("next_", self._t_next[slots])):
                self._gather_frames(self._history(ids, oldest), out, prefix)
            np.take(self._t_action, slots, axis=0, out=out["action"], mode="wrap")
            np.take(self._t_reward, slots, out=out["reward"], mode="wrap")
            np.take(self._t_discount, slots, out=out["discount"], mode="wrap")
            out["keys"][...] = self._first_key + ((slots - self._first_key) % self.max_size)
            out["priorities"] = self._t_priority[slots]
            out["times_sampled"] = self._t_sampled[slots]
            self._cond.notify_all()
        return out

    def _history(self, frame_ids: np.ndarray, oldest: int) -> np.ndarray:
        """Frame ids (B, history) of the observations ending at ``frame_ids``, oldest first."""
        h = self.layout.history
        hist = np.empty((len(frame_ids), h), np.int64)
        hist[:, h - 1] = ids = frame_ids
        for k in range(h - 2, -1, -1):
            prev = self._f_prev[ids % self.frame_capacity]
            ids = np.where(prev >= oldest, prev, ids)
            hist[:, k] = ids
        return hist

    def _observations(self, frame_ids: np.ndarray, oldest: int) -> np.ndarray:
        """Stacked float32 observations (B, size) ending at ``frame_ids``."""
        out = {name: np.empty(shape, dtype) for name, (dtype, shape) in self.frame_shapes(len(frame_ids)).items()}
        self._gather_frames(self._history(frame_ids, oldest), out, "obs_")
        return stack_frames(out["obs_ranges"], out["obs_labels"], out["obs_goal"], out.get("obs_memory"))

    def _gather_frames(self, hist: np.ndarray, out: dict[str, np.ndarray], prefix: str) -> None:
        lay = self.layout
        h = lay.history
        slots = hist % self.frame_capacity
        for name, store, count in (("ranges", self._f_ranges, lay.range_frames),
                                   ("labels", self._f_labels, lay.label_frames),
                                   ("goal", self._f_goal, lay.goal_frames)):
            np.take(store, slots[:, h - count:], axis=0, out=out[prefix + name], mode="wrap")
        if lay.memory_beams:  # the ring of the newest frame only
            np.take(self._f_memory, slots[:, h - 1], axis=0, out=out[prefix + "memory"], mode="wrap")

    def _live_slots(self) -> np.ndarray:
        return (self._first_key + np.arange(self.size)) % self.max_size

    def _draw(self, n: int) -> np.ndarray:
        size = self.size
        if self.sampler == "uniform":
            return (self._first_key + self._rng.integers(0, size, n)) % self.max_size
        live = self._live_slots()
        p = self._t_priority[live] ** self.priority_exponent
        total = p.sum()
        if total <= 0:
            return (self._first_key + self._rng.integers(0, size, n)) % self.max_size
        return live[self._rng.choice(size, n, p=p / total)]

    def _probabilities(self, slots: np.ndarray) -> np.ndarray:
        if self.sampler == "uniform":
            return np.full(len(slots), 1.0 / self.size)
        live = self._live_slots()
        total = (self._t_priority[live] ** self.priority_exponent).sum()
        return (self._t_priority[slots] ** self.priority_exponent) / max(total, 1e-300)

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> int:
        """Set priorities of live keys (stale keys are ignored); returns how many were set."""
        keys = np.asarray(keys, np.int64)
        priorities = np.asarray(priorities, np.float64)
        if keys.shape != priorities.shape:
            raise ValueError("keys and priorities must have the same shape")
        if not np.all(np.isfinite(priorities)) or np.any(priorities < 0):
            raise ValueError("priorities must be finite and non-negative")
        with self._cond:
            live = (keys >= self._first_key) & (keys < self._next_key)
            slots = keys[live] % self.max_size
            self._t_priority[slots] = priorities[live]
            if live.any():
                self._max_priority = max(self._max_priority, float(priorities[live].max()))
            return int(live.sum())

    # -- persistence -----------------------------------------------------------------------
    _FRAME_ARRAYS = ("f_ranges", "f_labels", "f_goal", "f_prev", "f_memory")
    _TRANSITION_ARRAYS = ("t_obs", "t_next", "t_action", "t_reward", "t_discount", "t_priority", "t_sampled")

    def _live_frame_slots(self) -> np.ndarray:
        """Ring slots of the frames still held, oldest first."""
        return np.arange(self._oldest_frame(), self._next_frame) % self.frame_capacity

    def save(self, path: str | Path) -> Path:
        """Write the table to ``path`` (a ``.npz`` of arrays plus JSON metadata, no pickle).

        Format version 2: only what the table holds (live frames oldest first, live transitions
        oldest first, with their priorities and sample counts), so the file grows with the
        content, not with the capacity; ``restore`` puts them back in their ring slots."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with self._cond:
            meta = {
                "format": "curlnav-replay", "version": REPLAY_FILE_VERSION, "layout": self.layout.to_dict(),
                "max_size": self.max_size, "frame_capacity": self.frame_capacity, "sampler": self.sampler,
                "priority_exponent": self.priority_exponent, "action_size": self.action_size,
                "next_frame": self._next_frame, "first_key": self._first_key, "next_key": self._next_key,
                "max_priority": self._max_priority, "total_inserted": self.total_inserted,
                "total_sampled": self.total_sampled, "rejected": self.rejected, "dropped": self.dropped,
                "streams": {name: [[k, v] for k, v in ids.items()] for name, ids in self._streams.items()},
            }
            frames, slots = self._live_frame_slots(), self._live_slots()
            arrays = {name: getattr(self, "_" + name)[frames] for name in self._FRAME_ARRAYS}
            arrays.update({name: getattr(self, "_" + name)[slots] for name in self._TRANSITION_ARRAYS})
            tmp = path.with_name(path.name + ".tmp.npz")
            np.savez(tmp, meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
            tmp.replace(path)
        return path

    @classmethod
    def restore(cls, path: str | Path, rate_limiter: SampleToInsertRatio | None = None, seed: int = 0) -> ReplayTable:
        """Load a table written by ``save`` (format version 2, or 1: the whole capacity) into a
        table of the saved capacity. The limiter is re-centred (see ``SampleToInsertRatio``)."""
        with np.load(Path(path), allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            version = meta.get("version")
            if meta.get("format") != "curlnav-replay" or version not in (1, REPLAY_FILE_VERSION):
                raise ValueError(f"{path}: not a curlnav replay file (format version 1 or {REPLAY_FILE_VERSION}, "
                                 f"found {meta.get('format')!r} version {version!r})")
            table = cls(ObservationLayout(**meta["layout"]), meta["max_size"], rate_limiter, meta["sampler"],
                        meta["priority_exponent"], meta["frame_capacity"], seed, meta["action_size"])
            table._next_frame = meta["next_frame"]
            table._first_key = meta["first_key"]
            table._next_key = meta["next_key"]
            if version == 1:  # every slot of the rings, as they were
                frames = slots = slice(None)
            else:
                frames, slots = table._live_frame_slots(), table._live_slots()
            for names, where in ((cls._FRAME_ARRAYS, frames), (cls._TRANSITION_ARRAYS, slots)):
                for name in names:
                    target = getattr(table, "_" + name)
                    if name == "f_memory" and name not in data.files and not target.shape[1]:
                        continue  # a file from before the network's memory, of a layout without one
                    saved = data[name]
                    expected = (target.shape[0] if isinstance(where, slice) else len(where),) + target.shape[1:]
                    if saved.shape != expected:
                        raise ValueError(f"{path}: {name} has shape {saved.shape}, its metadata says {expected} "
                                         "(a damaged replay file)")
                    target[where] = saved
        table._max_priority = meta["max_priority"]
        table.total_inserted = meta["total_inserted"]
        table.total_sampled = meta["total_sampled"]
        table.rejected = dict(meta["rejected"])
        legacy = table.rejected.pop("unknown_frame", 0)  # files from before issue 35 counted drops as refusals
        table.dropped = dict(meta.get("dropped", {"unknown_frame": legacy} if legacy else {}))
        table._streams = {name: OrderedDict((int(k), int(v)) for k, v in pairs) for name, pairs in meta["streams"].items()}
        table.rate_limiter.recentre(table.size)
        return table
