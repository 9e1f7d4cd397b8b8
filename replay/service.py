"""The replay service: ``ReplayTable`` behind Zenoh.

Transition batches arrive on ``transitions/*`` (reliable, BLOCK) on a Zenoh session of their
own and wait in a deque for one insert thread. Backpressure is explicit: every 20 ms the service
publishes an insert credit (what the rate limiter accepts now, minus the backlog) and actors pause
while it is exhausted. Zenoh's blocking puts remain the safety net, but they never have to block
for long (a put blocked for seconds makes Zenoh take the link down). Sampling is a
queryable (``replay/sample``) answered from its own thread. Malformed batches are counted by
reason and dropped; accepted ones are never lost: the table is saved every ``persist_every_s``
and on SIGTERM, and restored on start.
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

from curlnav.layout import ObservationLayout
from curlnav.transport import HttpServer, RateMeter, json_response, open_session
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import SampledBatch, SampleRequest, ServiceStatus, TransitionBatch
from curlnav.proto.topology import Topology

from .table import RateLimiterTimeout, ReplayInputError, ReplayTable, SampleToInsertRatio

log = logging.getLogger("curlnav.replay")


@dataclass(frozen=True)
class ReplayServiceConfig:
    run: str = "default"
    router: str = "tcp/127.0.0.1:7447"
    data_dir: str = "runs/service/replay"
    http_port: int = 0  # 0: pick a free port; /metrics and /healthz
    max_size: int = 200_000
    min_size_to_sample: int = 2000
    samples_per_insert: float = 64.0  # 0 disables rate limiting
    error_buffer: float | None = None  # default: max(0.1 * min * spi, 2 * 256 + spi)
    persist_every_s: float = 120.0


class ReplayService:
    def __init__(self, cfg: ReplayServiceConfig, layout: ObservationLayout | None = None) -> None:
        self.cfg = cfg
        self.topology = Topology(cfg.run)
        self.layout = layout or ObservationLayout()
        self.data_dir = Path(cfg.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        path = self.data_dir / "replay.npz"
        limiter = self._limiter()
        if path.exists():
            self.table = ReplayTable.restore(path, limiter)
            log.info("restored %d transitions from %s", self.table.size, path)
        else:
            self.table = ReplayTable(self.layout, cfg.max_size, limiter)
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

    def _limiter(self) -> SampleToInsertRatio:
        cfg = self.cfg
        if cfg.samples_per_insert <= 0:
            return SampleToInsertRatio.unlimited(cfg.min_size_to_sample)
        buffer = cfg.error_buffer or max(0.1 * cfg.min_size_to_sample * cfg.samples_per_insert,
                                         2 * 512 + cfg.samples_per_insert)
        return SampleToInsertRatio(cfg.samples_per_insert, cfg.min_size_to_sample, buffer)

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
                            sample.next_obs.astype(np.float16), sample.keys).encode()

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
        topo = self.topology
        session = open_session(cfg.router)
        # Transitions come in on a session of their own: when the limiter holds inserts back and
        # the channel is full, that session's receive path blocks (backpressure to the actors
        # through the router), while sampling queries keep flowing on the other one. With one
        # session, a full channel would stall the queries too, and nothing would ever unblock.
        ingest = open_session(cfg.router)
        # The subscriber callback only appends to a deque: it never blocks Zenoh (a long block
        # makes Zenoh close the link and lose data). Actors pace themselves on the insert credit
        # published below, which counts this backlog, so the deque stays short.
        subscriber = ingest.declare_subscriber(topo.transitions("*"), lambda s: self.backlog.append(s.payload.to_bytes()))
        queryable = session.declare_queryable(topo.sample)
        token = session.liveliness().declare_token(topo.alive("replay", "0"))
        status_pub = session.declare_publisher(topo.status("replay"))
        http = HttpServer("0.0.0.0", cfg.http_port, {("GET", "/healthz"): lambda r: json_response(self.status())},
                          registry=self.registry)
        (self.data_dir / "http_port").write_text(str(http.port))
        log.info("replay service up: run %s, router %s, http port %d", cfg.run, cfg.router, http.port)

        def insert_loop():
            while not self.stop.is_set():
                if not self.backlog:
                    time.sleep(0.001)
                    continue
                payload = self.backlog.popleft()
                while not self.stop.is_set():
                    try:
                        self.handle_batch(payload, timeout=0.5)
                        break
                    except RateLimiterTimeout:
                        continue  # the learner has not caught up: hold the batch (and the channel)

        def sample_loop():
            while not self.stop.is_set():
                query = queryable.try_recv()
                if query is None:
                    time.sleep(0.0005)
                    continue
                try:
                    payload = query.payload.to_bytes() if query.payload is not None else b""
                    query.reply(topo.sample, self.handle_sample(payload))
                except RateLimiterTimeout:
                    query.reply_err(b"rate_limited")
                except ProtoError as exc:
                    query.reply_err(str(exc).encode())
                finally:
                    query.drop()

        threads = [threading.Thread(target=insert_loop, daemon=True), threading.Thread(target=sample_loop, daemon=True)]
        for t in threads:
            t.start()
        credit_pub = session.declare_publisher(topo.credit)
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
            for t in threads:
                t.join(timeout=5)
            subscriber.undeclare()
            # insert what Zenoh already delivered before saving: accepted data is never lost
            while self.backlog:
                self.handle_batch(self.backlog.popleft(), force=True)
            self.save()
            log.info("replay saved %d transitions", self.table.size)
            token.undeclare()
            queryable.undeclare()
            http.close()
            ingest.close()
            session.close()
