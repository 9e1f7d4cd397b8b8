"""Thin shells shared by the services: Zenoh sessions, the router, HTTP, Prometheus, signals."""

from __future__ import annotations

import json
import logging
import signal
import threading
import time
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

import zenoh
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

log = logging.getLogger("curlnav")


class RouterUnreachable(ConnectionError):
    """The Zenoh router did not answer within the start-up deadline."""


def zenoh_config(mode: str = "client", connect: list[str] | None = None, listen: list[str] | None = None,
                 connect_timeout_s: float = -1) -> zenoh.Config:
    """Multicast scouting off (Docker networks carry none). Clients wait ``connect_timeout_s``
    for their router at start (-1: forever), so services can start in any order."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("connect/timeout_ms", str(-1 if connect_timeout_s < 0 else int(connect_timeout_s * 1000)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    return conf


ROUTER_TIMEOUT_S = -1.0  # set by `curlnav serve --router-timeout-s`


def open_session(router: str, connect_timeout_s: float | None = None) -> zenoh.Session:
    timeout = ROUTER_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
    try:
        return zenoh.open(zenoh_config("client", connect=[router], connect_timeout_s=timeout))
    except zenoh.ZError as exc:
        raise RouterUnreachable(f"cannot reach the Zenoh router at {router} within {timeout:.0f} s: {exc}") from None


def run_router(listen: str, stop: threading.Event, connect: list[str] | None = None) -> None:
    """A Zenoh router (a Python session in router mode) until ``stop`` is set."""
    session = zenoh.open(zenoh_config("router", connect=connect, listen=[listen]))
    try:
        stop.wait()
    finally:
        session.close()


def reliable_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """Reliable and blocking: a slow consumer throttles its producers instead of losing data."""
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                     reliability=zenoh.Reliability.RELIABLE)


Route = Callable[["Request"], tuple[int, str, bytes]]


@dataclass
class Request:
    method: str
    path: str
    headers: dict
    body: bytes


def json_response(obj, status: int = 200) -> tuple[int, str, bytes]:
    return status, "application/json", (json.dumps(obj, indent=1) + "\n").encode()


class HttpServer:
    """A threaded HTTP server. ``routes`` maps (method, path prefix) to handlers; the longest
    matching prefix wins. Unknown paths get 404, bad methods 405, handler errors 500; the
    server keeps running in every case."""

    def __init__(self, host: str, port: int, routes: dict[tuple[str, str], Route],
                 registry: CollectorRegistry | None = None) -> None:
        routes = dict(routes)
        if registry is not None:
            routes[("GET", "/metrics")] = lambda req: (200, CONTENT_TYPE_LATEST, generate_latest(registry))
        table = sorted(routes.items(), key=lambda item: -len(item[0][1]))

        class Handler(BaseHTTPRequestHandler):
            def _handle(self, method: str) -> None:
                path = self.path.split("?", 1)[0]
                length = int(self.headers.get("Content-Length") or 0)
                body = self.rfile.read(min(length, 1 << 20)) if length > 0 else b""
                matched = [(m, prefix, fn) for (m, prefix), fn in table
                           if path == prefix or (prefix.endswith("/") and path.startswith(prefix))]
                if not matched:
                    status, ctype, payload = json_response({"error": f"no such path {path}"}, 404)
                else:
                    chosen = [fn for m, _, fn in matched if m == method]
                    if not chosen:
                        status, ctype, payload = json_response({"error": f"{method} not allowed on {path}"}, 405)
                    else:
                        try:
                            status, ctype, payload = chosen[0](Request(method, path, dict(self.headers), body))
                        except Exception as exc:  # a handler bug must not take the service down
                            log.exception("HTTP handler failed for %s", path)
                            status, ctype, payload = json_response({"error": f"{type(exc).__name__}: {exc}"}, 500)
                self.send_response(status)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(payload)))
                self.end_headers()
                self.wfile.write(payload)

            def do_GET(self):  # noqa: N802
                self._handle("GET")

            def do_POST(self):  # noqa: N802
                self._handle("POST")

            def log_message(self, *args):  # quiet
                pass

        self.server = ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def stop_on_signals(stop: threading.Event) -> None:
    """SIGTERM, SIGINT and SIGHUP set ``stop``; services then save their state and exit cleanly."""
    def handler(signum, frame):
        stop.set()

    for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        if signal.getsignal(signum) is not signal.SIG_IGN:  # nohup: a hang-up stays ignored
            signal.signal(signum, handler)


class RateMeter:
    """Events per second over the last ``window`` seconds."""

    def __init__(self, window: float = 10.0) -> None:
        self.window = window
        self.events: list[tuple[float, float]] = []
        self.lock = threading.Lock()

    def add(self, n: float = 1.0) -> None:
        now = time.monotonic()
        with self.lock:
            self.events.append((now, n))
            while self.events and now - self.events[0][0] > self.window:
                self.events.pop(0)

    def rate(self) -> float:
        now = time.monotonic()
        with self.lock:
            recent = [n for t, n in self.events if now - t <= self.window]
            if not recent:
                return 0.0
            span = max(now - self.events[0][0], 1e-3)
            return sum(recent) / max(span, min(self.window, 1.0))
