"""The actor service: the simulator driven by the latest weights, feeding the replay.

Weights arrive on ``weights`` (and ``weights/latest`` when joining); the subscriber only keeps
the newest message and the loop loads it between steps, so weight traffic never stalls the
simulation. The environments, behaviour policy (actor ``actor_index``'s rung of the sigma ladder,
its share of the warm-up) and n-step writer come from ``D4PGBuilder``: ``envs`` environments
(``actor.envs_per_process``, default 8) stepped together with one batched policy call (``VectorEpisodeLoop``;
with one environment it acts exactly as the serial trainer's ``EpisodeLoop``). Transitions go out
in batches every ``batch_steps`` environment steps and at every episode end (reliable, BLOCK);
each episode is reported to the scheduler, which is asked for the next world and pair at every
reset of each environment, so each keeps its own assignment. A liveliness token
announces the actor; Zenoh reconnects by itself when the router comes back.

Every batch is kept until the replay acknowledges it (``ResendBuffer``: bounded in memory and on
disk) and sent only while the replay is heard from (its credit, every 20 ms): a partition, a
router or a replay restart loses nothing generated; the batches go out again, in order, once the
replay is back. When the buffer is full the actor stops stepping. At stop the actor sends its last
partial batch and waits (``flush_s``) for what it holds to be acknowledged, then writes its counts
to ``<data_dir>/actor-final.json``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from prometheus_client import CollectorRegistry, Counter, Gauge

from curlnav.bus.service import Deployment, ServiceShell
from curlnav.bus.transport import RateMeter, reliable_publisher
from curlnav.config import ActorConfig, ConfigError, D4PGConfig, ExperimentConfig
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import (
    MAX_ACTOR_ID,
    Assignment,
    AssignmentRequest,
    EpisodeReport,
    ServiceStatus,
    TransitionBatch,
    Weights,
)

from .resend import ResendBuffer

if TYPE_CHECKING:
    from curlnav.learner.networks import BehaviourPolicy

    from .vector import VectorEpisodeLoop

log = logging.getLogger("curlnav.actor")

#: in an actor's data folder: its environment steps, so that the helpers' fade survives a restart
HELPERS_FILE = "helpers.json"
HELPERS_SAVE_S = 10.0  # s between saves of HELPERS_FILE (and one at stop)


@dataclass(frozen=True)
class ActorServiceConfig:
    """Deployment of one actor (how it explores comes from the experiment config)."""

    actor_id: str = "actor-0"
    actor_index: int = 0  # rung of the sigma ladder and seed offset
    actor_count: int = 1  # actors in the run: each takes this share of the warm-up
    deployment: Deployment = Deployment(data_dir="")
    #: environment steps per transition batch on the bus (all environments together); 24 so that 8
    #: environments' n-step tails (8 x 5) still fit the default replay.insert_batch of 64
    batch_steps: int = 24
    envs: int = 1  # environments this process steps together (one batched policy call per step)
    resend_memory_bytes: int = 64 << 20  # unacknowledged batches kept in memory ...
    resend_disk_bytes: int = 1 << 30  # ... then in a spill file in data_dir; beyond both the actor pauses
    resend_after_s: float = 5.0  # an unacknowledged batch is sent again (with all after it) after this
    flush_s: float = 10.0  # at stop: how long to wait for the last batches to be acknowledged (the launcher waits 30 s)
    unheard_batches: int = 64  # while the replay is not heard (cut off, restarting): batches made, then wait

    def __post_init__(self) -> None:
        if not 0 < len(self.actor_id) <= MAX_ACTOR_ID or any(c in self.actor_id for c in "/*$?#"):
            raise ConfigError(f"actor id {self.actor_id[:40]!r}: 1..{MAX_ACTOR_ID} characters, none of / * $ ? #")
        ActorConfig(envs_per_process=self.envs)  # the config's own check (ConfigError, one line)


class ActorCore:
    """The episode loop with swappable weights; no network."""

    def __init__(self, cfg: ActorServiceConfig, experiment: ExperimentConfig, policy: BehaviourPolicy,
                 loop: VectorEpisodeLoop) -> None:
        """``policy`` and ``loop``: actor ``cfg.actor_index``'s behaviour policy and its loop of
        ``cfg.envs`` environments (``D4PGBuilder.make_actor_core`` wires them)."""
        self.cfg = cfg
        self.layout = policy.layout
        self.policy = policy
        self.loop = loop
        self.default_world = experiment.curriculum.world
        self.rng = np.random.default_rng([experiment.seed, cfg.actor_index, 1])
        self.weights_version = -1
        # sequence numbers start at this process's start time in microseconds, so a restarted
        # actor's batches always number above its predecessor's (the replay drops resends by seq)
        self.seq = time.time_ns() // 1000
        self.generated = 0  # transitions put into batches by this process
        max_batch = experiment.replay.insert_batch
        # a batch holds up to batch_steps + envs - 1 steps' transitions plus each environment's n-step
        # tail: fewer steps per batch where the tails need the room (a longer n-step, a smaller insert_batch)
        tails = cfg.envs * experiment.d4pg.n_step
        if cfg.batch_steps + tails > max_batch and max_batch - tails >= 1:
            log.info("actor batches of %d steps instead of %d: %d environments' n-step tails of %d fit "
                     "replay.insert_batch %d", max_batch - tails, cfg.batch_steps, cfg.envs, experiment.d4pg.n_step,
                     max_batch)
            cfg = self.cfg = dataclasses.replace(cfg, batch_steps=max_batch - tails)
        if cfg.batch_steps + tails > max_batch:
            raise ConfigError(f"actor batches of {cfg.batch_steps} steps (plus the n-step tails of {cfg.envs} "
                              f"environment(s) of {experiment.d4pg.n_step}) may exceed replay.insert_batch = "
                              f"{max_batch}, the most one batch may carry: lower actor.envs_per_process or raise "
                              f"replay.insert_batch")

    @property
    def steps(self) -> int:
        return self.loop.steps

    def load_weights(self, msg: Weights) -> int:
        self.policy.load_weights(msg.safetensors, D4PGConfig.from_dict(msg.d4pg_config))
        self.weights_version = msg.version
        return msg.version

    def batch(self) -> bytes | None:
        frames = self.loop.flush()
        if frames.num_frames == 0 and frames.num_transitions == 0:
            return None
        msg = TransitionBatch(self.cfg.actor_id, self.seq, self.weights_version, frames)
        self.seq += 1
        self.generated += frames.num_transitions
        return msg.encode()


class ActorService:
    def __init__(self, cfg: ActorServiceConfig, experiment: ExperimentConfig, core: ActorCore) -> None:
        """``core``: made from ``cfg`` and ``experiment`` (``D4PGBuilder.make_actor_service`` wires it)."""
        self.cfg = cfg
        self.experiment = experiment
        torch.set_num_threads(1)
        self.core = core
        self.cfg = self.core.cfg  # batch_steps as the core fitted it to replay.insert_batch
        self.registry = CollectorRegistry()
        self.m_steps = Counter("actor_env_steps", "environment steps", registry=self.registry)
        self.m_episodes = Counter("actor_episodes", "episodes", ["world", "outcome"], registry=self.registry)
        self.m_version = Gauge("actor_weights_version", "weights version in use", registry=self.registry)
        self.m_version.set_function(lambda: self.core.weights_version)
        self.m_rejected = Counter("actor_messages_rejected", "refused messages", ["reason"], registry=self.registry)
        self.m_rate = Gauge("actor_env_steps_per_second", "environment steps per second", registry=self.registry)
        self.m_control = Counter("actor_control_steps", "control steps by the part of the training stack that "
                                 "chose them (network, or a helper: helpers.stack)", ["role"], registry=self.registry)
        self.step_rate = RateMeter()
        self.m_rate.set_function(self.step_rate.rate)
        self._pending_weights: Weights | None = None
        self._credit = (1_000_000, 0.0)  # (transitions the replay accepts now, when heard)
        self.acked_seq = -1  # the highest of this actor's batch seqs the replay has accepted (logged)
        data_dir = cfg.deployment.data_dir or f"runs/service/actors/{cfg.actor_id}"
        self.helpers_file = Path(data_dir) / HELPERS_FILE
        self._helpers_saved_at = 0.0
        if self.core.loop.helpers is not None:
            self._resume_helpers()
        self.resend = ResendBuffer(data_dir, cfg.resend_memory_bytes, cfg.resend_disk_bytes, cfg.resend_after_s)
        self._resend_lock = threading.Lock()  # the credit callback acknowledges, the loop adds and sends
        self.m_unacked = Gauge("actor_batches_unacknowledged", "batches generated that the replay has not yet "
                               "accepted (kept and sent again)", registry=self.registry)
        self.m_unacked.set_function(lambda: len(self.resend))
        self.m_generated = Gauge("actor_transitions_generated", "transitions put into batches",
                                 registry=self.registry)
        self.m_generated.set_function(lambda: self.core.generated)
        self.m_resent = Gauge("actor_batches_resent", "batches sent again (go-back-N)", registry=self.registry)
        self.m_resent.set_function(lambda: self.resend.resent)
        self.paused_s = 0.0  # time spent with the resend buffer full
        self._lock = threading.Lock()
        self.stop = threading.Event()

    def _resume_helpers(self) -> None:
        """A restarted actor (a resumed run, a crash the supervisor restarted) goes on with the
        helpers' fade where it was: its environment steps from ``helpers.json`` (saved at most every
        ``HELPERS_SAVE_S`` and at stop), and the on/off draws from a stream of that count."""
        try:
            saved = json.loads(self.helpers_file.read_text())
            steps = saved["env_steps"]
            if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
                raise ValueError(f"env_steps must be a whole number >= 0, got {steps!r}")
        except FileNotFoundError:
            return
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("actor %s: %s unreadable (%s): the helpers' fade starts again", self.cfg.actor_id,
                        self.helpers_file, exc)
            return
        self.core.loop.steps = steps
        self.core.loop.helpers.resume(stream=steps)
        log.info("actor %s: the helpers' fade goes on from %d environment steps (share %.2f)", self.cfg.actor_id,
                 steps, self.experiment.helpers.share(steps))

    def _save_helpers(self, force: bool = False) -> None:
        """This actor's environment steps, for the helpers' fade after a restart (``_resume_helpers``)."""
        if self.core.loop.helpers is None or not force and time.monotonic() - self._helpers_saved_at < HELPERS_SAVE_S:
            return
        self._helpers_saved_at = time.monotonic()
        try:
            self.helpers_file.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.helpers_file.with_suffix(".tmp")
            tmp.write_text(json.dumps({"env_steps": self.core.loop.steps}) + "\n")
            tmp.replace(self.helpers_file)
        except OSError as exc:
            log.warning("actor %s: cannot save %s (%s)", self.cfg.actor_id, self.helpers_file, exc)

    def _on_weights(self, sample) -> None:
        """Validate and keep only the newest weights; the simulation loop loads them."""
        try:
            msg = Weights.decode(sample.payload.to_bytes())
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            return
        with self._lock:
            if self._pending_weights is None or msg.version >= self._pending_weights.version:
                self._pending_weights = msg

    def sent(self, seq: int, payload: bytes = b"") -> None:
        """Batch ``seq`` is made: kept until the replay acknowledges it."""
        with self._resend_lock:
            self.resend.add(seq, payload)

    def heard(self, within_s: float = 1.0) -> bool:
        """The replay's credit came within ``within_s``: it is reachable, batches may go."""
        return time.monotonic() - self._credit[1] <= within_s

    def send_due(self, publisher) -> int:
        """Put what the resend buffer says is due (nothing while the replay is not heard)."""
        if not self.heard():
            return 0
        with self._resend_lock:
            due = self.resend.due()
        for _, payload in due:
            publisher.put(payload)
        return len(due)

    def _on_credit(self, sample) -> None:
        try:
            msg = ServiceStatus.decode(sample.payload.to_bytes())
            self._credit = (int(msg.values.get("allowed", 0)), time.monotonic())
            acked = msg.values.get(f"ack/{self.cfg.actor_id}")
            if acked is not None:
                self._on_ack(int(acked))
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()

    def _on_ack(self, acked: int) -> None:
        """The replay's acknowledgement for this actor's id. One at or above the next seq was
        never sent by this process (another batch on its id, or a predecessor whose numbers ran
        ahead): the replay now drops this actor's batches as duplicates, so it numbers on above
        it (counted as ``foreign_ack``) and keeps the refused ones unacknowledged."""
        if acked >= self.core.seq:
            self.m_rejected.labels("foreign_ack").inc()
            with self._resend_lock:  # what it holds would be duplicates: numbered above the ack, sent again
                self.core.seq = self.resend.renumber(acked + 1, self._renumbered)
            return
        self.acked_seq = max(self.acked_seq, acked)
        with self._resend_lock:
            self.resend.ack(acked)

    def _batch_out(self, transitions) -> None:
        """The steps since the last batch as a batch: kept, then sent with whatever else is due."""
        seq = self.core.seq
        payload = self.core.batch()
        if payload is not None:
            self.sent(seq, payload)
            self._last_size = len(payload)
            allowed, heard = self._credit
            self._credit = (allowed - self.cfg.batch_steps, heard)  # spend it until the next word
        self.send_due(transitions)

    _last_size = 0

    def _wait_for_room(self, transitions) -> None:
        """While the resend buffer is full, step nothing: send what is due and wait for acknowledgements."""
        started = time.monotonic()
        while not self.stop.is_set():
            with self._resend_lock:  # full, or the replay unreachable: generate no more than it may take
                full = self.resend.full(self._last_size) or (
                    not self.heard() and self.resend.unsent() >= self.cfg.unheard_batches)
            if not full:
                break
            self.send_due(transitions)
            self.stop.wait(0.05)
        self.paused_s += time.monotonic() - started

    def _finish(self, transitions, data_dir: str) -> None:
        """At stop: the partial batch out, up to ``flush_s`` for everything held to be
        acknowledged, then the counts to ``<data_dir>/actor-final.json``."""
        self._batch_out(transitions)
        self._save_helpers(force=True)
        deadline = time.monotonic() + self.cfg.flush_s
        while len(self.resend) and time.monotonic() < deadline and self.heard(within_s=2.0):
            self.send_due(transitions)  # a replay not heard for 2 s acknowledges nothing: stop waiting
            time.sleep(0.05)
        with self._resend_lock:
            held = len(self.resend)
            final = {"actor_id": self.cfg.actor_id, "generated": self.core.generated, "unacknowledged_batches": held,
                     "unacknowledged_transitions": None if held else 0, "resent_batches": self.resend.resent,
                     "paused_s": round(self.paused_s, 3), "acked_seq": self.acked_seq}
            if held:
                final["unacknowledged_transitions"] = sum(
                    TransitionBatch.decode(p).batch.num_transitions for _, p in self.resend.due(float("inf")))
            self.resend.close()
        path = Path(data_dir) / "actor-final.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(final) + "\n")
        log.info("actor %s stopped: %d transitions generated, %d batches unacknowledged", self.cfg.actor_id,
                 self.core.generated, held)

    def _renumbered(self, payload: bytes, seq: int) -> bytes:
        try:
            msg = TransitionBatch.decode(payload)
        except ProtoError:
            return payload
        return dataclasses.replace(msg, seq=seq).encode()

    def _wait_for_credit(self) -> None:
        """Pause (sleeping, not spinning) while the replay's limiter holds inserts back. A stale
        credit (replay silent for a second) does not hold the actor: the blocking put does."""
        while not self.stop.is_set():
            allowed, heard = self._credit
            if allowed > 0 or time.monotonic() - heard > 1.0:
                return
            self.stop.wait(0.005)

    def _apply_weights(self) -> None:
        with self._lock:
            msg, self._pending_weights = self._pending_weights, None
        if msg is None:
            return
        if msg.version <= self.core.weights_version:  # versions only go forward
            self.m_rejected.labels("stale_weights").inc()
            return
        try:
            self.core.load_weights(msg)
        except Exception:  # safetensors or torch refused the tensors: count it, keep the old weights
            self.m_rejected.labels("bad_weights").inc()

    def _assignment(self, session, key: str) -> Assignment | None:
        request = AssignmentRequest(self.cfg.actor_id).encode()
        for reply in session.get(key, payload=request, timeout=2.0):
            if reply.ok is not None:
                try:
                    return Assignment.decode(reply.ok.payload.to_bytes())
                except ProtoError as exc:
                    self.m_rejected.labels(exc.reason).inc()
        return None

    def run(self) -> None:
        cfg = self.cfg
        core = self.core
        loop = core.loop
        deployment = cfg.deployment
        if not deployment.data_dir:
            deployment = dataclasses.replace(deployment, data_dir=f"runs/service/actors/{cfg.actor_id}")
        shell = ServiceShell("actor", cfg.actor_id, deployment, self.experiment, self.registry,
                             lambda: {"steps": core.steps, "weights_version": core.weights_version})
        with shell:
            session = shell.open()
            shell.on_close("environment", loop.close)
            topo = shell.topology
            transitions = reliable_publisher(session, topo.transitions(cfg.actor_id))
            episodes = reliable_publisher(session, topo.episodes(cfg.actor_id))
            weights_sub = session.declare_subscriber(topo.weights, self._on_weights)
            shell.on_close("weights subscriber", weights_sub.undeclare)
            credit_sub = session.declare_subscriber(topo.credit, self._on_credit)
            shell.on_close("credit subscriber", credit_sub.undeclare)
            for reply in session.get(topo.weights_latest, timeout=5.0):
                if reply.ok is not None:
                    self._on_weights(reply.ok)
            tasks: list[tuple] = [()] * loop.size  # per environment: (assignment, world, weights version at begin)
            since_batch = 0  # environment steps since the last batch
            asked_at = time.monotonic()
            while not self.stop.is_set():
                shell.recheck_agreement()  # a service of another config that joined after this actor
                if self.experiment.init_from and core.weights_version < 0:
                    # a run from a trained policy has no random warm-up: no step before its weights
                    self._apply_weights()
                    if core.weights_version < 0:
                        if time.monotonic() - asked_at >= 2.0:  # a learner that started after this actor
                            asked_at = time.monotonic()
                            for reply in session.get(topo.weights_latest, timeout=2.0):
                                if reply.ok is not None:
                                    self._on_weights(reply.ok)
                        self.stop.wait(0.1)
                        continue
                if not self._begin_waiting(session, topo.assign, tasks):
                    self.stop.wait(1.0)
                    continue
                if since_batch == 0:
                    self._wait_for_credit()
                    self._wait_for_room(transitions)
                    if self.stop.is_set():
                        break
                before = loop.steps
                ends = loop.step()
                stepped = loop.steps - before
                self.m_steps.inc(stepped)
                self.step_rate.add(stepped)
                since_batch += stepped
                if ends or since_batch >= cfg.batch_steps:
                    self._batch_out(transitions)
                    since_batch = 0
                if loop.steps // 50 != before // 50:
                    self._apply_weights()
                for k, end in ends:
                    assignment, world, version_used = tasks[k]
                    info = end.info
                    self.m_episodes.labels(info["world"], "success" if end.success else "failure").inc()
                    for role, count in end.control_steps.items():
                        self.m_control.labels(role).inc(count)
                    episodes.put(EpisodeReport(cfg.actor_id, world, assignment.pair if assignment else "",
                                               end.success, float(end.episode_return), int(info["base_collisions"]),
                                               int(info["end_effector_collisions"]), int(info["steps"]), version_used,
                                               assignment.epoch if assignment else -1,
                                               dict(end.control_steps)).encode())
                if ends:
                    self.send_due(transitions)  # resends (after a partition) go on between batches too
                    self._save_helpers()
            self._finish(transitions, deployment.data_dir)

    def _begin_waiting(self, session, assign_key: str, tasks: list) -> bool:
        """Begin a new episode in every environment whose last one ended, each with its own
        assignment from the scheduler (the newest weights loaded first). False when an
        assignment could not be used (logged; the caller waits and tries again)."""
        core, loop = self.core, self.core.loop
        waiting = loop.waiting()
        if waiting:
            self._apply_weights()
        for k in waiting:
            assignment = self._assignment(session, assign_key)
            world = assignment.world if assignment else core.default_world
            options = {"world": world}
            if assignment and assignment.pair:
                options["pair"] = assignment.pair
            try:
                loop.begin(k, seed=int(core.rng.integers(1 << 31)), options=options)
            except (KeyError, ValueError) as exc:
                log.error("actor %s: cannot use assignment %s: %s", self.cfg.actor_id, options, exc)
                return False
            tasks[k] = (assignment, world, core.weights_version)
        return True
