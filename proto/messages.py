"""Every message curlnav services exchange, as typed dataclasses with ``encode``/``decode``.

All carry ``kind`` and ``v`` (schema version, 1 for all today). Units: metres, seconds, radians.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

import numpy as np

from .codec import ProtoError, check_header, dumps, field, loads, pack_array, unpack_array
from .frames import FrameBatch
from .rawbuf import KIND_PRIORITY_UPDATE, KIND_SAMPLED_BATCH, RawWriter, first_dim, read_raw

VERSION = 1
MAX_BEAMS = 4096
MAX_ITEMS = 65_536  # frames or transitions in one batch
MAX_ACTOR_ID = 128  # characters in an actor id (it is a key chunk and travels in every credit message)


def check_actor_id(actor_id: str, kind: str) -> str:
    """``actor_id`` if it is 1..``MAX_ACTOR_ID`` characters, else ``ProtoError``."""
    if not 0 < len(actor_id) <= MAX_ACTOR_ID:
        raise ProtoError("range", f"{kind}: actor_id must be 1..{MAX_ACTOR_ID} characters, not {len(actor_id)}")
    return actor_id


@dataclass
class TransitionBatch:
    """actor -> replay: frames and n-step transitions of one actor (its ``stream``).

    Arrays as ``replay.nstep.FrameBatch``: frames ``local_id``, ``prev_id`` (int64),
    ``ranges`` (float16, m, (F, beams)), ``labels`` (uint8, (F, beams)), ``goal`` (float32, (F, 3));
    transitions ``obs_id``, ``next_id`` (int64), ``action`` (float32, (T, 3)), ``reward``,
    ``discount`` (float32, (T,)); ``memory`` (float16, m, (F, M)), the network memory's ring of
    each frame, only where the run's network has a memory (``curlnav.memory``; the field is absent
    otherwise, so batches without one are those of before it). ``seq`` numbers the actor's
    batches (gaps reveal loss)."""

    actor_id: str
    seq: int
    weights_version: int
    batch: FrameBatch
    KIND = "transition_batch"

    def encode(self) -> bytes:
        b = self.batch
        return dumps({"kind": self.KIND, "v": VERSION, "actor_id": self.actor_id, "seq": self.seq,
                      "weights_version": self.weights_version,
                      **{name: pack_array(getattr(b, name)) for name in FRAME_FIELDS},
                      **({"memory": pack_array(b.memory)} if b.memory.shape[1] else {})})

    @staticmethod
    def decode(data: bytes, beams: int | None = None, memory_beams: int | None = None) -> TransitionBatch:
        """``beams``, ``memory_beams``: the run's (a batch of other shapes is refused); None: any."""
        obj = loads(data)
        kind = TransitionBatch.KIND
        check_header(obj, kind, VERSION)
        actor_id = check_actor_id(field(obj, "actor_id", str, kind), kind)
        seq = field(obj, "seq", int, kind)
        version = field(obj, "weights_version", int, kind)
        f, t = _dim(obj, "local_id", 0), _dim(obj, "obs_id", 0)
        if f > MAX_ITEMS or t > MAX_ITEMS:
            raise ProtoError("shape", f"{f} frames / {t} transitions exceed {MAX_ITEMS}")
        nb = _dim(obj, "ranges", 1)
        if beams is not None and nb != beams:
            raise ProtoError("shape", f"ranges have {nb} beams, this run uses {beams}")
        if not 0 < nb <= MAX_BEAMS:
            raise ProtoError("shape", f"bad beam count {nb}")
        shapes = {"local_id": ("<i8", (f,)), "prev_id": ("<i8", (f,)), "ranges": ("<f2", (f, nb)),
                  "labels": ("|u1", (f, nb)), "goal": ("<f4", (f, 3)), "obs_id": ("<i8", (t,)),
                  "next_id": ("<i8", (t,)), "action": ("<f4", (t, 3)), "reward": ("<f4", (t,)),
                  "discount": ("<f4", (t,))}
        nm = _dim(obj, "memory", 1) if "memory" in obj else 0
        if memory_beams is not None and nm != memory_beams:
            raise ProtoError("shape", f"the memory's ring has {nm} sectors, this run's network reads {memory_beams}")
        if not 0 <= nm <= MAX_BEAMS:
            raise ProtoError("shape", f"bad memory sector count {nm}")
        if nm:
            shapes["memory"] = ("<f2", (f, nm))
        arrays = {name: unpack_array(obj.get(name), name, dt, shape) for name, (dt, shape) in shapes.items()}
        if t and (arrays["discount"].min() < 0 or arrays["discount"].max() > 1):
            raise ProtoError("range", "discount outside [0, 1]")
        return TransitionBatch(actor_id, seq, version, FrameBatch(**arrays))


def _dim(obj: dict, name: str, axis: int) -> int:
    """Dimension ``axis`` of array field ``name``, checked to be a non-negative int."""
    record = obj.get(name)
    shape = record.get("shape") if isinstance(record, dict) else None
    if not isinstance(shape, list) or len(shape) <= axis or not isinstance(shape[axis], int) or shape[axis] < 0:
        raise ProtoError("shape", f"{name} has no valid shape")
    return shape[axis]


FRAME_FIELDS = ("local_id", "prev_id", "ranges", "labels", "goal", "obs_id", "next_id", "action", "reward", "discount")


@dataclass
class SampleRequest:
    """learner -> replay (query payload): ``batch_size`` transitions, waiting at most
    ``timeout_s`` on the rate limiter."""

    batch_size: int
    timeout_s: float = 1.0
    KIND = "sample_request"

    def encode(self) -> bytes:
        return dumps({"kind": self.KIND, "v": VERSION, "batch_size": self.batch_size, "timeout_s": self.timeout_s})

    @staticmethod
    def decode(data: bytes) -> SampleRequest:
        obj = loads(data)
        check_header(obj, SampleRequest.KIND, VERSION)
        size = field(obj, "batch_size", int, SampleRequest.KIND)
        timeout = float(field(obj, "timeout_s", (int, float), SampleRequest.KIND))
        if not 1 <= size <= 8192 or not 0 <= timeout <= 60:
            raise ProtoError("range", "batch_size must be 1..8192 and timeout_s 0..60")
        return SampleRequest(size, timeout)


@dataclass
class SampledBatch:
    """replay -> learner (query reply): a sampled batch as frames, in raw contiguous buffers
    (``rawbuf.py``): for the observation and the next observation, the ranges (float16, m,
    (B, range_frames, beams)), labels (uint8, (B, label_frames, beams)) and goal frames
    (float32, (B, goal_frames, 3)) of their history, oldest first; ``action`` (float32, (B, 3)),
    ``reward``, ``discount`` (float32, (B,)), ``keys`` (int64, (B,)) and ``probabilities``
    (float32, (B,): each item's probability of being drawn); ``obs_memory``, ``next_memory``
    (float16, m, (B, memory_beams)) only where the layout has a memory. The stacked float32 observation is
    ``obs()`` (or built on the learner's device from the frames: fewer bytes to copy)."""

    obs_ranges: np.ndarray
    obs_labels: np.ndarray
    obs_goal: np.ndarray
    next_ranges: np.ndarray
    next_labels: np.ndarray
    next_goal: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    keys: np.ndarray
    probabilities: np.ndarray
    obs_memory: np.ndarray | None = None  # float16 (B, M): the memory's ring, where the network has one
    next_memory: np.ndarray | None = None
    KIND = "sampled_batch"
    VERSION = 3  # 2: msgpack, stacked float16 observations; 3: raw buffers, frames
    MAX_BATCH = 8192
    FIELDS = ("obs_ranges", "obs_labels", "obs_goal", "next_ranges", "next_labels", "next_goal", "action", "reward",
              "discount", "keys", "probabilities")

    @staticmethod
    def schema(batch: int, layout, action_size: int = 3) -> dict[str, tuple[str, tuple[int, ...]]]:
        """``name -> (dtype, shape)`` for ``batch`` items of ``layout`` (an ``ObservationLayout``)."""
        frames = {"ranges": ("<f2", (batch, layout.range_frames, layout.beams)),
                  "labels": ("|u1", (batch, layout.label_frames, layout.beams)),
                  "goal": ("<f4", (batch, layout.goal_frames, 3))}
        memory = getattr(layout, "memory_beams", 0)
        ring = ({"obs_memory": ("<f2", (batch, memory)), "next_memory": ("<f2", (batch, memory))} if memory else {})
        return {**{f"obs_{k}": v for k, v in frames.items()}, **{f"next_{k}": v for k, v in frames.items()},
                "action": ("<f4", (batch, action_size)), "reward": ("<f4", (batch,)), "discount": ("<f4", (batch,)),
                "keys": ("<i8", (batch,)), "probabilities": ("<f4", (batch,)), **ring}

    @staticmethod
    def writer(batch: int, layout, action_size: int = 3, buffer=None) -> RawWriter:
        """An empty message whose arrays (``writer.view(name)``) a replay gathers into."""
        return RawWriter(KIND_SAMPLED_BATCH, SampledBatch.VERSION, SampledBatch.schema(batch, layout, action_size),
                         buffer)

    def encode(self) -> bytearray:
        layout = _FrameDims(self.obs_ranges.shape[2], self.obs_ranges.shape[1], self.obs_labels.shape[1],
                            self.obs_goal.shape[1], 0 if self.obs_memory is None else self.obs_memory.shape[1])
        w = SampledBatch.writer(len(self.keys), layout, self.action.shape[1])
        for name in self.present():
            w.view(name)[...] = getattr(self, name)
        return w.payload()

    @staticmethod
    def decode(data: bytes | bytearray | memoryview, layout, action_size: int = 3) -> SampledBatch:
        """Check ``data`` against ``layout``'s frame shapes (any batch size 1..``MAX_BATCH``) and
        return read-only views into it. Rewards, discounts and probabilities are checked for
        range; the frames were checked by the replay when they were inserted."""
        batch = first_dim(data)
        if not 1 <= batch <= SampledBatch.MAX_BATCH:
            raise ProtoError("shape", f"a batch of {batch} items (1..{SampledBatch.MAX_BATCH})")
        arrays = read_raw(data, KIND_SAMPLED_BATCH, SampledBatch.VERSION,
                          SampledBatch.schema(batch, layout, action_size), SampledBatch.KIND)
        small = np.concatenate([arrays["reward"], arrays["discount"], arrays["probabilities"]])
        if not np.isfinite(small).all():
            raise ProtoError("non_finite", "reward, discount or probabilities contain NaN or infinity")
        if (arrays["discount"] < 0).any() or (arrays["discount"] > 1).any() or (arrays["probabilities"] < 0).any():
            raise ProtoError("range", "discount outside [0, 1] or a negative probability")
        return SampledBatch(**arrays)

    def present(self) -> tuple[str, ...]:
        """The names of the arrays this batch carries (the memory's only where it has one)."""
        return self.FIELDS + (("obs_memory", "next_memory") if self.obs_memory is not None else ())

    @staticmethod
    def stack(ranges: np.ndarray, labels: np.ndarray, goal: np.ndarray, memory: np.ndarray | None = None) -> np.ndarray:
        """Frames into stacked float32 observations (B, size): ranges, labels, the memory's ring
        (where there is one), goals."""
        b = len(ranges)
        r, lab = ranges[0].size, labels[0].size
        m = 0 if memory is None else memory.shape[1]
        out = np.empty((b, r + lab + m + goal[0].size), np.float32)
        out[:, :r] = ranges.reshape(b, -1)
        out[:, r:r + lab] = labels.reshape(b, -1)
        if m:
            out[:, r + lab:r + lab + m] = memory
        out[:, r + lab + m:] = goal.reshape(b, -1)
        return out

    def split(self, parts: int) -> list[SampledBatch]:
        """``parts`` batches of equal size (views, no copy): one reply that carried several of the
        learner's batches (``SampleFeed``'s ``batches_per_request``)."""
        size = len(self.keys)
        if parts < 1 or size % parts:
            raise ValueError(f"a batch of {size} items does not split into {parts} equal parts")
        step = size // parts
        return [SampledBatch(**{n: getattr(self, n)[i * step:(i + 1) * step] for n in self.present()})
                for i in range(parts)]

    def obs(self) -> np.ndarray:
        return self.stack(self.obs_ranges, self.obs_labels, self.obs_goal, self.obs_memory)

    def next_obs(self) -> np.ndarray:
        return self.stack(self.next_ranges, self.next_labels, self.next_goal, self.next_memory)


@dataclass(frozen=True)
class _FrameDims:
    beams: int
    range_frames: int
    label_frames: int
    goal_frames: int
    memory_beams: int = 0


@dataclass
class PriorityUpdate:
    """learner -> replay: new priorities (the items' critic losses) for sampled keys, when the
    replay is prioritized, in raw buffers like ``SampledBatch``; a learner sends the keys of
    several updates in one message. Keys that left the table meanwhile are ignored."""

    keys: np.ndarray  # int64 (B,)
    priorities: np.ndarray  # float32 (B,), positive
    KIND = "priority_update"
    VERSION = 2  # 1: msgpack; 2: raw buffers

    @staticmethod
    def schema(n: int) -> dict[str, tuple[str, tuple[int, ...]]]:
        return {"keys": ("<i8", (n,)), "priorities": ("<f4", (n,))}

    def encode(self) -> bytearray:
        w = RawWriter(KIND_PRIORITY_UPDATE, self.VERSION, self.schema(len(self.keys)))
        w.view("keys")[...] = self.keys
        w.view("priorities")[...] = self.priorities
        return w.payload()

    @staticmethod
    def merge(updates: list[PriorityUpdate]) -> PriorityUpdate:
        """Several updates as one message (a key sampled twice keeps its latest priority:
        the replay applies them in order)."""
        return PriorityUpdate(np.concatenate([u.keys for u in updates]),
                              np.concatenate([u.priorities for u in updates]))

    @staticmethod
    def decode(data: bytes | bytearray | memoryview) -> PriorityUpdate:
        b = first_dim(data)
        if not 0 < b <= MAX_ITEMS:
            raise ProtoError("size", f"priority_update of {b} items (1..{MAX_ITEMS})")
        arrays = read_raw(data, KIND_PRIORITY_UPDATE, PriorityUpdate.VERSION, PriorityUpdate.schema(b),
                          PriorityUpdate.KIND)
        priorities = arrays["priorities"]
        if not (np.isfinite(priorities).all() and (priorities > 0).all()):
            raise ProtoError("non_finite", "priorities must be finite and positive")
        return PriorityUpdate(arrays["keys"], priorities)


@dataclass
class RunConfig:
    """every service -> any service (query reply): the experiment config a service runs with.
    A service joining a run compares hashes and refuses to join on a difference."""

    role: str
    instance: str
    config_hash: str  # sha256 hex of the config's canonical JSON
    config_json: str  # the config itself, to name the fields that differ
    KIND = "run_config"

    def encode(self) -> bytes:
        return dumps({"kind": self.KIND, "v": VERSION, "role": self.role, "instance": self.instance,
                      "config_hash": self.config_hash, "config_json": self.config_json})

    @staticmethod
    def decode(data: bytes) -> RunConfig:
        obj = loads(data)
        check_header(obj, RunConfig.KIND, VERSION)
        return RunConfig(*(field(obj, name, str, RunConfig.KIND) for name in ("role", "instance", "config_hash",
                                                                              "config_json")))


@dataclass
class Weights:
    """learner -> actors: the actor network's weights as a safetensors blob, with its version
    (learner updates at export) and a JSON-able description of the network."""

    version: int
    learner_steps: int
    safetensors: bytes
    d4pg_config: dict
    KIND = "weights"

    def encode(self) -> bytes:
        return dumps({"kind": self.KIND, "v": VERSION, "version": self.version, "learner_steps": self.learner_steps,
                      "safetensors": self.safetensors, "d4pg_config": self.d4pg_config})

    @staticmethod
    def decode(data: bytes) -> Weights:
        obj = loads(data)
        check_header(obj, Weights.KIND, VERSION)
        blob = field(obj, "safetensors", bytes, Weights.KIND)
        return Weights(field(obj, "version", int, Weights.KIND), field(obj, "learner_steps", int, Weights.KIND), blob,
                       field(obj, "d4pg_config", dict, Weights.KIND))


def _encode_flat(msg) -> bytes:
    """A message whose fields are all scalars, as one msgpack map."""
    return dumps({"kind": msg.KIND, "v": VERSION, **{name: getattr(msg, name) for name in msg.FIELD_TYPES}})


def _decode_flat(cls, data: bytes):
    """Check every field of ``cls.FIELD_TYPES`` (a float field also takes an int)."""
    return _flat_fields(cls, loads(data))


def _flat_fields(cls, obj: dict):
    """``_decode_flat`` of a message already unpacked."""
    check_header(obj, cls.KIND, VERSION)
    values = {}
    for name, kind in cls.FIELD_TYPES.items():
        value = field(obj, name, (int, float) if kind is float else kind, cls.KIND)
        values[name] = float(value) if kind is float else value
    return cls(**values)


#: at most this many roles in an ``EpisodeReport``'s ``control_steps``, each name this long
MAX_CONTROL_ROLES = 16
MAX_ROLE_NAME = 40
ROLE_NAME = re.compile(rf"[a-z0-9][a-z0-9_-]{{0,{MAX_ROLE_NAME - 1}}}")


def check_control_steps(value: Any, kind: str, steps: int) -> dict[str, int]:
    """An episode's control steps by chooser (role -> steps): at most ``MAX_CONTROL_ROLES`` names
    as the registry spells its entries (``ROLE_NAME``), counts whole numbers summing to the
    episode's ``steps``; else ``ProtoError``."""
    if not isinstance(value, dict):
        raise ProtoError("field", f"{kind}.control_steps has type {type(value).__name__}")
    if len(value) > MAX_CONTROL_ROLES:
        raise ProtoError("range", f"{kind}.control_steps names {len(value)} roles (at most {MAX_CONTROL_ROLES})")
    for role, count in value.items():
        if not isinstance(role, str) or not ROLE_NAME.fullmatch(role):
            raise ProtoError("range", f"{kind}.control_steps: a role is 1..{MAX_ROLE_NAME} characters of a-z, 0-9, - "
                                      f"and _")
        if not isinstance(count, int) or isinstance(count, bool) or count < 0:
            raise ProtoError("range", f"{kind}.control_steps[{role!r}] must be a whole number >= 0")
    if value and sum(value.values()) != steps:
        raise ProtoError("range", f"{kind}.control_steps sum to {sum(value.values())}, not the episode's {steps} steps")
    return dict(value)


@dataclass
class EpisodeReport:
    """actor -> scheduler: one finished episode. ``control_steps``: its steps by the part of the
    training stack that chose them (``curlnav.nav.roles.chooser``; optional on the wire)."""

    actor_id: str
    world: str
    pair: str
    success: bool
    episode_return: float
    base_collisions: int
    end_effector_collisions: int
    steps: int
    weights_version: int
    assignment_epoch: int
    control_steps: dict = dc_field(default_factory=dict)
    KIND = "episode_report"

    FIELD_TYPES = {"actor_id": str, "world": str, "pair": str, "success": bool, "episode_return": float,
                   "base_collisions": int, "end_effector_collisions": int, "steps": int, "weights_version": int,
                   "assignment_epoch": int}

    def encode(self) -> bytes:
        check_control_steps(self.control_steps, self.KIND, self.steps)
        return dumps({"kind": self.KIND, "v": VERSION, **{name: getattr(self, name) for name in self.FIELD_TYPES},
                      **({"control_steps": self.control_steps} if self.control_steps else {})})

    @staticmethod
    def decode(data: bytes) -> EpisodeReport:
        obj = loads(data)
        report = _flat_fields(EpisodeReport, obj)
        check_actor_id(report.actor_id, EpisodeReport.KIND)
        if "control_steps" in obj:
            report.control_steps = check_control_steps(obj["control_steps"], EpisodeReport.KIND, report.steps)
        return report


@dataclass
class AssignmentRequest:
    """actor -> scheduler (query payload): which world and pair next?"""

    actor_id: str
    KIND = "assignment_request"

    def encode(self) -> bytes:
        return dumps({"kind": self.KIND, "v": VERSION, "actor_id": self.actor_id})

    @staticmethod
    def decode(data: bytes) -> AssignmentRequest:
        obj = loads(data)
        check_header(obj, AssignmentRequest.KIND, VERSION)
        return AssignmentRequest(check_actor_id(field(obj, "actor_id", str, AssignmentRequest.KIND),
                                                AssignmentRequest.KIND))


@dataclass
class Assignment:
    """scheduler -> actor: the world (built-in name or YAML path visible to the actor) and the
    pair (name, or "" for a random pair) to train on; ``epoch`` rises at every advance."""

    actor_id: str
    world: str
    pair: str
    stage: str
    substep: int
    epoch: int
    KIND = "assignment"

    FIELD_TYPES = {"actor_id": str, "world": str, "pair": str, "stage": str, "substep": int, "epoch": int}

    def encode(self) -> bytes:
        return _encode_flat(self)

    @staticmethod
    def decode(data: bytes) -> Assignment:
        return _decode_flat(Assignment, data)


@dataclass
class ServiceStatus:
    """replay or learner -> scheduler, every second: numbers for ``/status``."""

    role: str
    values: dict = dc_field(default_factory=dict)  # name -> number
    KIND = "service_status"

    def encode(self) -> bytes:
        return dumps({"kind": self.KIND, "v": VERSION, "role": self.role, "values": self.values})

    @staticmethod
    def decode(data: bytes) -> ServiceStatus:
        obj = loads(data)
        check_header(obj, ServiceStatus.KIND, VERSION)
        values = field(obj, "values", dict, ServiceStatus.KIND)
        clean = {}
        for k, v in values.items():
            if not isinstance(k, str) or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ProtoError("field", f"service_status value {k!r} is not a finite number")
            clean[k] = v
        return ServiceStatus(field(obj, "role", str, ServiceStatus.KIND), clean)
