"""The replay service: ``ReplayTable`` behind Zenoh.

Transition batches arrive on ``transitions/*`` (reliable, BLOCK) on a Zenoh session of their
own and wait in a deque for one insert thread. Backpressure is explicit: every 20 ms the service
publishes an insert credit (what the rate limiter accepts now, minus the backlog) and actors pause
while it is exhausted. Zenoh's blocking puts remain the safety net, but they never have to block
for long (a put blocked for seconds makes Zenoh take the link down). Sampling is a
queryable (``replay/sample``) answered from its own thread. Malformed batches are counted by
reason and dropped; accepted ones are never lost: the table is saved every ``persist_every_s``
and on SIGTERM, and restored on start. With a prioritized replay, the learner's
``PriorityUpdate`` messages set the sampled items' new priorities. The table and its rate limiter
come from ``D4PGBuilder`` (the experiment config), exactly as in the serial trainer.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge

from curlnav.builder import D4PGBuilder
from curlnav.config import ExperimentConfig
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import PriorityUpdate, SampledBatch, SampleRequest, ServiceStatus, TransitionBatch
from curlnav.service import Deployment, ServiceShell
from curlnav.transport import RateMeter

from .table import RateLimiterTimeout, ReplayInputError

log = logging.getLogger("curlnav.replay")


@dataclass(frozen=True)
class ReplayServiceConfig:
    """Deployment of the replay service (what it holds comes from the experiment config)."""

    deployment: Deployment = Deployment(data_dir="runs/service/replay")
    persist_every_s: float = 120.0  # s between saves of the whole table


class ReplayService:
    def __init__(self, cfg: ReplayServiceConfig, experiment: ExperimentConfig) -> None:
        self.cfg = cfg
        self.experiment = experiment
        builder = D4PGBuilder(experiment)
        self.layout = builder.layout
        self.data_dir = Path(cfg.deployment.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        path = self.data_dir / "replay.npz"
        if path.exists():
            self.table = builder.restore_replay_table(path)
            log.info("restored %d transitions from %s", self.table.size, path)
        else:
            self.table = builder.make_replay_table()
        self.registry = CollectorRegistry()
        self.m_in = Counter("replay_transitions_inserted", "transitions accepted", registry=self.registry)
        self.m_batches = Counter("replay_batches_received", "transition batches received", registry=self.registry)
        self.m_rejected = Counter("replay_messages_rejected", "refused messages", ["reason"], registry=self.registry)
        self.m_sampled = Counter("replay_transitions_sampled", "transitions served to the learner", registry=self.registry)
        self.m_size = Gauge("replay_size", "transitions held", registry=self.registry)
        self.m_size.set_function(lambda: self.table.size)
        self.insert_rate = RateMeter()
        self.sample_rate = RateMeter()
        self.backlog: deque[bytes] = deque()  # received batches not yet inserted
        self.mean_batch = 32.0  # transitions per batch, running mean, to size the backlog
        self.last_seq: dict[str, int] = {}
        self.seq_gaps = 0
        self.stop = threading.Event()

    # -- pure handlers (tested without a network) --------------------------------------------
    def handle_batch(self, payload: bytes, timeout: float | None = None, force: bool = False) -> int:
        """Decode and insert one batch; returns transitions added (0 when rejected)."""
        self.m_batches.inc()
        try:
            msg = TransitionBatch.decode(payload, beams=self.layout.beams)
            added = self.table.insert(msg.batch, stream=msg.actor_id, timeout=timeout, force=force)
        except (ProtoError, ReplayInputError) as exc:
            self.m_rejected.labels(exc.reason).inc()
            return 0
        last = self.last_seq.get(msg.actor_id)
        if last is not None and msg.seq != last + 1:
            self.seq_gaps += 1
        self.last_seq[msg.actor_id] = msg.seq
        self.m_in.inc(added)
        self.insert_rate.add(added)
        self.mean_batch = 0.9 * self.mean_batch + 0.1 * msg.batch.num_transitions
        return added

    def handle_sample(self, payload: bytes) -> bytes:
        try:
            request = SampleRequest.decode(payload)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            raise
        sample = self.table.sample(request.batch_size, timeout=request.timeout_s)
        self.m_sampled.inc(request.batch_size)
        self.sample_rate.add(request.batch_size)
        return SampledBatch(sample.obs.astype(np.float16), sample.action, sample.reward, sample.discount,
                            sample.next_obs.astype(np.float16), sample.keys,
                            sample.probabilities.astype(np.float32)).encode()

    def handle_priorities(self, payload: bytes) -> int:
        """Apply a learner's ``PriorityUpdate``; returns the items updated (0 when refused)."""
        try:
            msg = PriorityUpdate.decode(payload)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            return 0
        if not self.experiment.replay.prioritized:
            self.m_rejected.labels("not_prioritized").inc()
            return 0
        self.table.update_priorities(msg.keys, msg.priorities)
        return len(msg.keys)

    def insert_credit(self) -> int:
        """Transitions the limiter would accept now (actors pace themselves on it instead of
        spinning in a blocked put); large when the table is still filling."""
        limiter = self.table.rate_limiter
        backlog = len(self.backlog) * self.mean_batch
        if self.table.size < limiter.min_size_to_sample or limiter.window[1] > 1e15:
            return int(max(limiter.min_size_to_sample - self.table.size, 0) + 100_000 - backlog)
        return int((limiter.window[1] - limiter.error) // limiter.samples_per_insert - backlog)

    def status(self) -> dict:
        info = self.table.info()
        return {"size": info["size"], "inserted": info["total_inserted"], "sampled": info["total_sampled"],
                "insert_rate": self.insert_rate.rate(), "sample_rate": self.sample_rate.rate(),
                "rejected": sum(self.rejected().values()), "seq_gaps": self.seq_gaps}

    def rejected(self) -> dict[str, float]:
        out = {}
        for metric in self.m_rejected.collect():
            for s in metric.samples:
                if s.name.endswith("_total"):
                    out[s.labels["reason"]] = s.value
        return out

    def save(self) -> None:
        self.table.save(self.data_dir / "replay.npz")

    # -- shell -----------------------------------------------------------------------------------
    def run(self) -> None:
        cfg = self.cfg
        shell = ServiceShell("replay", "0", cfg.deployment, self.experiment, self.registry, self.status)
        with shell:
            session = shell.open()
            topo = shell.topology
            # Transitions come in on a session of their own: when the limiter holds inserts back
            # and the channel is full, that session's receive path blocks (backpressure to the
            # actors through the router), while sampling queries keep flowing on the other one.
            ingest = shell.new_session()
            # The subscriber callback only appends to a deque: it never blocks Zenoh (a long
            # block makes Zenoh close the link and lose data). Actors pace themselves on the
            # insert credit published below, which counts this backlog, so the deque stays short.
            subscriber = ingest.declare_subscriber(topo.transitions("*"),
                                                   lambda s: self.backlog.append(s.payload.to_bytes()))
            priorities = session.declare_subscriber(topo.priorities,
                                                    lambda s: self.handle_priorities(s.payload.to_bytes()))
            shell.on_close("priority subscriber", priorities.undeclare)
            queryable = session.declare_queryable(topo.sample)
            shell.on_close("sample queryable", queryable.undeclare)
            status_pub = session.declare_publisher(topo.status("replay"))
            credit_pub = session.declare_publisher(topo.credit)
            threads = [threading.Thread(target=self._insert_loop, daemon=True),
                       threading.Thread(target=self._sample_loop, args=(queryable, topo.sample), daemon=True)]
            for t in threads:
                t.start()
            last_save = last_status = time.monotonic()
            try:
                while not self.stop.wait(0.02):
                    credit_pub.put(ServiceStatus("replay-credit", {"allowed": self.insert_credit()}).encode())
                    if time.monotonic() - last_status < 1.0:
                        continue
                    last_status = time.monotonic()
                    status_pub.put(ServiceStatus("replay", self.status()).encode())
                    if time.monotonic() - last_save >= cfg.persist_every_s:
                        self.save()
                        last_save = time.monotonic()
            finally:
                self.stop.set()
                for t in threads:
                    t.join(timeout=5)
                subscriber.undeclare()
                # insert what Zenoh already delivered before saving: accepted data is never lost
                while self.backlog:
                    self.handle_batch(self.backlog.popleft(), force=True)
                self.save()
                log.info("replay saved %d transitions", self.table.size)

    def _insert_loop(self) -> None:
        while not self.stop.is_set():
            if not self.backlog:
                time.sleep(0.001)
                continue
            payload = self.backlog.popleft()
            while True:
                if self.stop.is_set():
                    self.backlog.appendleft(payload)  # inserted (forced) with the rest at shutdown
                    return
                try:
                    self.handle_batch(payload, timeout=0.5)
                    break
                except RateLimiterTimeout:
                    continue  # the learner has not caught up: hold the batch (and the channel)

    def _sample_loop(self, queryable, key: str) -> None:
        while not self.stop.is_set():
            query = queryable.try_recv()
            if query is None:
                time.sleep(0.0005)
                continue
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                query.reply(key, self.handle_sample(payload))
            except RateLimiterTimeout:
                query.reply_err(b"rate_limited")
            except ProtoError as exc:
                query.reply_err(str(exc).encode())
            finally:
                query.drop()
