"""The actor service: the simulator driven by the latest weights, feeding the replay.

Weights arrive on ``weights`` (and ``weights/latest`` when joining); the subscriber only keeps
the newest message and the loop loads it between steps, so weight traffic never stalls the
simulation. The environment, behaviour policy (actor ``actor_index``'s rung of the sigma ladder,
its share of the warm-up) and n-step writer come from ``D4PGBuilder`` and run in the shared
``EpisodeLoop``, exactly as in the serial trainer. Transitions go out in batches every
``batch_steps`` steps and at every episode end (reliable, BLOCK); each episode is reported to
the scheduler, which is asked for the next world and pair at every reset. A liveliness token
announces the actor; Zenoh reconnects by itself when the router comes back.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import torch
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
from prometheus_client import CollectorRegistry, Counter, Gauge

from curlnav.builder import D4PGBuilder
from curlnav.bus.service import Deployment, ServiceShell
from curlnav.bus.transport import RateMeter, reliable_publisher
from curlnav.config import ConfigError, D4PGConfig, ExperimentConfig

from .loop import EpisodeLoop

log = logging.getLogger("curlnav.actor")


@dataclass(frozen=True)
class ActorServiceConfig:
    """Deployment of one actor (how it explores comes from the experiment config)."""

    actor_id: str = "actor-0"
    actor_index: int = 0  # rung of the sigma ladder and seed offset
    actor_count: int = 1  # actors in the run: each takes this share of the warm-up
    deployment: Deployment = Deployment(data_dir="")
    batch_steps: int = 32  # environment steps per transition batch on the bus

    def __post_init__(self) -> None:
        if not 0 < len(self.actor_id) <= MAX_ACTOR_ID or any(c in self.actor_id for c in "/*$?#"):
            raise ConfigError(f"actor id {self.actor_id[:40]!r}: 1..{MAX_ACTOR_ID} characters, none of / * $ ? #")


class ActorCore:
    """The episode loop with swappable weights; no network."""

    def __init__(self, cfg: ActorServiceConfig, experiment: ExperimentConfig) -> None:
        self.cfg = cfg
        builder = D4PGBuilder(experiment)
        self.layout = builder.layout
        self.policy = builder.make_behaviour_policy(cfg.actor_index, cfg.actor_count)
        self.loop = EpisodeLoop(builder.make_env(), self.policy, builder.make_nstep_writer(),
                                builder.make_world_draws(cfg.actor_index))
        self.env = self.loop.env
        self.default_world = experiment.curriculum.world
        self.rng = np.random.default_rng([experiment.seed, cfg.actor_index, 1])
        self.weights_version = -1
        # sequence numbers start at this process's start time in microseconds, so a restarted
        # actor's batches always number above its predecessor's (the replay drops resends by seq)
        self.seq = time.time_ns() // 1000
        max_batch = experiment.replay.insert_batch
        if cfg.batch_steps + experiment.d4pg.n_step > max_batch:
            raise ConfigError(f"actor batches of {cfg.batch_steps} steps (plus the n-step tail of "
                              f"{experiment.d4pg.n_step}) exceed replay.insert_batch = {max_batch}, the most one "
                              f"batch may carry: lower --batch-steps or raise replay.insert_batch")

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
        return msg.encode()


class ActorService:
    def __init__(self, cfg: ActorServiceConfig, experiment: ExperimentConfig) -> None:
        self.cfg = cfg
        self.experiment = experiment
        torch.set_num_threads(1)
        self.core = ActorCore(cfg, experiment)
        self.registry = CollectorRegistry()
        self.m_steps = Counter("actor_env_steps", "environment steps", registry=self.registry)
        self.m_episodes = Counter("actor_episodes", "episodes", ["world", "outcome"], registry=self.registry)
        self.m_version = Gauge("actor_weights_version", "weights version in use", registry=self.registry)
        self.m_version.set_function(lambda: self.core.weights_version)
        self.m_rejected = Counter("actor_messages_rejected", "refused messages", ["reason"], registry=self.registry)
        self.m_rate = Gauge("actor_env_steps_per_second", "environment steps per second", registry=self.registry)
        self.step_rate = RateMeter()
        self.m_rate.set_function(self.step_rate.rate)
        self._pending_weights: Weights | None = None
        self._credit = (1_000_000, 0.0)  # (transitions the replay accepts now, when heard)
        self.acked_seq = -1  # the highest of this actor's batch seqs the replay has accepted (logged)
        self.unacked: deque[int] = deque(maxlen=100_000)  # seqs sent and not yet acknowledged, oldest first
        self.m_unacked = Gauge("actor_batches_unacknowledged", "batches sent that the replay has not yet accepted "
                               "(batches refused as duplicates stay counted)", registry=self.registry)
        self.m_unacked.set_function(lambda: len(self.unacked))
        self._lock = threading.Lock()
        self.stop = threading.Event()

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

    def sent(self, seq: int) -> None:
        """Batch ``seq`` went out: unacknowledged until the replay's credit says otherwise."""
        self.unacked.append(seq)

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
            self.core.seq = acked + 1
            return
        self.acked_seq = max(self.acked_seq, acked)
        while self.unacked and self.unacked[0] <= acked:
            self.unacked.popleft()

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
            while not self.stop.is_set():
                shell.recheck_agreement()  # a service of another config that joined after this actor
                self._apply_weights()
                assignment = self._assignment(session, topo.assign)
                world = assignment.world if assignment else core.default_world
                options = {"world": world}
                if assignment and assignment.pair:
                    options["pair"] = assignment.pair
                try:
                    loop.begin(seed=int(core.rng.integers(1 << 31)), options=options)
                except (KeyError, ValueError) as exc:
                    log.error("actor %s: cannot use assignment %s: %s", cfg.actor_id, options, exc)
                    self.stop.wait(1.0)
                    continue
                version_used = core.weights_version
                end = None
                while not self.stop.is_set() and end is None:
                    if core.steps % cfg.batch_steps == 0:
                        self._wait_for_credit()
                    end = loop.step()
                    self.m_steps.inc()
                    self.step_rate.add()
                    if end is not None or core.steps % cfg.batch_steps == 0:
                        seq = core.seq
                        payload = core.batch()
                        if payload is not None:
                            self.sent(seq)
                            transitions.put(payload)
                            allowed, heard = self._credit
                            self._credit = (allowed - cfg.batch_steps, heard)  # spend it until the next word
                    if end is None and core.steps % 50 == 0:
                        self._apply_weights()
                if end is None:
                    break
                info = end.info
                self.m_episodes.labels(info["world"], "success" if end.success else "failure").inc()
                episodes.put(EpisodeReport(cfg.actor_id, world, assignment.pair if assignment else "",
                                           end.success, float(end.episode_return), int(info["base_collisions"]),
                                           int(info["end_effector_collisions"]), int(info["steps"]), version_used,
                                           assignment.epoch if assignment else -1).encode())
