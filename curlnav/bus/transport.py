"""Thin shells shared by the services: Zenoh sessions, the router, HTTP, Prometheus, signals."""

from __future__ import annotations

import json
import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import zenoh
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from curlnav.bus.security import BusUser, RouterAuth, load_router

log = logging.getLogger("curlnav")


class RouterUnreachable(ConnectionError):
    """The Zenoh router did not answer within the start-up deadline."""


def zenoh_config(mode: str = "client", connect: list[str] | None = None, listen: list[str] | None = None,
                 connect_timeout_s: float = -1, user: BusUser | None = None,
                 guard: RouterAuth | None = None) -> zenoh.Config:
    """Multicast scouting off (Docker networks carry none). Clients wait ``connect_timeout_s``
    for their router at start (-1: forever), so services can start in any order. ``user``: the
    bus user this session authenticates as (Zenoh usrpwd); ``guard``: a router's dictionary of
    users and access control (``curlnav.bus.security``)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("connect/timeout_ms", str(-1 if connect_timeout_s < 0 else int(connect_timeout_s * 1000)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    user = guard.user if guard is not None else user
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(user.password))
    if guard is not None:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(guard.users_file)))
        conf.insert_json5("access_control", json.dumps(guard.access_control))
    return conf


ROUTER_TIMEOUT_S = -1.0  # set by `curlnav serve --router-timeout-s`


def open_session(router: str, connect_timeout_s: float | None = None, user: BusUser | None = None) -> zenoh.Session:
    """A client session to ``router``, authenticated as ``user`` when given."""
    timeout = ROUTER_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
    try:
        return zenoh.open(zenoh_config("client", connect=[router], connect_timeout_s=timeout, user=user))
    except zenoh.ZError as exc:
        refused = f" (or it refused the bus user {user.user!r}: another run's credentials?)" if user else ""
        raise RouterUnreachable(f"cannot reach the Zenoh router at {router} within {timeout:.0f} s{refused}: "
                                f"{exc}") from None


def run_router(listen: str, stop: threading.Event, connect: list[str] | None = None, credentials: str = "") -> None:
    """A Zenoh router (a Python session in router mode) until ``stop`` is set. ``credentials``:
    a run's bus credentials folder (or the router's own): the router then admits only the run's
    users and applies the run's access control."""
    guard = load_router(credentials) if credentials else None
    if guard is not None:
        log.info("bus: user-password authentication (%d users), access control for run %r, default deny",
                 sum(1 for line in guard.users_file.read_text().splitlines() if line.strip()), guard.user.run)
    else:
        log.warning("bus: no credentials: anyone who reaches this router may publish and query (--bus-credentials)")
    session = zenoh.open(zenoh_config("router", connect=connect, listen=[listen], guard=guard))
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
    matching prefix wins. Unknown paths get 404, other methods (HEAD, PUT, ...) 405, handler
    errors 500; the server keeps running in every case.

    Limits, so that no client can hold the service: a listen backlog of ``backlog`` connections
    (with 128, a third of a burst of 200 connects waited for the kernel's 1 s SYN retry); every
    socket operation of a connection times out after ``timeout_s`` (a silent or slow client is
    dropped); at most ``max_threads`` connections are handled at once, and beyond that new
    connections wait in the backlog until a handler thread is free (no 503: a burst is served
    late rather than refused). One request per connection (HTTP/1.0). A
    ``Content-Length`` that is not a non-negative integer gets 400, a body above ``max_body``
    bytes 413 (not read); malformed request lines and headers 400/431. Every error is JSON,
    and client mistakes are never logged as tracebacks."""

    def __init__(self, host: str, port: int, routes: dict[tuple[str, str], Route],
                 registry: CollectorRegistry | None = None, *, backlog: int = 1024, timeout_s: float = 10.0,
                 max_threads: int = 64, max_body: int = 1 << 20) -> None:
        routes = dict(routes)
        if registry is not None:
            routes[("GET", "/metrics")] = lambda req: (200, CONTENT_TYPE_LATEST, generate_latest(registry))
        table = sorted(routes.items(), key=lambda item: -len(item[0][1]))

        def respond(path: str, method: str, request: Callable[[], Request]) -> tuple[int, str, bytes]:
            matched = [(m, fn) for (m, prefix), fn in table
                       if path == prefix or (prefix.endswith("/") and path.startswith(prefix))]
            if not matched:
                return json_response({"error": f"no such path {path}"}, 404)
            chosen = [fn for m, fn in matched if m == method]
            if not chosen:
                return json_response({"error": f"{method} not allowed on {path}"}, 405)
            try:
                return chosen[0](request())
            except Exception as exc:  # a handler bug must not take the service down
                log.exception("HTTP handler failed for %s", path)
                return json_response({"error": f"{type(exc).__name__}: {exc}"}, 500)

        class Handler(BaseHTTPRequestHandler):
            timeout = timeout_s  # every recv/send of the connection (StreamRequestHandler.setup)

            def _reply(self, status: int, ctype: str, payload: bytes) -> None:
                self.send_response(status)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(payload)))
                if status >= 400:
                    self.send_header("Connection", "close")
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(payload)

            def _handle(self) -> None:
                method, path = self.command, self.path.split("?", 1)[0]
                if self.headers.get("Transfer-Encoding"):
                    return self._reply(*json_response({"error": "send the body with Content-Length"}, 400))
                lengths = {v.strip() for v in self.headers.get_all("Content-Length") or []}
                raw = next(iter(lengths)) if len(lengths) == 1 else "0" if not lengths else ", ".join(sorted(lengths))
                if not (raw.isascii() and raw.isdigit() and len(raw) < 20):
                    return self._reply(*json_response({"error": f"bad Content-Length {raw[:40]!r}"}, 400))
                length = int(raw)
                if length > max_body:
                    return self._reply(*json_response({"error": f"body of {length} bytes, above {max_body}"}, 413))
                try:
                    body = self.rfile.read(length) if length else b""
                except TimeoutError:  # a slow or silent client: answered (if it still listens) and dropped
                    return self._reply(*json_response({"error": f"no body within {timeout_s:g} s"}, 408))
                if len(body) < length:  # the client closed before sending its body
                    return self._reply(*json_response({"error": "body shorter than Content-Length"}, 400))
                self._reply(*respond(path, method, lambda: Request(method, path, dict(self.headers), body)))

            def __getattr__(self, name: str):
                if name.startswith("do_"):  # every method: GET/POST routes, 404 or 405 for the rest
                    return self._handle
                raise AttributeError(name)

            def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
                """http.server's own errors (bad request line, headers, ...) as JSON."""
                short = self.responses.get(code, ("error",))[0]
                self.close_connection = True
                if not str(getattr(self, "request_version", "")).startswith("HTTP/1."):
                    self.request_version = "HTTP/1.0"  # a broken request line still gets a status line
                self._reply(*json_response({"error": message or short}, code))

            def log_message(self, *args):  # quiet
                pass

        class Server(ThreadingHTTPServer):
            request_queue_size = backlog
            daemon_threads = True
            slots = threading.BoundedSemaphore(max_threads)
            closing = threading.Event()

            def process_request(self, request, client_address):
                while not self.slots.acquire(timeout=0.2):  # all threads busy: the backlog waits
                    if self.closing.is_set():
                        self.shutdown_request(request)
                        return
                try:
                    super().process_request(request, client_address)
                except BaseException:
                    self.slots.release()
                    raise

            def process_request_thread(self, request, client_address):
                try:
                    self.finish_request(request, client_address)
                except Exception as exc:  # a reset or timed-out client: one line, no traceback
                    log.debug("HTTP connection from %s dropped: %r", client_address, exc)
                finally:
                    self.shutdown_request(request)
                    self.slots.release()

        self.server = Server((host, port), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.closing.set()
        self.server.shutdown()
        self.server.server_close()


#: the signals that stop a service or a run, with the words a person reads
STOP_SIGNALS = {signal.SIGINT: "SIGINT (Ctrl-C)", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP (terminal closed)"}


def on_stop_signals(handler: Callable[[int, object], None]) -> dict:
    """Route ``STOP_SIGNALS`` to ``handler``, except one already ignored (under ``nohup`` a
    hang-up stays ignored). Returns the previous dispositions, for ``restore_signals``."""
    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    for signum, before in previous.items():
        if before is not signal.SIG_IGN:
            signal.signal(signum, handler)
    return previous


def ignore_stop_signals() -> None:
    """During an orderly stop: a second Ctrl-C must not cut it short."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


def restore_signals(previous: dict) -> None:
    for signum, handler in previous.items():
        signal.signal(signum, handler)


def stop_on_signals(stop: threading.Event) -> None:
    """SIGTERM, SIGINT and SIGHUP set ``stop``; services then save their state and exit cleanly."""
    on_stop_signals(lambda signum, frame: stop.set())


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
