"""The router's audit of its access control: every message it refuses is counted and logged.

Zenoh writes one line per message its access control drops (``Msg intercepted!``, target
``zenoh::net::routing::interceptor``, at TRACE level) and nothing for the messages it lets
through, so ``FILTER`` turns exactly that line on and nothing else. Zenoh's logger writes to the
process's stdout; ``DenialAudit`` puts a pipe in its place, counts those lines as they pass (the
rest goes on to the real stdout unchanged) and logs the count (on stderr): the first refusal at once, then
one line per ``every_s`` in which more came. A flood of refused messages therefore costs one
counted line each, never a log line each.

The line does not say who sent what. To see that (two lines per message, allowed ones too: not
for a busy run) start the router with
``RUST_LOG=zenoh::net::routing::interceptor::access_control=trace``.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger("curlnav.bus.audit")

FILTER = "error,zenoh::net::routing::interceptor=trace,zenoh::net::routing::interceptor::access_control=off"
DENIED = b"Msg intercepted!"


class DenialAudit:
    """Counts the router's access-control refusals (``total``) and logs them."""

    def __init__(self, every_s: float = 10.0) -> None:
        self.every_s = every_s
        self.total = 0
        self.reported = 0
        self._stdout = -1
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> DenialAudit:
        """Route Zenoh's log through the counter (call before the router's session opens)."""
        import zenoh

        if os.environ.get("RUST_LOG"):
            log.warning("bus: RUST_LOG is set: access-control refusals are counted only if it enables "
                        "zenoh::net::routing::interceptor at trace level")
        import sys

        sys.stdout.flush()
        read, write = os.pipe()
        self._stdout = os.dup(1)
        os.dup2(write, 1)
        os.close(write)
        self._threads = [threading.Thread(target=self._read, args=(read,), daemon=True, name="acl-audit-read"),
                         threading.Thread(target=self._report, daemon=True, name="acl-audit-report")]
        for t in self._threads:
            t.start()
        zenoh.init_log_from_env_or(FILTER)
        return self

    def _read(self, fd: int) -> None:
        """Count refusal lines, pass every other line on; never slower than Zenoh writes."""
        rest = b""
        while True:
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                break
            data = rest + chunk
            cut = data.rfind(b"\n")
            if cut < 0 and len(data) < 1 << 20:  # a line still coming (a longer one passes in pieces)
                rest = data
                continue
            chunk, rest = (data[:cut], data[cut + 1:]) if cut >= 0 else (data, b"")
            if DENIED not in chunk:
                os.write(self._stdout, chunk + b"\n")
                continue
            lines = chunk.split(b"\n")
            kept = [line for line in lines if DENIED not in line]
            self.total += len(lines) - len(kept)
            if kept:
                os.write(self._stdout, b"\n".join(kept) + b"\n")

    def _report(self) -> None:
        first = True
        while not self._stop.wait(0.2 if first else self.every_s):
            if self.total > self.reported:
                new, self.reported = self.total - self.reported, self.total
                when = "" if first else f" in the last {self.every_s:g} s"
                log.warning("bus: access control refused %d message%s%s (%d since the router started)",
                            new, "" if new == 1 else "s", when, self.total)
                first = False

    def stop(self) -> None:
        """Log what is left to log and stop the reporter (the pipe stays: stdout is still it)."""
        self._stop.set()
        if self.total > self.reported:
            log.warning("bus: access control refused %d messages at the end (%d since the router started)",
                        self.total - self.reported, self.total)
            self.reported = self.total
