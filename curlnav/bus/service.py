"""The one service base: Zenoh session, the run's config agreement, liveliness, HTTP, metrics,
teardown. Every service (replay, learner, scheduler, actor) is a pure core plus a thin shell
built on ``ServiceShell``.

Config agreement: every service answers ``config/<role>/<id>`` with the ``ExperimentConfig`` it
runs (``RunConfig``: hash and JSON). A service joining a run declares its own answer, then asks
every service there; if any runs another config (every section but ``budget`` and
``evaluation``, which only the launcher reads), it refuses to join (``ConfigMismatch``: one line
naming the service and the first fields that differ; ``curlnav serve`` exits 2). Services may
start in any order, even at once: the later one, or both, notice.

Only the services that own the run's config answer and are believed (``CONFIG_OWNERS``: replay,
learner, scheduler), on their own key: an actor (which holds credentials any actor holds) can
never make another service refuse to join. An actor checks the owners' configs when it joins
and again every ``RECHECK_S`` while it runs (``recheck_agreement``), so an actor that started
before a service of another config still notices and stops.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from prometheus_client import CollectorRegistry

from curlnav.bus.security import CONFIG_OWNERS, load_user
from curlnav.bus.transport import HttpServer, Route, json_response, open_session
from curlnav.config import ExperimentConfig, config_differences, config_to_dict, service_config_hash
from curlnav.proto.codec import ProtoError
from curlnav.proto.messages import RunConfig
from curlnav.proto.topology import Topology

log = logging.getLogger("curlnav.bus.service")

CONFIG_QUERY_TIMEOUT_S = 3.0  # how long a joining service listens for the run's configs
RECHECK_S = 60.0  # how often a service that answers no config queries asks again


class ConfigMismatch(RuntimeError):
    """A service of the run already runs another experiment config."""


@dataclass(frozen=True)
class Deployment:
    """Where and how a service runs; nothing here changes what is learned."""

    run: str = "default"  # run name: the Zenoh key prefix
    router: str = "tcp/127.0.0.1:7447"  # Zenoh router endpoint
    data_dir: str = "runs/service"  # the service's own state folder
    http_host: str = "127.0.0.1"  # HTTP bind address (/healthz, /metrics, /config, ...); `curlnav serve`: 0.0.0.0
    http_port: int = 0  # 0: any free port (written to <data_dir>/http_port)
    credentials: str = ""  # the run's bus credentials folder (or this role's): "" = no bus authentication


def _shared_part(config: dict) -> dict:
    return {k: v for k, v in config.items() if k not in ("budget", "evaluation")}


def check_agreement(own: ExperimentConfig, replies: list[RunConfig]) -> None:
    """Raise ``ConfigMismatch`` if any reply carries another config than ``own`` (compared on
    ``service_config_hash``: the budget and evaluation sections are the launcher's own, actor each actor's)."""
    own_hash = service_config_hash(own)
    for reply in replies:
        if reply.config_hash == own_hash or reply.role not in CONFIG_OWNERS:
            continue
        try:
            theirs = json.loads(reply.config_json)
            diffs = config_differences(_shared_part(config_to_dict(own)), _shared_part(theirs))
        except ValueError:
            diffs = []
        detail = "; ".join(diffs[:3]) + (f" (+{len(diffs) - 3} more)" if len(diffs) > 3 else "")
        raise ConfigMismatch(f"the run's {reply.role} {reply.instance} runs service-agreement hash "
                             f"{reply.config_hash[:12]}, this service {own_hash[:12]}: {detail or 'they differ'} "
                             "(this service's value first)")


class ServiceShell:
    """Opens and closes everything a service needs on the network, in order.

    ``open(routes)`` connects to the router, checks the run's config agreement, answers config
    queries, declares the liveliness token and starts the HTTP server (``/healthz`` from
    ``health``, ``/metrics`` from ``registry``, ``/config``, plus ``routes``); ``close()`` undoes
    all of it in reverse, whatever failed. Usable as a context manager.
    """

    def __init__(self, role: str, instance: str, deployment: Deployment, experiment: ExperimentConfig,
                 registry: CollectorRegistry, health: Callable[[], dict]) -> None:
        self.role = role
        self.instance = instance
        self.deployment = deployment
        self.experiment = experiment
        self.registry = registry
        self.health = health
        self.topology = Topology(deployment.run)
        self.config_hash = service_config_hash(experiment)
        self.data_dir = Path(deployment.data_dir)
        self.session = None
        self.http: HttpServer | None = None
        self._closers: list[tuple[str, Callable[[], object]]] = []
        self._lock = threading.Lock()

    def on_close(self, what: str, fn: Callable[[], object]) -> None:
        """Run ``fn`` at ``close()`` (last registered, first run)."""
        with self._lock:
            self._closers.append((what, fn))

    def open(self, routes: dict[tuple[str, str], Route] | None = None):
        """Connect and announce; returns the Zenoh session. Raises ``ConfigMismatch`` (nothing
        left open) when the run already runs another config."""
        try:
            self.session = session = self.new_session()
            # answer first, then ask: two services starting together see each other
            if self.role in CONFIG_OWNERS:
                reply = RunConfig(self.role, self.instance, self.config_hash,
                                  json.dumps(config_to_dict(self.experiment), sort_keys=True)).encode()
                key = self.topology.config(self.role, self.instance)
                queryable = session.declare_queryable(key, lambda q: q.reply(key, reply))
                self.on_close("config queryable", queryable.undeclare)
            self.recheck_agreement(force=True)
            token = session.liveliness().declare_token(self.topology.alive(self.role, self.instance))
            self.on_close("liveliness token", token.undeclare)
            all_routes = {("GET", "/healthz"): lambda r: json_response({"ok": True, **self.health()}),
                          ("GET", "/config"): lambda r: json_response({"hash": self.config_hash,
                                                                        "config": config_to_dict(self.experiment)}),
                          **(routes or {})}
            self.http = HttpServer(self.deployment.http_host, self.deployment.http_port, all_routes,
                                   registry=self.registry)
            self.on_close("HTTP server", self.http.close)
            self.data_dir.mkdir(parents=True, exist_ok=True)
            (self.data_dir / "http_port").write_text(str(self.http.port))
        except BaseException:
            self.close()
            raise
        log.info("%s %s up: run %s, router %s, http port %d, service-agreement hash %s", self.role, self.instance,
                 self.deployment.run, self.deployment.router, self.http.port, self.config_hash[:12])
        return session

    def new_session(self):
        """Another Zenoh session to the router, closed with the shell."""
        credentials = self.deployment.credentials
        ident = self.instance if self.role == "actor" else None  # an actor authenticates as itself
        user = load_user(credentials, self.role, self.deployment.run, ident) if credentials else None
        session = open_session(self.deployment.router, user=user)
        self.on_close("Zenoh session", session.close)
        return session

    _checked_at = float("-inf")

    def recheck_agreement(self, force: bool = False) -> None:
        """Ask the run's config owners again (at most every ``RECHECK_S`` unless ``force``);
        ``ConfigMismatch`` if one runs another config."""
        if not force and time.monotonic() - self._checked_at < RECHECK_S:
            return
        self._checked_at = time.monotonic()
        check_agreement(self.experiment, [c for c in self.run_configs()
                                          if (c.role, c.instance) != (self.role, self.instance)])

    def run_configs(self) -> list[RunConfig]:
        """The configs of the run's config owners (``CONFIG_OWNERS``), each believed only on its
        own key ``config/<role>/<instance>``; malformed and other replies are skipped."""
        out = []
        for reply in self.session.get(self.topology.config("*", "*"), timeout=CONFIG_QUERY_TIMEOUT_S):
            if reply.ok is None:
                continue
            try:
                config = RunConfig.decode(reply.ok.payload.to_bytes())
            except ProtoError:
                log.warning("%s: ignored a malformed run config reply", self.role)
                continue
            if config.role not in CONFIG_OWNERS or str(reply.ok.key_expr) != self.topology.config(config.role,
                                                                                                config.instance):
                log.warning("%s: ignored a run config answered on %s for %s %s (only %s answer, on their own key)",
                            self.role, str(reply.ok.key_expr)[:200], config.role[:40], config.instance[:40],
                            "/".join(CONFIG_OWNERS))
                continue
            out.append(config)
        return out

    def close(self) -> None:
        with self._lock:
            closers, self._closers = self._closers, []
        for what, fn in reversed(closers):
            try:
                fn()
            except Exception:  # teardown goes on: one failure must not leave the rest open
                log.exception("%s: closing the %s failed", self.role, what)

    def __enter__(self) -> ServiceShell:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
