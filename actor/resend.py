"""What an actor has generated and the replay has not yet acknowledged: kept, and sent again.

A batch put on the bus can be lost without an error: the host is cut off (its router drops what
has no route), a router restarts, the replay restarts. So an actor keeps every batch, in order,
until the replay's acknowledgement covers it (``ack``: every seq at or below it is accepted), and
sends (``due``) while the replay is heard from:

- batches never sent, oldest first;
- all unacknowledged ones again from the oldest (go-back-N), once the oldest sent one has waited
  ``resend_after_s`` (the replay acknowledges within ~20 ms; it refuses a batch above a gap,
  so the acknowledgement advances only once the lost ones come, in order).

Bounds: ``memory_bytes`` of payloads in memory (default 64 MiB), then ``disk_bytes`` more in a
spill file in the actor's folder (default 1 GiB; emptied once everything in it is
acknowledged). When both are full the actor stops stepping (``full``) until acknowledgements free
room: it generates nothing it could lose. (The actor also makes at most ``unheard_batches`` while
the replay is not heard at all, so a long partition costs neither CPU nor disk.)
"""

from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path


@dataclass
class _Held:
    seq: int
    size: int
    payload: bytes | None  # None: in the spill file at ``offset``
    offset: int = -1
    sent_at: float = float("-inf")  # monotonic time of the last send; -inf: never sent


class ResendBuffer:
    """Unacknowledged batches of one actor, oldest first (see the module docstring)."""

    def __init__(self, folder: str | Path | None = None, memory_bytes: int = 64 << 20, disk_bytes: int = 1 << 30,
                 resend_after_s: float = 5.0, burst: int = 64) -> None:
        self.memory_bytes, self.disk_bytes = int(memory_bytes), int(disk_bytes) if folder else 0
        self.resend_after_s, self.burst = resend_after_s, burst
        self.spill_path = Path(folder) / "unacknowledged.spill" if folder else None
        self._spill = None
        self.held: deque[_Held] = deque()
        self.in_memory = 0  # payload bytes held in memory
        self.on_disk = 0  # bytes written to the spill file since it was last emptied
        self._next = 0  # index in ``held`` of the next batch to send
        self.resent = 0  # batches sent again (go-back-N)
        self.acked = -1

    def __len__(self) -> int:
        return len(self.held)

    def full(self, size: int = 0) -> bool:
        """No room for a batch of ``size`` bytes in memory nor on disk."""
        return self.in_memory + size > self.memory_bytes and self.on_disk + size > self.disk_bytes

    def add(self, seq: int, payload: bytes) -> None:
        """Keep batch ``seq`` (numbered above every one held) until it is acknowledged."""
        size = len(payload)
        if self.in_memory + size <= self.memory_bytes or self.on_disk + size > self.disk_bytes:
            self.held.append(_Held(seq, size, payload))
            self.in_memory += size
            return
        if self._spill is None:
            self.spill_path.parent.mkdir(parents=True, exist_ok=True)
            self._spill = open(self.spill_path, "w+b")
        self._spill.seek(self.on_disk)
        self._spill.write(payload)
        self.held.append(_Held(seq, size, None, self.on_disk))
        self.on_disk += size

    def ack(self, seq: int) -> int:
        """The replay has accepted every batch up to ``seq``: drop them. Returns how many went."""
        self.acked = max(self.acked, seq)
        gone = 0
        while self.held and self.held[0].seq <= seq:
            held = self.held.popleft()
            if held.payload is not None:
                self.in_memory -= held.size
            gone += 1
        self._next = max(0, self._next - gone)
        if self.on_disk and not any(h.payload is None for h in self.held):
            self._spill.truncate(0)  # every spilled batch is acknowledged: the file starts again
            self.on_disk = 0
        return gone

    def _payload(self, held: _Held) -> bytes:
        if held.payload is not None:
            return held.payload
        self._spill.seek(held.offset)
        return self._spill.read(held.size)

    def due(self, now: float | None = None) -> list[tuple[int, bytes]]:
        """The batches to put now, in order (at most ``burst``), marked sent: never-sent ones, or
        every unacknowledged one from the oldest when the oldest sent one waited ``resend_after_s``."""
        now = time.monotonic() if now is None else now
        if self.held and self._next > 0 and now - self.held[0].sent_at >= self.resend_after_s:
            self.resent += self._next
            self._next = 0  # go back to the oldest unacknowledged batch
        out = []
        while self._next < len(self.held) and len(out) < self.burst:
            held = self.held[self._next]
            held.sent_at = now
            out.append((held.seq, self._payload(held)))
            self._next += 1
        return out

    def renumber(self, start: int, recode) -> int:
        """Number every held batch again from ``start`` (``recode(payload, seq)``: the batch with its
        new number), all to be sent again; returns the next free number. For an acknowledgement this
        process never earned (a predecessor on its id whose numbers ran ahead): its batches would be
        refused as duplicates for ever."""
        for i, held in enumerate(self.held):
            payload = recode(self._payload(held), start + i)
            if held.payload is not None:
                self.in_memory -= held.size
            held.seq, held.payload, held.size, held.offset = start + i, payload, len(payload), -1
            held.sent_at = float("-inf")
            self.in_memory += held.size
        if self._spill is not None:
            self._spill.truncate(0)
        self.on_disk, self._next = 0, 0
        return start + len(self.held)

    def unsent(self) -> int:
        return len(self.held) - self._next

    def close(self) -> None:
        if self._spill is not None:
            self._spill.close()
            self._spill = None
            try:
                os.unlink(self.spill_path)
            except OSError:
                pass
