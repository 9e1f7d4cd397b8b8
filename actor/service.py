"""The actor service: the simulator driven by the latest weights, feeding the replay.

Weights arrive on ``weights`` (and ``weights/latest`` when joining); the subscriber only keeps
the newest message and the loop loads it between steps, so weight traffic never stalls the
simulation. Each actor has its own exploration sigma. Transitions go out in batches every
``batch_steps`` steps and at every episode end (reliable, BLOCK); each episode is reported to
the scheduler, which is asked for the next world and pair at every reset. A liveliness token
announces the actor; Zenoh reconnects by itself when the router comes back.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
import time
from dataclasses import dataclass

import numpy as np
import torch
from prometheus_client import CollectorRegistry, Counter, Gauge
from safetensors.torch import load as safetensors_load

from curlnav.layout import ObservationLayout
from curlnav.sim import EnvConfig, NamoEnv
from curlnav.transport import HttpServer, RateMeter, open_session, reliable_publisher
from curlnav.learner.config import D4PGConfig
from curlnav.learner.d4pg import act
from curlnav.learner.networks import Actor
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import Assignment, AssignmentRequest, EpisodeReport, ServiceStatus, TransitionBatch, Weights
from curlnav.proto.topology import Topology
from curlnav.replay.nstep import NStepWriter

log = logging.getLogger("curlnav.actor")


@dataclass(frozen=True)
class ActorServiceConfig:
    actor_id: str = "actor-0"
    run: str = "default"
    router: str = "tcp/127.0.0.1:7447"
    http_port: int = 0
    sigma: float = 0.3  # exploration noise, fraction of each action's half-range
    n_step: int = 5
    discount: float = 0.99
    batch_steps: int = 32  # steps per transition batch
    max_episode_steps: int = 200
    default_world: str = "open-room"  # when no scheduler answers
    data_dir: str = ""  # where to write http_port (optional)
    warmup_steps: int = 0  # random actions before the first weights arrive are always used
    seed: int = 0


class ActorCore:
    """Environment loop with n-step writer and swappable weights; no network."""

    def __init__(self, cfg: ActorServiceConfig) -> None:
        self.cfg = cfg
        self.env_cfg = EnvConfig(max_episode_steps=cfg.max_episode_steps, end_on_base_collision=True)
        self.layout = ObservationLayout.from_env_config(self.env_cfg)
        self.env = NamoEnv(cfg.default_world, self.env_cfg)
        self.writer = NStepWriter(self.layout, cfg.n_step, cfg.discount)
        self.rng = np.random.default_rng(cfg.seed)
        self.actor: Actor | None = None
        self.weights_version = -1
        self.seq = 0
        self.steps = 0
        self.episodes = 0

    def load_weights(self, msg: Weights) -> int:
        if self.actor is None:
            self.actor = Actor(self.layout, D4PGConfig.from_dict(msg.d4pg_config))
            self.actor.eval()
        self.actor.load_state_dict(safetensors_load(msg.safetensors))
        self.weights_version = msg.version
        return msg.version

    def action(self, obs: np.ndarray) -> np.ndarray:
        if self.actor is None or self.steps < self.cfg.warmup_steps:
            return self.rng.uniform((0.0, -1.0, 0.0), (1.0, 1.0, 1.0)).astype(np.float32)
        return act(self.actor, obs, self.cfg.sigma, self.rng)

    def batch(self) -> bytes | None:
        frames = self.writer.flush()
        if frames.num_frames == 0 and frames.num_transitions == 0:
            return None
        msg = TransitionBatch(self.cfg.actor_id, self.seq, self.weights_version, frames)
        self.seq += 1
        return msg.encode()


class ActorService:
    def __init__(self, cfg: ActorServiceConfig) -> None:
        self.cfg = cfg
        self.topology = Topology(cfg.run)
        torch.set_num_threads(1)
        self.core = ActorCore(cfg)
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

    def _on_credit(self, sample) -> None:
        try:
            msg = ServiceStatus.decode(sample.payload.to_bytes())
            self._credit = (int(msg.values.get("allowed", 0)), time.monotonic())
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()

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
        if msg is None or msg.version == self.core.weights_version:
            return
        try:
            self.core.load_weights(msg)
        except Exception:  # safetensors or torch refused the tensors: count it, keep the old weights
            self.m_rejected.labels("bad_weights").inc()

    def _assignment(self, session) -> Assignment | None:
        request = AssignmentRequest(self.cfg.actor_id).encode()
        for reply in session.get(self.topology.assign, payload=request, timeout=2.0):
            if reply.ok is not None:
                try:
                    return Assignment.decode(reply.ok.payload.to_bytes())
                except ProtoError as exc:
                    self.m_rejected.labels(exc.reason).inc()
        return None

    def run(self) -> None:
        cfg = self.cfg
        topo = self.topology
        core = self.core
        session = open_session(cfg.router)
        transitions = reliable_publisher(session, topo.transitions(cfg.actor_id))
        episodes = reliable_publisher(session, topo.episodes(cfg.actor_id))
        weights_sub = session.declare_subscriber(topo.weights, self._on_weights)
        credit_sub = session.declare_subscriber(topo.credit, self._on_credit)
        token = session.liveliness().declare_token(topo.alive("actor", cfg.actor_id))
        http = HttpServer("0.0.0.0", cfg.http_port, {}, registry=self.registry)
        if cfg.data_dir:
            Path(cfg.data_dir).mkdir(parents=True, exist_ok=True)
            (Path(cfg.data_dir) / "http_port").write_text(str(http.port))
        for reply in session.get(topo.weights_latest, timeout=5.0):
            if reply.ok is not None:
                self._on_weights(reply.ok)
        log.info("actor %s up: run %s, router %s", cfg.actor_id, cfg.run, cfg.router)
        try:
            while not self.stop.is_set():
                self._apply_weights()
                assignment = self._assignment(session)
                world = assignment.world if assignment else cfg.default_world
                options = {"world": world}
                if assignment and assignment.pair:
                    options["pair"] = assignment.pair
                try:
                    obs, _ = core.env.reset(seed=int(core.rng.integers(1 << 31)), options=options)
                except (KeyError, ValueError) as exc:
                    log.error("actor %s: cannot use assignment %s: %s", cfg.actor_id, options, exc)
                    self.stop.wait(1.0)
                    continue
                core.writer.first(obs)
                episode_return, version_used = 0.0, core.weights_version
                while not self.stop.is_set():
                    if core.steps % cfg.batch_steps == 0:
                        self._wait_for_credit()
                    action = core.action(obs)
                    obs, reward, terminated, truncated, info = core.env.step(action)
                    core.writer.step(action, reward, obs, terminated, truncated)
                    core.steps += 1
                    episode_return += reward
                    self.m_steps.inc()
                    self.step_rate.add()
                    done = terminated or truncated
                    if done or core.steps % cfg.batch_steps == 0:
                        payload = core.batch()
                        if payload is not None:
                            transitions.put(payload)
                            allowed, heard = self._credit
                            self._credit = (allowed - cfg.batch_steps, heard)  # spend it until the next word
                    if done:
                        break
                    if core.steps % 50 == 0:
                        self._apply_weights()
                if self.stop.is_set():
                    break
                core.episodes += 1
                self.m_episodes.labels(info["world"], "success" if info["is_success"] else "failure").inc()
                episodes.put(EpisodeReport(cfg.actor_id, world, assignment.pair if assignment else "",
                                           bool(info["is_success"]), float(episode_return), int(info["base_collisions"]),
                                           int(info["end_effector_collisions"]), int(info["steps"]), version_used,
                                           assignment.epoch if assignment else -1).encode())
        finally:
            token.undeclare()
            credit_sub.undeclare()
            weights_sub.undeclare()
            http.close()
            session.close()
            core.env.close()
