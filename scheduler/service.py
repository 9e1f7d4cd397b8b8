"""The scheduler service: the curriculum behind Zenoh and HTTP.

Answers ``scheduler/assign`` queries, counts ``episodes/*`` reports, tracks live actors by
their liveliness tokens (a killed actor leaves ``/status`` within a second), reads replay and
learner status, persists its state after every advance and every 10 s, and resumes from it.

HTTP: ``GET /status``, ``GET /curriculum``, ``GET /metrics``, ``GET /healthz``, and, with
``Authorization: Bearer <admin token>``, ``POST /admin/advance`` (force the next step) and
``POST /admin/evaluation`` (JSON ``{"epoch", "success_rate", "episodes"}``: a held-out evaluation
of the current step, which a criterion with ``source: evaluation`` advances on; the evaluator
beside a run sends it).
"""

from __future__ import annotations

import hmac
import json
import logging
import os
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge

from curlnav.bus.service import Deployment, ServiceShell
from curlnav.bus.transport import json_response
from curlnav.config import ExperimentConfig
from curlnav.nav.roles import NETWORK, ControlSteps
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import MAX_ACTOR_ID, Assignment, AssignmentRequest, EpisodeReport, ServiceStatus

from .curriculum import Curriculum, CurriculumState, load_curriculum

log = logging.getLogger("curlnav.scheduler")


def mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


@dataclass(frozen=True)
class SchedulerServiceConfig:
    """Deployment of the scheduler (the curriculum itself is ``curriculum`` of the experiment)."""

    deployment: Deployment = Deployment(data_dir="runs/service/scheduler", http_port=8080)
    admin_token: str = ""  # empty: the admin call is refused


#: bounds on what the scheduler keeps, whatever arrives
MAX_ACTORS = 1024  # live actors tracked (tokens beyond it wait for room: see SchedulerCore)
MAX_WAITING = 4 * MAX_ACTORS  # liveliness tokens remembered while the table is full (oldest forgotten)
IDLE_S = 120.0  # an actor that has neither asked for a world nor reported for this long may make room
STATUS_ACTORS = 64  # actors detailed in /status (the rest are counted in live_actor_count)
STATUS_ROLES = ("replay", "learner")  # services whose status the scheduler keeps
MAX_LOST = 256  # actors remembered as lost (their token went: killed, or cut off by a partition)


class SchedulerCore:
    """Everything the scheduler decides, without a network: assignments, reports, status.

    Its state is bounded: actors exist only through their liveliness token (at most
    ``MAX_ACTORS``); a report from an id without one (``unknown_actor``), from an id that never
    asked for a world (``unassigned``: a bare token is not an actor at work), on another actor's
    key (``key_mismatch``), or about a world or pair that is not in the curriculum, is refused and
    counted; per-(world, pair) counts are keyed by the curriculum's own worlds and pairs; only the
    replay's and learner's status values are kept.

    Ghost tokens (held, never used) cannot lock real actors out: when the table is full, a new
    token waits (``too_many_actors``; at most ``MAX_WAITING`` remembered) and takes the place of an
    actor idle for ``IDLE_S``, or, as soon as it asks for a world, of one that never asked (else
    of the one idle longest): an actor at work asks at every episode.
    """

    def __init__(self, curriculum: Curriculum, state: CurriculumState | None = None,
                 extra_worlds: tuple[str, ...] = ()) -> None:
        self.curriculum = curriculum
        self.state = state or CurriculumState(curriculum)
        self.known_worlds = {w for stage in curriculum.stages for w in stage.worlds} | set(extra_worlds)
        self.known_pairs = {""} | {p for stage in curriculum.stages for p in stage.substeps}
        self.lock = threading.RLock()
        self.actors: dict[str, dict] = {}  # live actors: id -> {assignment, last_report, episodes, joined}
        self.active: dict[str, float] = {}  # live actor id -> monotonic time it last asked or reported (or joined)
        self.waiting: OrderedDict[str, None] = OrderedDict()  # tokens that came while the table was full
        self.lost: OrderedDict[str, dict] = OrderedDict()  # actors whose token went: id -> {since, episodes}
        self.rejoined = 0  # lost actors whose token came back (a healed partition, a restart)
        self.services: dict[str, dict] = {}  # role -> last status values
        self.recent_episodes: deque = deque(maxlen=100)  # (return, base collisions) of the last 100 reports
        self.recent_control: deque = deque(maxlen=100)  # control steps by chooser of the last 100 reports
        self.registry = CollectorRegistry()
        self.m_episodes = Counter("scheduler_episodes", "episodes reported", ["world", "pair", "outcome"],
                                  registry=self.registry)
        self.m_rejected = Counter("scheduler_messages_rejected", "refused messages", ["reason"], registry=self.registry)
        self.m_advances = Counter("scheduler_advances", "curriculum advances", registry=self.registry)
        self.m_actors = Gauge("scheduler_live_actors", "actors holding a liveliness token", registry=self.registry)
        self.m_actors.set_function(lambda: len(self.actors))
        self.m_lag = Gauge("scheduler_actor_policy_lag", "learner version minus the actor's weights version",
                           ["actor"], registry=self.registry)

    def assign(self, payload: bytes) -> bytes:
        request = AssignmentRequest.decode(payload)
        with self.lock:
            world, pair = self.state.assign()
            st = self.state
            assignment = Assignment(request.actor_id, world, pair, st.current.name, st.substep, st.epoch)
            if request.actor_id in self.waiting:  # a token that waited for room, now at work
                self._make_room(idle_only=False)
                self._admit(request.actor_id)
            entry = self.actors.get(request.actor_id)  # an id without a liveliness token is not kept
            if entry is not None:
                self.active[request.actor_id] = time.monotonic()
                entry["assignment"] = {"world": world, "pair": pair, "stage": st.current.name, "substep": st.substep,
                                       "epoch": st.epoch}
        return assignment.encode()

    def report(self, payload: bytes, sender: str | None = None) -> bool:
        """Count an episode report (``sender``: the actor id of its key); returns True if the
        curriculum advanced."""
        try:
            r = EpisodeReport.decode(payload)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            return False
        with self.lock:
            entry = self.actors.get(r.actor_id)
            reason = ("key_mismatch" if sender is not None and sender != r.actor_id
                      else "unknown_actor" if entry is None else "unassigned" if entry["assignment"] is None
                      else "unknown_world" if r.world not in self.known_worlds
                      else "unknown_pair" if r.pair not in self.known_pairs else None)
            if reason:
                self.m_rejected.labels(reason).inc()
                return False
            self.active[r.actor_id] = time.monotonic()
            self.m_episodes.labels(r.world, r.pair or "random", "success" if r.success else "failure").inc()
            entry["episodes"] += 1
            entry["last_report"] = {"world": r.world, "pair": r.pair, "success": r.success, "return": r.episode_return,
                                    "collisions": r.base_collisions, "steps": r.steps,
                                    "weights_version": r.weights_version, "time": time.time()}
            learner_version = self.services.get("learner", {}).get("version")
            if learner_version is not None:
                self.m_lag.labels(r.actor_id).set(learner_version - r.weights_version)
            self.recent_episodes.append((r.episode_return, r.base_collisions))
            self.recent_control.append(r.control_steps or {NETWORK: r.steps})  # an actor without helpers
            advanced = self.state.record(r.world, r.pair, r.success, r.assignment_epoch, r.steps)
            if advanced:
                self.m_advances.inc()
            return advanced

    def service_status(self, payload: bytes) -> None:
        try:
            s = ServiceStatus.decode(payload)
        except ProtoError as exc:
            self.m_rejected.labels(exc.reason).inc()
            return
        if s.role not in STATUS_ROLES:
            self.m_rejected.labels("unknown_role").inc()
            return
        with self.lock:
            self.services[s.role] = {**s.values, "time": time.time()}

    def actor_joined(self, actor_id: str) -> None:
        if not 0 < len(actor_id) <= MAX_ACTOR_ID:
            self.m_rejected.labels("range").inc()
            return
        with self.lock:
            if actor_id in self.actors:
                return
            if len(self.actors) >= MAX_ACTORS and not self._make_room(idle_only=True):
                self.m_rejected.labels("too_many_actors").inc()
                self._wait(actor_id)
                return
            self._admit(actor_id)

    def _admit(self, actor_id: str) -> None:
        self.waiting.pop(actor_id, None)
        lost = self.lost.pop(actor_id, None)
        if lost is not None:  # taken back: its count goes on; it asks for a world before its reports count
            self.rejoined += 1
        self.actors[actor_id] = {"episodes": lost["episodes"] if lost else 0, "assignment": None,
                                 "last_report": None, "joined": time.time()}
        self.active[actor_id] = time.monotonic()

    def _wait(self, actor_id: str) -> None:
        self.waiting.pop(actor_id, None)
        self.waiting[actor_id] = None
        while len(self.waiting) > MAX_WAITING:
            self.waiting.popitem(last=False)

    def _make_room(self, idle_only: bool) -> bool:
        """Below ``MAX_ACTORS``, or move one actor to the waiting tokens: one idle for ``IDLE_S``
        (the longest idle); unless ``idle_only``, else one that never asked for a world, else the
        longest idle. Returns whether there is room now."""
        if len(self.actors) < MAX_ACTORS:
            return True
        idlest = min(self.active, key=self.active.__getitem__)
        if time.monotonic() - self.active[idlest] < IDLE_S:
            if idle_only:
                return False
            idlest = next((a for a, e in self.actors.items() if e["assignment"] is None), idlest)
        self.m_rejected.labels("evicted_idle").inc()
        self._forget(idlest)
        self._wait(idlest)
        return True

    def _forget(self, actor_id: str) -> None:
        self.actors.pop(actor_id, None)
        self.active.pop(actor_id, None)
        try:
            self.m_lag.remove(actor_id)
        except KeyError:
            pass

    def actor_left(self, actor_id: str) -> None:
        """Its liveliness token went (killed, or its host cut off): marked lost (``MAX_LOST`` kept),
        taken back when the token comes again. The curriculum is not touched: reports count only
        from live actors with an assignment, and assignments carry their epoch."""
        with self.lock:
            self.waiting.pop(actor_id, None)
            entry = self.actors.get(actor_id)
            if entry is not None:
                self.lost.pop(actor_id, None)
                self.lost[actor_id] = {"since": time.time(), "episodes": entry["episodes"]}
                while len(self.lost) > MAX_LOST:
                    self.lost.popitem(last=False)
            self._forget(actor_id)

    def force_advance(self) -> bool:
        with self.lock:
            advanced = self.state.advance("forced by admin")
            if advanced:
                self.m_advances.inc()
            return advanced

    def record_evaluation(self, success_rate: float, episodes: int, epoch: int) -> bool:
        with self.lock:
            advanced = self.state.record_evaluation(success_rate, episodes, epoch)
            if advanced:
                self.m_advances.inc()
            return advanced

    def _shown_actors(self) -> list[str]:
        """The ``STATUS_ACTORS`` actors ``/status`` details: those that reported last."""
        if len(self.actors) <= STATUS_ACTORS:
            return list(self.actors)
        return sorted(self.actors, key=lambda k: (self.actors[k].get("last_report") or {}).get("time", 0.0),
                      reverse=True)[:STATUS_ACTORS]

    def _policy_lag(self, learner_version: int | None) -> float | None:
        """Mean over live actors of (learner version - the weights version of its last episode)."""
        versions = [a["last_report"]["weights_version"] for a in self.actors.values() if a.get("last_report")]
        return None if learner_version is None or not versions else mean([learner_version - v for v in versions])

    def status(self) -> dict:
        with self.lock:
            st = self.state
            rates = {k: {"episodes": v[0], "success_rate": v[1] / v[0] if v[0] else None} for k, v in st.per_world.items()}
            learner = self.services.get("learner", {})
            replay = self.services.get("replay", {})
            return {
                "curriculum": self.curriculum.name, "stage": st.current.name, "stage_index": st.stage,
                "substep": st.substep, "substep_pair": st.current.substeps[st.substep] if st.current.substeps else None,
                "epoch": st.epoch, "episodes": st.episodes, "window_success_rate": st.success_rate(),
                "success_last_100": sum(st.recent) / len(st.recent) if st.recent else None,
                "window_size": len(st.window), "criterion": None if st.criterion is None else vars(st.criterion),
                "success_by_world_pair": rates, "advances": st.history,
                "live_actor_count": len(self.actors),
                "lost_actors": {k: dict(v) for k, v in list(self.lost.items())[-STATUS_ACTORS:]},
                "rejoined_actors": self.rejoined,
                "live_actors": {k: dict(self.actors[k]) for k in self._shown_actors()},
                "return_last_100": mean([e[0] for e in self.recent_episodes]),
                "base_collisions_last_100": mean([e[1] for e in self.recent_episodes]),
                "control_steps_last_100": ControlSteps.summed(self.recent_control).shares(),  # the network first
                "policy_lag": self._policy_lag(learner.get("version")),
                "learner": {k: learner.get(k) for k in ("version", "updates", "updates_per_s", "env_steps",
                                                        "critic_loss", "actor_loss", "q_mean", "uptime_s")},
                "replay": {k: replay.get(k) for k in ("size", "inserted", "accepted", "restored", "insert_rate",
                                                      "sample_rate", "rejected", "uptime_s")},
                "rejected": {s.labels["reason"]: s.value for m in self.m_rejected.collect() for s in m.samples
                             if s.name.endswith("_total")},
            }


class SchedulerService:
    def __init__(self, cfg: SchedulerServiceConfig, experiment: ExperimentConfig) -> None:
        self.cfg = cfg
        self.experiment = experiment
        self.data_dir = Path(cfg.deployment.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if experiment.curriculum.file:
            curriculum = load_curriculum(experiment.curriculum.file)
        else:
            from .curriculum import Stage

            curriculum = Curriculum("no-curriculum", (Stage("train", (experiment.curriculum.world,)),))
        state_path = self.data_dir / "state.json"
        state = None
        if state_path.exists():
            saved = json.loads(state_path.read_text())
            if saved.get("curriculum") == curriculum.name:
                state = CurriculumState.from_dict(curriculum, saved["state"], seed=experiment.seed)
                log.info("resumed curriculum %s at stage %s", curriculum.name, state.current.name)
        self.core = SchedulerCore(curriculum, state or CurriculumState(curriculum, seed=experiment.seed),
                                  extra_worlds=(experiment.curriculum.world,))
        self.saved_episodes = self.core.state.episodes
        self.stop = threading.Event()

    def save(self) -> None:
        path = self.data_dir / "state.json"
        tmp = path.with_suffix(".tmp")
        with self.core.lock:
            self.saved_episodes = self.core.state.episodes
            text = json.dumps({"curriculum": self.core.curriculum.name, "state": self.core.state.to_dict()})
            with open(tmp, "w") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            tmp.replace(path)

    def _authorised(self, request) -> bool:
        token = self.cfg.admin_token
        given = request.headers.get("Authorization", "")
        return bool(token) and hmac.compare_digest(given.encode(), f"Bearer {token}".encode())

    def _admin_evaluation(self, request) -> tuple[int, str, bytes]:
        if not self._authorised(request):
            return json_response({"error": "unauthorised: send Authorization: Bearer <admin token>"}, 401)
        try:
            body = json.loads(request.body or b"")
            rate, episodes, epoch = float(body["success_rate"]), int(body["episodes"]), int(body["epoch"])
            if not 0 <= rate <= 1 or episodes < 1:
                raise ValueError("success_rate in [0, 1], episodes >= 1")
        except (ValueError, KeyError, TypeError, OverflowError) as exc:
            return json_response({"error": f"body must be JSON {{epoch, success_rate, episodes}}: {exc}"}, 400)
        advanced = self.core.record_evaluation(rate, episodes, epoch)
        if advanced:
            self.save()
        return json_response({"advanced": advanced, "stage": self.core.state.current.name,
                              "substep": self.core.state.substep, "epoch": self.core.state.epoch})

    def _admin(self, request) -> tuple[int, str, bytes]:
        if not self._authorised(request):
            return json_response({"error": "unauthorised: send Authorization: Bearer <admin token>"}, 401)
        advanced = self.core.force_advance()
        if advanced:
            self.save()
        return json_response({"advanced": advanced, "stage": self.core.state.current.name,
                              "substep": self.core.state.substep, "epoch": self.core.state.epoch})

    def run(self) -> None:
        core = self.core
        shell = ServiceShell("scheduler", "0", self.cfg.deployment, self.experiment, core.registry,
                             lambda: {"stage": core.state.current.name})
        with shell:
            session = shell.open({
                ("GET", "/status"): lambda r: json_response(core.status()),
                ("GET", "/curriculum"): lambda r: json_response({**core.curriculum.to_dict(),
                                                                 "state": core.state.to_dict()}),
                ("POST", "/admin/advance"): self._admin,
                ("POST", "/admin/evaluation"): self._admin_evaluation,
            })
            topo = shell.topology

            def on_assign(query):
                try:
                    payload = query.payload.to_bytes() if query.payload is not None else b""
                    query.reply(topo.assign, core.assign(payload))
                except ProtoError as exc:
                    core.m_rejected.labels(exc.reason).inc()
                    query.reply_err(str(exc).encode())

            def on_report(sample):
                advanced = core.report(sample.payload.to_bytes(), sender=str(sample.key_expr).rsplit("/", 1)[-1])
                if core.state.episodes != self.saved_episodes:
                    self.save()  # every counted episode is on disk at once: a kill -9 loses none
                if advanced:
                    log.info("curriculum advanced to %s, sub-step %d", core.state.current.name, core.state.substep)

            def on_alive(sample):
                parts = str(sample.key_expr).split("/")
                if len(parts) >= 5 and parts[-2] == "actor":
                    if sample.kind == sample.kind.PUT:
                        core.actor_joined(parts[-1])
                    else:
                        core.actor_left(parts[-1])

            for what, entity in (
                    ("assign queryable", session.declare_queryable(topo.assign, on_assign)),
                    ("report subscriber", session.declare_subscriber(topo.episodes("*"), on_report)),
                    ("status subscriber", session.declare_subscriber(
                        topo.status("*"), lambda s: core.service_status(s.payload.to_bytes()))),
                    ("actor liveliness subscriber", session.liveliness().declare_subscriber(
                        topo.alive("actor", "*"), on_alive, history=True))):
                shell.on_close(what, entity.undeclare)
            log.info("scheduler curriculum %s", core.curriculum.name)
            try:
                while not self.stop.wait(10.0):
                    self.save()
            finally:
                self.save()
