"""Thin shells shared by the services: Zenoh sessions, the router, HTTP, Prometheus, signals."""

from __future__ import annotations

import contextlib
import io
import ipaddress
import json
import logging
import os
import queue
import re
import selectors
import signal
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler

import zenoh
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from curlnav.bus.security import BusUser, RouterAuth, TlsFiles, load_router, load_tls

log = logging.getLogger("curlnav")


class RouterUnreachable(ConnectionError):
    """The Zenoh router did not answer within the start-up deadline."""


def zenoh_config(mode: str = "client", connect: list[str] | None = None, listen: list[str] | None = None,
                 connect_timeout_s: float = -1, user: BusUser | None = None,
                 guard: RouterAuth | None = None, tls: TlsFiles | None = None) -> zenoh.Config:
    """Multicast scouting off (Docker networks carry none). Clients wait ``connect_timeout_s``
    for their router at start (-1: forever), so services can start in any order. ``user``: the
    bus user this session authenticates as (Zenoh usrpwd); ``guard``: a router's dictionary of
    users and access control (``curlnav.bus.security``); ``tls``: the run's CA and this router's
    certificate for its ``tls/`` links, mutual (each side shows a certificate of the run's CA; the
    connecting side checks that the other's names the address it dialled)."""
    conf = zenoh.Config()
    if tls is not None:
        for key, value in (("root_ca_certificate", tls.ca), ("listen_certificate", tls.certificate),
                           ("listen_private_key", tls.key), ("connect_certificate", tls.certificate),
                           ("connect_private_key", tls.key)):
            conf.insert_json5(f"transport/link/tls/{key}", json.dumps(str(value)))
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/verify_name_on_connect", "true")
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if connect and mode == "router":  # other routers may be down or cut off: start anyway, retry for ever
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("connect/timeout_ms", "-1")  # with exit_on_failure false: in the background (measured)
        conf.insert_json5("connect/exit_on_failure", "false")
        conf.insert_json5("connect/retry", '{"period_init_ms": 500, "period_max_ms": 2000, "period_increase_factor": 2}')
    elif connect:
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


LINK_ACK_TIMEOUT_S = 10.0  # Zenoh's link lease (transport/link/tx/lease, 10 s by default)


class LinkAckTimeout:
    """``TCP_USER_TIMEOUT`` (``seconds``) on every TCP connection of this process to another host:
    the kernel drops a connection whose sent data stays unacknowledged that long.

    Why (issue 30): Zenoh closes a link whose lease expired by flushing its TLS stream first, with
    no time limit (zenoh-link-tls ``close``: ``flush().await``, then ``shutdown``). When a router
    still had data queued for a host that was cut off, that flush waits on a socket whose peer
    never acknowledges, as long as the kernel retransmits (``tcp_retries2``: about 15 minutes), so
    the transport is never deleted: the cut-off host's tokens and subscriptions stay declared, and
    when its router reconnects (same Zenoh id) the new link joins that stale transport while the
    other side starts afresh. The two routers' routing state then disagree (``Unknown wire expr``
    on the reconnected side): nothing reaches the host's actors (not the replay's credit, so they
    resend nothing) and the scheduler never sees their tokens go or come, until a TCP
    retransmission after the heal happens to draw a reset (tens of seconds to minutes). Zenoh has
    no setting for this, so the router process sets the socket option itself: the stuck flush then
    fails with the connection after a lease, the transport is deleted, and the reconnection after
    the heal is a clean new session. Loopback connections (a host's own services) are left alone:
    no partition happens there, and a service busy for a while must not lose its session.

    A thread looks at the process's sockets (``/proc/self/fd``) every ``every_s`` and sets the
    option once per new connection (on a duplicate of its descriptor: the socket is shared, the
    duplicate closed). Linux only; elsewhere ``available`` is False and nothing runs."""

    def __init__(self, seconds: float = LINK_ACK_TIMEOUT_S, every_s: float = 1.0) -> None:
        self.ms = int(seconds * 1000)
        self.every_s = every_s
        self.available = hasattr(socket, "TCP_USER_TIMEOUT") and os.path.isdir("/proc/self/fd")
        self.count = 0  # connections given the timeout
        self._done: set[str] = set()  # sockets ("socket:[inode]") looked at for good
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def sweep(self) -> int:
        """Set the timeout on the connections not seen yet; returns how many got it now."""
        if not self.available:
            return 0
        try:
            names = os.listdir("/proc/self/fd")
        except OSError:
            return 0
        seen, now = set(), 0
        for name in names:
            try:
                target = os.readlink(f"/proc/self/fd/{name}")
            except OSError:  # closed meanwhile
                continue
            if not target.startswith("socket:"):
                continue
            seen.add(target)
            if target in self._done:
                continue
            try:
                sock = socket.socket(fileno=os.dup(int(name)))  # the family and type are read from it
            except OSError:
                continue
            try:
                if sock.type != socket.SOCK_STREAM or sock.family not in (socket.AF_INET, socket.AF_INET6):
                    self._done.add(target)
                    continue
                try:
                    peer = ipaddress.ip_address(sock.getpeername()[0].split("%", 1)[0])
                except OSError:  # listening, or still connecting: looked at again next time
                    continue
                peer = getattr(peer, "ipv4_mapped", None) or peer
                if not peer.is_loopback:
                    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, self.ms)
                    now += 1
                self._done.add(target)
            except (OSError, ValueError):
                pass
            finally:
                sock.close()  # the duplicate only
        self._done &= seen
        self.count += now
        return now

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            added = self.sweep()
            if added:
                log.debug("bus: TCP user timeout %d ms on %d more link(s) (%d in all)", self.ms, added, self.count)

    def start(self) -> LinkAckTimeout:
        if self.available:
            self.sweep()
            self._thread = threading.Thread(target=self._run, daemon=True, name="link-ack-timeout")
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)


def run_router(listen: str | list[str], stop: threading.Event, connect: list[str] | None = None,
               credentials: str = "", audit: bool = True, tls_name: str = "") -> None:
    """A Zenoh router (a Python session in router mode) until ``stop`` is set. ``listen``: one
    endpoint or several. ``credentials``: a run's bus credentials folder (or the router's own):
    the router then admits only the run's users and applies the run's access control, and
    (``audit``) counts and logs every message it refuses (``curlnav.bus.audit``: it takes over the
    process's stdout, so only in a router process of its own). ``tls_name``: this router's name in
    the run's TLS folder (``curlnav bus credentials --tls NAME=ADDRESS``): its ``tls/`` endpoints,
    listening and connecting, use mutual TLS with the run's CA."""
    listen = [listen] if isinstance(listen, str) else list(listen)
    tls = load_tls(credentials, tls_name) if tls_name else None
    from curlnav.bus.audit import DenialAudit

    guard = load_router(credentials) if credentials else None
    denials = None
    if guard is not None:
        log.info("bus: user-password authentication (%d users), access control for run %r, default deny",
                 sum(1 for line in guard.users_file.read_text().splitlines() if line.strip()), guard.user.run)
        denials = DenialAudit().start() if audit else None
    else:
        log.warning("bus: no credentials: anyone who reaches this router may publish and query (--bus-credentials)")
    if tls is not None:
        log.info("bus: mutual TLS on tls/ links as router %r (CA %s)", tls_name, tls.ca)
    session = zenoh.open(zenoh_config("router", connect=connect, listen=listen, guard=guard, tls=tls))
    links = LinkAckTimeout().start()  # links to other hosts end within a lease of a partition (see there)
    if links.available:
        log.info("bus: TCP user timeout %g s on links to other hosts", links.ms / 1000)
    else:
        log.warning("bus: no TCP_USER_TIMEOUT here: after a partition longer than the link lease this router may "
                    "keep a stale session to the cut-off host until the kernel gives up on it")
    try:
        stop.wait()
    finally:
        links.stop()
        session.close()
        if denials is not None:
            denials.stop()


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


class _SocketWriter(io.BufferedIOBase):
    """``wfile`` of a handler: every write is one ``sendall`` (bounded by the socket timeout)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        self._sock.sendall(b)
        return len(b)


@dataclass
class _Incoming:
    """A connection still sending its request: read by the server's loop, no thread held."""

    sock: socket.socket
    client: str  # the client's address
    started: float  # time.monotonic() of the connect
    deadline: float  # time.monotonic() by which the whole request (head and body) must be in
    data: bytearray
    head_end: int = -1  # index just past the blank line that ends the head; -1: not yet
    need: int = -1  # bytes to wait for in all (head + Content-Length); -1: head not complete
    oversize: bool = False  # the head passed its budget: discarded until its end, then 431


_HEAD_END = re.compile(rb"\r?\n\r?\n")
_CONTENT_LENGTH = re.compile(rb"(?im)^content-length[ \t]*:[ \t]*([^\r\n]*)")


class HttpServer:
    """A threaded HTTP server. ``routes`` maps (method, path prefix) to handlers; the longest
    matching prefix wins. Unknown paths get 404, other methods (HEAD, PUT, ...) 405, handler
    errors 500; the server keeps running in every case.

    Limits, so that no client can hold the service:

    - one loop reads every request (head and body) without a thread, so slow or silent clients
      hold no handler thread; a request reaches a handler only once it is complete;
    - the whole request (head and body) must arrive within ``timeout_s`` of the connect, however
      it trickles in: past it, a silent or slow client is dropped (a partial body gets 408);
      every reply write times out after ``timeout_s`` too;
    - a head above ``max_head`` bytes in all (64 KiB) gets 431, a ``Content-Length`` that is not a
      non-negative integer 400, a body above ``max_body`` bytes 413 (not read);
    - a connection still sending its request ``slow_s`` (1 s) after it connected is slow (an
      honest request is read within milliseconds): at most ``max_per_client`` slow connections
      per client address, the oldest beyond are closed (a client pushes out only its own);
    - at most ``max_connections`` connections in all; when they are open, a new one closes the
      oldest slow connection, or waits in the listen backlog of ``backlog`` connections (with
      128, a third of a burst of 200 connects waited for the kernel's 1 s SYN retry);
    - at most ``max_threads`` handlers run at once; further complete requests wait for one (a
      burst is served late rather than refused).

    One request per connection (HTTP/1.0). Malformed request lines and headers get 400/431.
    Every error is JSON, and client mistakes are never logged as tracebacks."""

    def __init__(self, host: str, port: int, routes: dict[tuple[str, str], Route],
                 registry: CollectorRegistry | None = None, *, backlog: int = 1024, timeout_s: float = 10.0,
                 max_threads: int = 64, max_body: int = 1 << 20, max_head: int = 64 << 10,
                 max_connections: int = 512, max_per_client: int = 32, slow_s: float = 1.0) -> None:
        routes = dict(routes)
        if registry is not None:
            routes[("GET", "/metrics")] = lambda req: (200, CONTENT_TYPE_LATEST, generate_latest(registry))
        table = sorted(routes.items(), key=lambda item: -len(item[0][1]))
        self.timeout_s, self.max_body, self.max_head = timeout_s, max_body, max_head
        self.max_connections, self.max_per_client, self.slow_s = max_connections, max_per_client, slow_s

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
            """Parses and answers one request that the loop has read in full (``request`` is
            ``(socket, bytes)``)."""

            def setup(self) -> None:
                self.connection, data = self.request
                self.connection.settimeout(timeout_s)  # every reply write
                self.rfile = io.BytesIO(data)
                self.wfile = _SocketWriter(self.connection)

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
                body = self.rfile.read(length) if length else b""
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

        self._handler = Handler
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host, port), family=family, backlog=backlog)
        self._listener.setblocking(False)
        self.port = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._open = 0  # connections open: reading, waiting for a handler or answered
        self._complete: queue.SimpleQueue = queue.SimpleQueue()  # (socket, client, request bytes) or None
        self._closing = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self.workers = [threading.Thread(target=self._work, daemon=True, name=f"http-{i}") for i in range(max_threads)]
        for worker in self.workers:
            worker.start()
        self.thread = threading.Thread(target=self._loop, daemon=True, name="http-loop")
        self.thread.start()

    # -- the loop: accept, read requests, enforce deadlines and caps --------------------------------
    def _loop(self) -> None:
        selector = selectors.DefaultSelector()
        selector.register(self._wake_r, selectors.EVENT_READ)
        selector.register(self._listener, selectors.EVENT_READ)
        listening = True
        incoming: dict[socket.socket, _Incoming] = {}  # insertion order: oldest first
        try:
            while not self._closing.is_set():
                now = time.monotonic()
                wait = min([c.deadline for c in incoming.values()], default=now + 1.0) - now
                for key, _ in selector.select(max(0.0, min(wait, 1.0 if listening else 0.1))):
                    if key.fileobj is self._wake_r:
                        with contextlib.suppress(OSError):
                            self._wake_r.recv(4096)
                    elif key.fileobj is self._listener:
                        self._accept(selector, incoming)
                    else:
                        self._read(selector, incoming, incoming.get(key.fileobj))
                self._sweep(selector, incoming)
                with self._lock:
                    full = self._open >= self.max_connections
                room = not full or self._oldest_slow(incoming) is not None
                if listening and not room:
                    selector.unregister(self._listener)  # the backlog holds new connections
                elif room and not listening:
                    selector.register(self._listener, selectors.EVENT_READ)
                listening = room
        finally:
            for conn in list(incoming.values()):
                self._drop(selector, incoming, conn, None, "")
            selector.close()

    def _oldest_slow(self, incoming: dict, client: str | None = None) -> _Incoming | None:
        slow_since = time.monotonic() - self.slow_s
        return next((c for c in incoming.values() if c.started <= slow_since and client in (None, c.client)), None)

    def _sweep(self, selector, incoming: dict) -> None:
        """Close the connections past their deadline, and each address's slow ones beyond its cap."""
        now = time.monotonic()
        for conn in [c for c in incoming.values() if c.deadline <= now]:
            if conn.oversize:
                self._drop(selector, incoming, conn, 431, f"request head above {self.max_head} bytes")
            else:  # a partial body is answered (as a slow body always was); a head, silently dropped
                self._drop(selector, incoming, conn, 408 if conn.head_end >= 0 else None,
                           f"no complete request within {self.timeout_s:g} s")
        slow: dict[str, list[_Incoming]] = {}
        for conn in incoming.values():  # oldest first
            if conn.started <= now - self.slow_s:
                slow.setdefault(conn.client, []).append(conn)
        for conns in slow.values():
            for conn in conns[:max(0, len(conns) - self.max_per_client)]:
                self._drop(selector, incoming, conn, None, "")

    def _accept(self, selector, incoming: dict) -> None:
        for _ in range(64):  # a burst: take what the backlog holds, then read the requests
            with self._lock:
                full = self._open >= self.max_connections
            if full:
                oldest = self._oldest_slow(incoming)
                if oldest is None:
                    return
                self._drop(selector, incoming, oldest, None, "")
            try:
                sock, address = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # out of file descriptors, ...: the backlog keeps the rest
                log.debug("HTTP accept failed: %r", exc)
                return
            sock.setblocking(False)
            with self._lock:
                self._open += 1
            now = time.monotonic()
            conn = _Incoming(sock, str(address[0]), now, now + self.timeout_s, bytearray())
            incoming[sock] = conn
            selector.register(sock, selectors.EVENT_READ)
            self._read(selector, incoming, conn)  # most requests are there already

    def _read(self, selector, incoming: dict, conn: _Incoming | None) -> None:
        if conn is None:
            return
        try:
            chunk = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            chunk = b""
        if not chunk:  # the client closed: a complete head goes on (the handler says what is missing)
            if conn.head_end >= 0:
                self._dispatch(selector, incoming, conn)
            else:
                self._drop(selector, incoming, conn, None, "")
            return
        if conn.oversize:  # past the head budget: discard up to the blank line, then answer 431
            tail = bytes(conn.data[-3:]) + chunk
            if _HEAD_END.search(tail):
                self._drop(selector, incoming, conn, 431, f"request head above {self.max_head} bytes")
            else:
                conn.data = bytearray(tail[-3:])
            return
        start = max(0, len(conn.data) - 3)
        conn.data += chunk
        if conn.head_end < 0:
            end = _HEAD_END.search(conn.data, start)
            if end is None or end.end() > self.max_head:
                if end is not None:
                    self._drop(selector, incoming, conn, 431, f"request head above {self.max_head} bytes")
                elif len(conn.data) > self.max_head:
                    conn.oversize, conn.data = True, conn.data[-3:]
                return
            conn.head_end = end.end()
            lengths = {v.strip() for v in _CONTENT_LENGTH.findall(bytes(conn.data[:conn.head_end]))}
            raw = lengths.pop() if len(lengths) == 1 else b""
            length = int(raw) if raw.isascii() and raw.isdigit() and len(raw) < 20 else 0  # else the handler answers 400
            conn.need = conn.head_end + (length if length <= self.max_body else 0)  # 413 without the body
        if len(conn.data) >= conn.need:
            self._dispatch(selector, incoming, conn)

    def _dispatch(self, selector, incoming: dict, conn: _Incoming) -> None:
        selector.unregister(conn.sock)
        del incoming[conn.sock]
        conn.sock.setblocking(True)
        self._complete.put((conn.sock, conn.client, bytes(conn.data)))

    def _drop(self, selector, incoming: dict, conn: _Incoming, status: int | None, why: str) -> None:
        with contextlib.suppress(KeyError, ValueError):
            selector.unregister(conn.sock)
        incoming.pop(conn.sock, None)
        if status is not None:
            with contextlib.suppress(OSError):
                conn.sock.send(_error_bytes(status, why))
                conn.sock.shutdown(socket.SHUT_WR)
        self._release(conn.sock, conn.client)

    def _release(self, sock: socket.socket, client: str) -> None:
        with contextlib.suppress(OSError):
            sock.close()
        with self._lock:
            self._open -= 1
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")  # the loop may listen again

    # -- handler threads -------------------------------------------------------------------------
    def _work(self) -> None:
        while (item := self._complete.get()) is not None:
            sock, client, data = item
            try:
                if not self._closing.is_set():
                    self._handler((sock, data), (client, 0), self)
            except Exception as exc:  # a reset or timed-out client: one line, no traceback
                log.debug("HTTP connection from %s dropped: %r", client, exc)
            finally:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_WR)  # the reply is sent (a close with unread input would reset it)
                self._release(sock, client)

    def close(self) -> None:
        self._closing.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self.thread.join(5)
        self._listener.close()
        for _ in self.workers:
            self._complete.put(None)
        for sock in (self._wake_r, self._wake_w):
            sock.close()


def _error_bytes(status: int, message: str) -> bytes:
    """A whole HTTP/1.0 JSON error reply, for the loop to send without a handler."""
    _, ctype, body = json_response({"error": message}, status)
    reason = {408: "Request Timeout", 431: "Request Header Fields Too Large"}[status]
    return (f"HTTP/1.0 {status} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\n\r\n").encode() + body


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
