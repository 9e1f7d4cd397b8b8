"""The learner's feed: sampled batches from the replay service, several requests in flight, a
prefetch queue, and batches assembled straight into tensors on the learner's device.

Reverb's design, in Zenoh terms: a sampler keeps ``in_flight`` ``replay/sample`` queries
outstanding (Reverb's ``max_in_flight_samples_per_worker``), so the replay gathers the next batch
while this one travels and the learner steps; each reply (a raw ``SampledBatch``: frames, not
stacked observations, about 1.5 MB for 256 transitions of the default layout) is checked
(dtypes, shapes, sizes; a malformed one is counted by reason and dropped) and turned into a
``TensorBatch`` before it enters the queue, so the SGD step only takes it.

``BatchAssembler`` does the last part: on CPU it writes the float32 observations in place (one
copy from the frames); on CUDA the raw frames (float16 ranges, uint8 labels: 2.6x fewer bytes
than float32 observations) go through pinned staging buffers with asynchronous copies and the
observations are stacked on the GPU.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import warnings
from collections import deque

import numpy as np
import torch

from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import SampledBatch, SampleRequest

from .d4pg import TensorBatch

log = logging.getLogger("curlnav.learner")



def _tensor(a: np.ndarray) -> torch.Tensor:
    """A tensor over ``a`` without a copy; received frames are read-only views of the reply,
    only ever copied from (torch warns about read-only arrays)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.from_numpy(a)


def resolve_device(name: str = "auto") -> torch.device:
    """``auto``: CUDA when a GPU is present, else CPU; ``cuda`` without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device cuda asked for, but torch sees no CUDA device (torch.cuda.is_available() is False)")
    return device


def describe_device(device: torch.device) -> str:
    """One line naming the device the learner runs on."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        props = torch.cuda.get_device_properties(index)
        return (f"learner device: cuda:{index} ({props.name}, {props.total_memory / 2**30:.0f} GiB), pinned host "
                f"memory, asynchronous copies")
    why = "no CUDA device present" if not torch.cuda.is_available() else "cpu asked for"
    return f"learner device: cpu ({why}; torch threads {torch.get_num_threads()})"


class BatchAssembler:
    """``SampledBatch`` -> ``TensorBatch`` on ``device`` (float32 observations (B, size))."""

    def __init__(self, device: torch.device, staging: int = 4) -> None:
        self.device = device
        self.cuda = device.type == "cuda"
        self._staging: list[tuple[dict[str, torch.Tensor], torch.cuda.Event]] = []
        self._slots = staging
        self._next = 0

    def _stage(self, shapes: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """Raw arrays into a ring of pinned buffers, then asynchronously onto the GPU."""
        if not self._staging or any(self._staging[0][0][n].shape != a.shape for n, a in shapes.items()):
            self._staging = [({n: torch.empty(a.shape, dtype=torch.from_numpy(a[:0].copy()).dtype, pin_memory=True)
                               for n, a in shapes.items()}, torch.cuda.Event()) for _ in range(self._slots)]
        pinned, done = self._staging[self._next]
        self._next = (self._next + 1) % self._slots
        done.synchronize()  # the copies out of this slot's previous batch have finished
        out = {}
        for n, a in shapes.items():
            pinned[n].copy_(_tensor(a))
            out[n] = pinned[n].to(self.device, non_blocking=True)
        done.record()
        return out

    @staticmethod
    def _stack(ranges: torch.Tensor, labels: torch.Tensor, goal: torch.Tensor, device,
               memory: torch.Tensor | None = None) -> torch.Tensor:
        """Frames into float32 observations: ranges, labels, the memory's ring (if any), goals."""
        b = ranges.shape[0]
        r, lab = ranges[0].numel(), labels[0].numel()
        m = 0 if memory is None else memory.shape[1]
        obs = torch.empty((b, r + lab + m + goal[0].numel()), dtype=torch.float32, device=device)
        obs[:, :r].copy_(ranges.reshape(b, -1))
        obs[:, r:r + lab].copy_(labels.reshape(b, -1))
        if m:
            obs[:, r + lab:r + lab + m].copy_(memory)
        obs[:, r + lab + m:].copy_(goal.reshape(b, -1))
        return obs

    def __call__(self, batch: SampledBatch | dict[str, np.ndarray], weights: np.ndarray | None = None) -> TensorBatch:
        """``batch``: a decoded message, or ``ReplayTable.sample_frames``' arrays (in one process)."""
        names = SampledBatch.FIELDS + ("obs_memory", "next_memory")
        arrays = {n: batch.get(n) if isinstance(batch, dict) else getattr(batch, n) for n in names}
        arrays = {n: a for n, a in arrays.items() if a is not None}  # the ring's only where there is one
        if self.cuda:
            t = self._stage(arrays)
        else:
            t = {n: _tensor(a) for n, a in arrays.items()}
        dev = self.device

        def f32(x: torch.Tensor) -> torch.Tensor:
            return x.to(dev, torch.float32, copy=True)  # a copy: decoded arrays are read-only

        return TensorBatch(self._stack(t["obs_ranges"], t["obs_labels"], t["obs_goal"], dev, t.get("obs_memory")),
                           f32(t["action"]), f32(t["reward"]), f32(t["discount"]),
                           self._stack(t["next_ranges"], t["next_labels"], t["next_goal"], dev, t.get("next_memory")),
                           None if weights is None else torch.as_tensor(weights, dtype=torch.float32).to(dev))


class SampleFeed:
    """Batches from the replay's ``replay/sample`` queryable, ``in_flight`` queries outstanding,
    up to ``depth`` decoded batches waiting in the queue.

    ``batches_per_request`` (k): each query asks for ``k * batch_size`` transitions and the reply
    is split into k batches (views of it), so the per-query costs (the query's routing, the
    replay's locking and message header, the reply's allocation) are paid once per k batches; the
    k batches are independent draws like any others (uniform or by priority, with replacement).

    ``get(timeout)`` -> ``(SampledBatch, TensorBatch | None)`` (the tensor batch when an
    ``assembler`` was given), or ``None`` on timeout. ``rejected`` counts refused replies by
    reason (``ProtoError`` reasons); ``errors`` counts error replies (rate limited, not ready).
    ``payload_shm`` counts replies that came through Zenoh shared memory."""

    def __init__(self, session, key: str, batch_size: int, layout, in_flight: int = 4, depth: int = 4,
                 assembler: BatchAssembler | None = None, request_timeout_s: float = 0.1,
                 on_reject=None, batches_per_request: int = 1) -> None:
        self.session, self.key, self.layout = session, key, layout
        self.batch_size = batch_size
        self.in_flight = max(1, in_flight)
        self.assembler = assembler
        if not 1 <= batches_per_request * batch_size <= SampledBatch.MAX_BATCH:
            raise ValueError(f"batches_per_request x batch_size = {batches_per_request * batch_size}: must be "
                             f"1..{SampledBatch.MAX_BATCH} transitions per request")
        self.per_request = batches_per_request
        self.request = SampleRequest(batch_size * batches_per_request, timeout_s=request_timeout_s).encode()
        self.ready: queue.Queue = queue.Queue(maxsize=max(1, depth))
        self.rejected: dict[str, int] = {}
        self.errors = 0
        self.requested = 0
        self.unanswered = 0  # queries that ended without any reply (timed out on the way)
        self.received = 0
        self.payload_shm = 0
        self.on_reject = on_reject
        self.stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="sample-feed")

    def start(self) -> SampleFeed:
        self._thread.start()
        return self

    def close(self, timeout: float = 10.0) -> None:
        self.stop.set()
        self._thread.join(timeout)

    def get(self, timeout: float | None = None):
        try:
            return self.ready.get(timeout=timeout)
        except queue.Empty:
            return None

    def _ask(self):
        self.requested += 1
        return self.session.get(self.key, payload=self.request, timeout=5.0)

    def decode(self, payload) -> list[tuple[SampledBatch, TensorBatch | None]] | None:
        """One reply's payload (a ``ZBytes``) into checked batches (``batches_per_request`` of
        them); ``None`` when refused."""
        shm = payload.as_shm() if hasattr(payload, "as_shm") else None
        try:
            if shm is not None:
                data = bytes(shm)  # one copy out of the shared segment (ZShm has no buffer interface)
                self.payload_shm += 1
            else:
                data = payload.to_bytes() if hasattr(payload, "to_bytes") else payload
            batch = SampledBatch.decode(data, self.layout)
            if len(batch.keys) != self.batch_size * self.per_request:
                raise ProtoError("shape", f"a reply of {len(batch.keys)} transitions to a request for "
                                          f"{self.batch_size * self.per_request}")
        except ProtoError as exc:
            self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
            if self.on_reject is not None:
                self.on_reject(exc.reason)
            return None
        self.received += 1
        parts = batch.split(self.per_request) if self.per_request > 1 else [batch]
        return [(part, self.assembler(part) if self.assembler is not None else None) for part in parts]

    def _run(self) -> None:
        pending: deque = deque(self._ask() for _ in range(self.in_flight))
        while not self.stop.is_set():
            handler = pending.popleft()
            replies = 0
            for reply in handler:
                replies += 1
                if reply.ok is None:  # rate limited or not ready: ask again
                    self.errors += 1
                    continue
                for item in self.decode(reply.ok.payload) or ():
                    while not self.stop.is_set():
                        try:
                            self.ready.put(item, timeout=0.2)
                            break
                        except queue.Full:
                            continue
            self.unanswered += replies == 0
            if not self.stop.is_set():
                pending.append(self._ask())
        deadline = time.monotonic() + 2.0
        for handler in pending:  # let the outstanding queries end before the session closes
            for _ in handler:
                if time.monotonic() > deadline:
                    break
