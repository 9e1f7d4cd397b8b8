"""The replay service: ``ReplayTable`` behind Zenoh, crash-safe.

Transition batches arrive on ``transitions/*`` (reliable, BLOCK) on a Zenoh session of their
own and wait in a deque (the receive queue). The **accept** thread drains it: each batch is
decoded and checked (at most ``replay.insert_batch`` transitions: the one batch limit, which the
rate limiter is sized to always admit eventually; a larger or malformed batch is refused and
counted by reason, never retried), duplicates of batches already accepted are dropped, the rest
are written to the segment log (``replay/wal.py``) and the log is fsync'd once per drain. From
then on a batch is **accepted**: a ``kill -9`` does not lose it, because the service re-inserts
the log at start. The **insert** thread then puts accepted batches into the table, waiting on the
rate limiter for the learner (backpressure, not a retry: an accepted batch always fits).

Every 20 ms the service publishes an insert credit (what the rate limiter accepts now, minus
what waits) and, per actor, the highest sequence number accepted (the acknowledgement); actors
pause while the credit is exhausted.

Nothing one actor sends can block another (issue 26): a batch must come on the key of the actor
it names (``transitions/<actor_id>``, else ``key_mismatch``); a ``seq`` above the present in
microseconds plus ``SEQ_FUTURE_MARGIN_S`` is refused (``seq_future``; actors number their batches
from their start time in microseconds, one per batch, so they never get there), also when the log
is read back at a restart. The acknowledgements are bounded (``MAX_TRACKED_ACTORS`` ids, those
without a liveliness token leave first), an actor leaves the credit message when its liveliness token goes, and
the credit message names only actors holding a token (at most ``CREDIT_ACKS``; ids are at most
128 characters): a few KB whatever is sent.

Nothing generated is lost across a partition or a restart: an actor keeps every batch until it is
acknowledged and resends from the oldest one, in order (``curlnav.actor.resend``). The replay
accepts an actor's batches in sequence only: a resend at or below its acknowledgement is a
``duplicate``; a batch above a gap (those before it were lost) is refused (``out_of_order``), so the
acknowledgement stays below the gap until the lost batches arrive; a jump of ``NEW_STREAM_GAP`` or
more is a restarted actor. Sampling is a queryable (``replay/sample``) answered from
its own thread, never stalled by persistence (there is no snapshot to write: the log is the
state; segments whose transitions have left the table are deleted). With a prioritized replay,
the learner's ``PriorityUpdate`` messages set the sampled items' new priorities (priorities are
not persisted: restored items start at the maximum). The table and its rate limiter come from
``D4PGBuilder`` (the experiment config; its ``make_replay_service`` hands the table in), exactly as
in the serial trainer.

An accepted transition the table cannot store (a frame it no longer knows or holds: the table's
``dropped``) is counted by reason, over the run like ``accepted``: ``dropped`` and
``dropped/<reason>`` in ``/status`` (``stored`` = what went into the table, accepted less dropped,
of what has left the wait), ``replay_transitions_dropped_total{reason}`` in ``/metrics``. The count
survives a restart without counting a batch twice: ``dropped.json`` (the counts and the log
index they cover) is rewritten after each insert that drops something and at a clean stop; at
start, the log's batches from that index on count again (those before it were counted), except
the first segment of a pruned log (its transitions left the table long ago, and may name frames
of the segment deleted before it).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import zenoh
from prometheus_client import CollectorRegistry, Counter, Gauge

from curlnav.bus.service import Deployment, ServiceShell
from curlnav.bus.transport import RateMeter, json_response
from curlnav.config import ExperimentConfig
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import PriorityUpdate, SampledBatch, SampleRequest, ServiceStatus, TransitionBatch

from .table import RateLimiterTimeout, ReplayInputError, ReplayTable
from .wal import SegmentLog

log = logging.getLogger("curlnav.replay")

SEQ_FUTURE_MARGIN_S = 600.0  # clock skew allowed between an actor's host and the replay's
MAX_TRACKED_ACTORS = 1024  # actor ids whose acknowledgement and last seq are kept
MAX_LIVE_ACTORS = 4096  # liveliness tokens of actors followed (beyond: counted and ignored)
CREDIT_ACKS = 256  # acknowledgements in one credit message (the most recently accepted live actors)
#: a seq this far (1 s of microseconds) above an actor's last accepted one starts a new stream (a
#: restarted actor numbers from its start time); a smaller jump is a gap: batches were lost on the way
NEW_STREAM_GAP = 1_000_000
DROPPED_FILE = "dropped.json"  # in the data folder: the drop counts and the log index they cover


def read_dropped(data_dir: str | Path) -> tuple[int, dict[str, int]]:
    """The replay's drops as last saved in ``data_dir``: (the log index they cover, reason ->
    transitions); (0, {}) when none were saved (or the file is unreadable: the log counts again)."""
    try:
        saved = json.loads((Path(data_dir) / DROPPED_FILE).read_text())
        through, dropped = int(saved["through"]), saved["dropped"]
        counts = {str(reason): int(n) for reason, n in dropped.items() if int(n) > 0}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return 0, {}
    return (through, counts) if through >= 0 else (0, {})


def seq_limit() -> int:
    """The highest batch ``seq`` believed now: the present in microseconds plus the margin."""
    return time.time_ns() // 1000 + int(SEQ_FUTURE_MARGIN_S * 1e6)


@dataclass(frozen=True)
class ReplayServiceConfig:
    """Deployment of the replay service (what it holds comes from the experiment config)."""

    deployment: Deployment = Deployment(data_dir="runs/service/replay")
    prune_every_s: float = 30.0  # s between deletions of log segments that left the table
    fsync: bool = True  # fsync the log before a batch counts as accepted (off: only for benchmarks)
    shm: bool = False  # answer samples from Zenoh shared memory (a learner on this host reads them without a socket)
    shm_pool_mib: int = 64  # the shared-memory pool (MiB): a few sampled replies of 6 MB (4 batches of 256) each


class ReplayService:
    def __init__(self, cfg: ReplayServiceConfig, experiment: ExperimentConfig, table: ReplayTable) -> None:
        """``table``: the experiment's empty table (``D4PGBuilder.make_replay_table``; the builder's
        ``make_replay_service`` wires both)."""
        self.cfg = cfg
        self.experiment = experiment
        self.layout = table.layout
        self.data_dir = Path(cfg.deployment.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.table = table
        self.max_batch = experiment.replay.insert_batch
        self.log = SegmentLog(self.data_dir / "wal", fsync=cfg.fsync)
        self.accepted_total = 0  # transitions accepted in the run's lifetime (the log's index)
        self.in_table_total = 0  # of those, how many have gone into the table (the rest wait)
        self.acked: dict[str, int] = {}  # actor id -> highest batch seq accepted (most recent last)
        self.live: set[str] = set()  # actor ids holding a liveliness token
        self._acks_lock = threading.Lock()  # acked, last_seq and live change on two threads
        self.registry = CollectorRegistry()
        self.m_in = Counter("replay_transitions_inserted", "transitions accepted", registry=self.registry)
        self.m_batches = Counter("replay_batches_received", "transition batches received", registry=self.registry)
        self.m_rejected = Counter("replay_messages_rejected", "refused messages", ["reason"], registry=self.registry)
        self.m_dropped = Counter("replay_transitions_dropped", "accepted transitions not stored, by reason (over "
                                 "the run, across restarts)", ["reason"], registry=self.registry)
        self.dropped: dict[str, int] = {}  # reason -> accepted transitions not stored, over the run
        self.m_sampled = Counter("replay_transitions_sampled", "transitions served to the learner", registry=self.registry)
        self.m_size = Gauge("replay_size", "transitions held", registry=self.registry)
        self.m_size.set_function(lambda: self.table.size)
        self.insert_rate = RateMeter()
        self.sample_rate = RateMeter()
        self.backlog: deque[tuple[str | None, bytes]] = deque()  # (key's actor id, batch) received, not accepted
        self.accepted: deque[TransitionBatch] = deque()  # accepted (in the log), not yet in the table
        self.mean_batch = 32.0  # transitions per batch, running mean, to size the backlog
        self.last_seq: dict[str, int] = {}
        self.seq_gaps = 0
        self.stop = threading.Event()
        self.restored = self._restore()
        self.started = time.monotonic()

    # -- pure handlers (tested without a network) --------------------------------------------
    def _restore(self) -> int:
        """Re-insert the log's batches (the accepted ones, in order); returns transitions restored."""
        restored = future = 0
        limit = seq_limit()
        drops: list[tuple[int, dict[str, int]]] = []  # (log index, the table's drops before) of records that dropped
        for first, payload in self.log.records():
            msg = TransitionBatch.decode(payload, beams=self.layout.beams, memory_beams=self.layout.memory_beams)
            before = dict(self.table.dropped)
            added = self.table.insert(msg.batch, stream=msg.actor_id, force=True)
            restored += added
            if added < msg.batch.num_transitions:
                drops.append((first, before))
            self.accepted_total = self.in_table_total = first + msg.batch.num_transitions
            if msg.seq > limit:  # logged before seqs were checked: the data stays, its number is not believed
                future += 1
                continue
            self._remember(msg.actor_id, max(self.acked.get(msg.actor_id, -1), msg.seq))
            self.last_seq[msg.actor_id] = msg.seq
        if future:
            log.warning("the log holds %d batches numbered beyond now + %g s: restored, not acknowledged",
                        future, SEQ_FUTURE_MARGIN_S)
        self._restore_drops(drops)
        if restored:
            self.table.total_inserted = self.accepted_total
            self.table.rate_limiter.recentre(self.table.size)
            log.info("restored %d transitions from the log (%d accepted in the run)", self.table.size,
                     self.accepted_total)
        elif (self.data_dir / "replay.npz").exists():
            log.warning("%s is a replay file of an earlier version: not restored (the log is the state now)",
                        self.data_dir / "replay.npz")
        return restored

    def _restore_drops(self, drops: list[tuple[int, dict[str, int]]]) -> None:
        """The run's drop count at start: the saved one, plus the drops of the log's records from
        the index it covers on (``drops``: (index, the table's ``dropped`` before) of each record
        that dropped something at restore), except the first segment of a pruned log."""
        through, saved = read_dropped(self.data_dir)
        if through > self.accepted_total:  # saved beside another log (this one was cleared): not ours
            through, saved = 0, {}
        segments = self.log.segments()
        count_from = through
        if segments and segments[0][0] > 0:  # pruned: its first segment's drops are never counted, even alone
            count_from = max(through, segments[1][0] if len(segments) > 1 else self.accepted_total)
        counted = dict(saved)
        ends = [before for _, before in drops[1:]] + [self.table.dropped]  # after a record: before the next
        for (first, before), after in zip(drops, ends):
            if first >= count_from:
                for reason, n in after.items():
                    counted[reason] = counted.get(reason, 0) + n - before.get(reason, 0)
        self.dropped = {reason: n for reason, n in counted.items() if n}
        for reason, n in self.dropped.items():
            self.m_dropped.labels(reason).inc(n)
        if self.dropped != saved:
            log.warning("%d accepted transitions not stored over the run (%s)", sum(self.dropped.values()),
                        ", ".join(f"{reason} {n}" for reason, n in sorted(self.dropped.items())))
            self._save_dropped()

    def _remember(self, actor: str, seq: int) -> None:
        """Set ``actor``'s acknowledged seq (most recent last); beyond ``MAX_TRACKED_ACTORS`` ids
        the oldest without a liveliness token goes (else the oldest)."""
        with self._acks_lock:
            self.acked.pop(actor, None)
            self.acked[actor] = seq
            while len(self.acked) > MAX_TRACKED_ACTORS:
                gone = next((a for a in self.acked if a not in self.live), next(iter(self.acked)))
                self.acked.pop(gone)
                self.last_seq.pop(gone, None)

    def actor_alive(self, actor: str, alive: bool) -> None:
        """An actor's liveliness token came (``alive``) or went. A gone actor leaves the credit
        message but keeps its acknowledgement (bounded with the others, gone ones first out): an
        actor cut off by a partition comes back and resends what it holds unacknowledged, and
        the batches accepted before the cut must stay duplicates."""
        with self._acks_lock:
            if not alive:
                self.live.discard(actor)
                return
            if len(self.live) < MAX_LIVE_ACTORS:
                self.live.add(actor)
                return
        self.m_rejected.labels("too_many_actors").inc()

    def accept_batches(self, payloads: list[bytes | tuple[str | None, bytes]]) -> list[TransitionBatch]:
        """Decode and check ``payloads`` (each a batch, or (the actor id of its key, batch));
        write the good ones to the log and commit (fsync): from here on they are accepted.
        Refused ones are counted by reason."""
        good = []
        total = self.accepted_total
        acked: dict[str, int] = {}
        limit = seq_limit()
        for item in payloads:
            sender, payload = item if isinstance(item, tuple) else (None, item)
            self.m_batches.inc()
            try:
                msg = TransitionBatch.decode(payload, beams=self.layout.beams, memory_beams=self.layout.memory_beams)
                if sender is not None and msg.actor_id != sender:
                    raise ReplayInputError("key_mismatch", "the batch names another actor than its key")
                if msg.seq > limit:
                    raise ReplayInputError("seq_future", f"seq {msg.seq} beyond now + {SEQ_FUTURE_MARGIN_S:g} s")
                if msg.batch.num_transitions > self.max_batch:
                    raise ReplayInputError("too_large", f"{msg.batch.num_transitions} transitions in one batch, "
                                                        f"at most replay.insert_batch = {self.max_batch}")
                self.table.validate(msg.batch)
            except (ProtoError, ReplayInputError) as exc:
                self.m_rejected.labels(exc.reason).inc()
                continue
            last = acked.get(msg.actor_id, self.acked.get(msg.actor_id))
            if last is not None and msg.seq <= last:
                self.m_rejected.labels("duplicate").inc()  # a resend of a batch already accepted
                continue
            if last is not None and last + 1 < msg.seq < last + NEW_STREAM_GAP:
                # batches before it were lost (a partition, a replay restart): refused, so the
                # acknowledgement stays below the gap and the actor resends from it, in order
                self.m_rejected.labels("out_of_order").inc()
                continue
            self.log.append(payload, total)
            total += msg.batch.num_transitions
            acked[msg.actor_id] = msg.seq
            good.append(msg)
        if good:
            self.log.commit()  # from here on they are accepted: only now are they counted and acked
            self.accepted_total = total
            for actor, seq in acked.items():
                self._remember(actor, seq)
        return good

    def insert_accepted(self, msg: TransitionBatch, timeout: float | None = None, force: bool = False) -> int:
        """Insert one accepted batch into the table (waits on the rate limiter, up to
        ``timeout``: ``RateLimiterTimeout``). Transitions not stored are counted (``dropped``)."""
        before = dict(self.table.dropped)
        added = self.table.insert(msg.batch, stream=msg.actor_id, timeout=timeout, force=force)
        self.in_table_total += msg.batch.num_transitions  # the log index the table has reached
        if added < msg.batch.num_transitions and self._count_drops(before):
            self._save_dropped()
        last = self.last_seq.get(msg.actor_id)
        if last is not None and msg.seq != last + 1:
            self.seq_gaps += 1
        with self._acks_lock:
            if msg.actor_id in self.acked:  # bounded with the acknowledgements
                self.last_seq[msg.actor_id] = msg.seq
        self.m_in.inc(added)
        self.insert_rate.add(added)
        self.mean_batch = 0.9 * self.mean_batch + 0.1 * msg.batch.num_transitions
        return added

    def _count_drops(self, before: dict[str, int]) -> int:
        """Add what the table dropped since ``before`` (its ``dropped`` then) to the run's count;
        returns transitions."""
        new = 0
        for reason, n in self.table.dropped.items():
            if (more := n - before.get(reason, 0)) > 0:
                self.dropped[reason] = self.dropped.get(reason, 0) + more
                self.m_dropped.labels(reason).inc(more)
                new += more
        return new

    def _save_dropped(self) -> None:
        """Write the drop counts and the log index they cover (atomically: a kill leaves the old
        file or the new one; an old one only makes the next start count a few batches again)."""
        path = self.data_dir / DROPPED_FILE
        tmp = path.with_name(f"{path.name}.{threading.get_ident()}.tmp")  # the insert thread's, or the stop's
        tmp.write_text(json.dumps({"through": self.in_table_total, "dropped": self.dropped}))
        os.replace(tmp, path)

    def handle_batch(self, payload: bytes, timeout: float | None = None, force: bool = False,
                     sender: str | None = None) -> int:
        """Accept and insert one batch at once (``sender``: the actor id of its key); returns
        transitions added (0 when refused)."""
        return sum(self.insert_accepted(msg, timeout, force) for msg in self.accept_batches([(sender, payload)]))

    def handle_sample(self, payload: bytes) -> bytearray:
        try:
            request = SampleRequest.decode(payload)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            raise
        try:  # a request the rate limiter could never admit would wait for ever: refuse it now
            self.table.rate_limiter.check_batch(request.batch_size, insert=self.experiment.replay.insert_batch)
        except ValueError as exc:
            self.m_rejected.labels("range").inc()
            raise ProtoError("range", f"a sample request of {request.batch_size} transitions: {exc}") from None
        # gathered straight into the reply's raw buffers (frames, not stacked observations)
        writer = SampledBatch.writer(request.batch_size, self.layout, self.table.action_size)
        self.table.sample_frames(request.batch_size, timeout=request.timeout_s,
                                 out={name: writer.view(name) for name in writer.schema})
        self.m_sampled.inc(request.batch_size)
        self.sample_rate.add(request.batch_size)
        return writer.payload()

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
        backlog = (len(self.backlog) + len(self.accepted)) * self.mean_batch
        if self.table.size < limiter.min_size_to_sample or limiter.window[1] > 1e15:
            return int(max(limiter.min_size_to_sample - self.table.size, 0) + 100_000 - backlog)
        return int((limiter.window[1] - limiter.error) // limiter.samples_per_insert - backlog)

    def status(self) -> dict:
        info = self.table.info()
        dropped = dict(self.dropped)
        return {"size": info["size"], "inserted": self.accepted_total, "accepted": self.accepted_total,
                "in_table": info["total_inserted"], "sampled": info["total_sampled"], "waiting": len(self.accepted),
                "stored": self.in_table_total - sum(dropped.values()), "dropped": sum(dropped.values()),
                **{f"dropped/{reason}": n for reason, n in sorted(dropped.items())},
                "insert_rate": self.insert_rate.rate(), "sample_rate": self.sample_rate.rate(),
                "rejected": sum(self.rejected().values()), "seq_gaps": self.seq_gaps,
                "log_bytes": self.log.bytes_written, "restored": self.restored,
                "uptime_s": time.monotonic() - self.started}

    def rejected(self) -> dict[str, float]:
        out = {}
        for metric in self.m_rejected.collect():
            for s in metric.samples:
                if s.name.endswith("_total"):
                    out[s.labels["reason"]] = s.value
        return out

    def prune_log(self) -> int:
        """Delete log segments whose transitions have all left the table (FIFO)."""
        return self.log.drop_before(self.in_table_total - self.table.max_size)

    def credit_message(self) -> bytes:
        """The insert credit, the run's accepted count and the acknowledged seq of each actor
        holding a liveliness token (the ``CREDIT_ACKS`` most recently accepted)."""
        with self._acks_lock:
            acks = [(a, seq) for a, seq in reversed(self.acked.items()) if a in self.live][:CREDIT_ACKS]
        return ServiceStatus("replay-credit", {"allowed": self.insert_credit(), "accepted": self.accepted_total,
                                               **{f"ack/{actor}": seq for actor, seq in acks}}).encode()

    # -- shell -----------------------------------------------------------------------------------
    def run(self) -> None:
        cfg = self.cfg
        shell = ServiceShell("replay", "0", cfg.deployment, self.experiment, self.registry, self.status)
        with shell:
            session = shell.open({("GET", "/status"): lambda request: json_response(self.status())})
            topo = shell.topology
            # Transitions come in on a session of their own: when the limiter holds inserts back
            # and the channel is full, that session's receive path blocks (backpressure to the
            # actors through the router), while sampling queries keep flowing on the other one.
            ingest = shell.new_session()
            # The subscriber callback only appends to a deque: it never blocks Zenoh (a long
            # block makes Zenoh close the link and lose data). Actors pace themselves on the
            # insert credit published below, which counts this backlog, so the deque stays short.
            subscriber = ingest.declare_subscriber(
                topo.transitions("*"), lambda s: self.backlog.append((str(s.key_expr).rsplit("/", 1)[-1],
                                                                      s.payload.to_bytes())))
            alive = session.liveliness().declare_subscriber(
                topo.alive("actor", "*"), lambda s: self.actor_alive(str(s.key_expr).rsplit("/", 1)[-1],
                                                                     s.kind == zenoh.SampleKind.PUT), history=True)
            shell.on_close("actor liveliness subscriber", alive.undeclare)
            priorities = session.declare_subscriber(topo.priorities,
                                                    lambda s: self.handle_priorities(s.payload.to_bytes()))
            shell.on_close("priority subscriber", priorities.undeclare)
            queryable = session.declare_queryable(topo.sample)
            shell.on_close("sample queryable", queryable.undeclare)
            status_pub = session.declare_publisher(topo.status("replay"))
            credit_pub = session.declare_publisher(topo.credit)
            threads = [threading.Thread(target=self._guarded, args=(self._accept_loop,), daemon=True, name="accept"),
                       threading.Thread(target=self._guarded, args=(self._insert_loop,), daemon=True, name="insert"),
                       threading.Thread(target=self._sample_loop, args=(queryable, topo.sample), daemon=True)]
            for t in threads:
                t.start()
            last_prune = last_status = time.monotonic()
            try:
                while not self.stop.wait(0.02):
                    credit_pub.put(self.credit_message())
                    if time.monotonic() - last_status < 1.0:
                        continue
                    last_status = time.monotonic()
                    status_pub.put(ServiceStatus("replay", self.status()).encode())
                    if time.monotonic() - last_prune >= cfg.prune_every_s:
                        self.prune_log()
                        last_prune = time.monotonic()
            finally:
                self.stop.set()
                subscriber.undeclare()
                threads[0].join()  # the accept thread writes the log: never two writers
                for t in threads[1:]:
                    t.join(timeout=5)
                if self.failure is not None:
                    self.log.close()
                    raise RuntimeError(f"replay stopped after a failure: {self.failure!r}") from self.failure
                # accept what Zenoh already delivered, then put every accepted batch in the table
                # (the log has them all anyway: this only spares the next start the work)
                while self.backlog:
                    self.accepted.extend(self.accept_batches([self.backlog.popleft() for _ in range(
                        min(len(self.backlog), 256))]))
                while self.accepted:
                    self.insert_accepted(self.accepted.popleft(), force=True)
                self._save_dropped()  # covers the whole log: the next start counts none of it again
                self.log.close()
                log.info("replay stopped: %d transitions held, %d accepted in the run", self.table.size,
                         self.accepted_total)

    failure: BaseException | None = None  # what stopped the accept or insert thread

    def _guarded(self, loop) -> None:
        """Run ``loop``; if it fails (a full disk, a bug), stop the service so that it exits
        non-zero and its supervisor restarts it from the log, instead of hanging half-alive."""
        try:
            loop()
        except BaseException as exc:
            log.exception("replay %s thread failed: stopping", loop.__name__)
            self.failure = exc
            self.stop.set()

    def _accept_loop(self) -> None:
        """Drain the receive queue: decode, check, log, fsync once per drain (group commit)."""
        while not self.stop.is_set():
            if not self.backlog:
                time.sleep(0.001)
                continue
            payloads = [self.backlog.popleft() for _ in range(min(len(self.backlog), 256))]
            self.accepted.extend(self.accept_batches(payloads))

    def _insert_loop(self) -> None:
        """Accepted batches into the table, as fast as the rate limiter lets them in."""
        while not self.stop.is_set():
            if not self.accepted:
                time.sleep(0.001)
                continue
            try:
                self.insert_accepted(self.accepted[0], timeout=0.5)
                self.accepted.popleft()
            except RateLimiterTimeout:
                continue  # the learner has not caught up: the batch waits, accepted and logged

    _shm_provider = None

    def _in_shm(self, data: bytearray):
        """``data`` in a Zenoh shared-memory buffer when ``shm`` is on (one copy in; Zenoh hands a
        reader on this host the segment, and sends the bytes to one elsewhere), else as is."""
        if not self.cfg.shm:
            return data
        from zenoh import shm

        if self._shm_provider is None:
            self._shm_provider = shm.ShmProvider.default_backend(self.cfg.shm_pool_mib << 20)
        buf = self._shm_provider.alloc(len(data), shm.BlockOn(shm.GarbageCollect()))
        buf[0:len(data)] = data
        return zenoh.ZBytes(buf)

    def _sample_loop(self, queryable, key: str) -> None:
        while not self.stop.is_set():
            query = queryable.try_recv()
            if query is None:
                time.sleep(0.0005)
                continue
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                query.reply(key, self._in_shm(self.handle_sample(payload)))
            except RateLimiterTimeout:
                query.reply_err(b"rate_limited")
            except ProtoError as exc:
                query.reply_err(str(exc).encode())
            finally:
                query.drop()
