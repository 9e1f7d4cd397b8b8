"""The replay's segment log: every accepted transition batch, on disk before it counts.

A batch is **accepted** when its record is in the log and the log is fsync'd. The replay service
writes the records of everything it has received since the last commit, then fsyncs once (a
group commit, once per drain of its receive queue: at most a few milliseconds of batches), and
only then inserts them into the table and acknowledges them to their actors. So a ``kill -9``
loses nothing accepted: at start the service re-inserts the log's records, in order.

The log is the replay's persistent state (no snapshot): segments ``seg-<first index>.log`` of at
most ``segment_bytes``; a record is ``<u32 length><u32 crc32><u64 first transition index>``
followed by the batch exactly as it came off the wire (a ``TransitionBatch`` message, decoded
again at restore). A segment is deleted once every transition in it, and in the segment after
it, has left the table (FIFO, ``capacity``), so the log holds about the table plus one segment
(the extra segment keeps the frames that the oldest kept transitions refer to). A torn record
at the end of the last segment (a crash mid-write, never fsync'd, so never accepted) is cut off.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

HEADER = struct.Struct("<IIQ")  # payload length, crc32 of the payload, first transition index
MAX_RECORD_BYTES = 64 * 1024 * 1024


class SegmentLog:
    """Append-only, segmented, checksummed log of accepted batches (see the module docstring)."""

    def __init__(self, folder: str | Path, segment_bytes: int = 64 * 1024 * 1024, fsync: bool = True) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.segment_bytes = int(segment_bytes)
        self.fsync = fsync
        self._file = None
        self._path: Path | None = None
        self._dirty = False
        self.records_written = 0
        self.bytes_written = 0

    # -- reading (at start) ----------------------------------------------------------------------
    def segments(self) -> list[tuple[int, Path]]:
        out = []
        for p in self.folder.glob("seg-*.log"):
            try:
                out.append((int(p.stem[4:]), p))
            except ValueError:
                continue
        return sorted(out)

    def records(self) -> Iterator[tuple[int, bytes]]:
        """Every record, oldest first: (first transition index, payload). A torn tail of the
        last segment is truncated away; a bad record anywhere else raises ``ValueError``."""
        segments = self.segments()
        for n, (_, path) in enumerate(segments):
            last = n == len(segments) - 1
            with open(path, "rb") as f:
                offset = 0
                while True:
                    head = f.read(HEADER.size)
                    if not head:
                        break
                    bad = len(head) < HEADER.size
                    if not bad:
                        length, crc, first = HEADER.unpack(head)
                        payload = f.read(length) if length <= MAX_RECORD_BYTES else b""
                        # zeros left by a crash read as an empty record with a valid CRC: torn too
                        bad = length == 0 or len(payload) != length or zlib.crc32(payload) != crc
                    if bad:
                        if not last:
                            raise ValueError(f"{path}: damaged record at byte {offset} (not at the log's end)")
                        os.truncate(path, offset)  # a write the crash cut short: never accepted
                        break
                    yield first, payload
                    offset += HEADER.size + length

    # -- writing ---------------------------------------------------------------------------------
    def append(self, payload: bytes, first_index: int) -> None:
        """Write one record (buffered; ``commit`` makes it durable)."""
        if self._file is None or self._file.tell() >= self.segment_bytes:
            self._rotate(first_index)
        self._file.write(HEADER.pack(len(payload), zlib.crc32(payload), first_index))
        self._file.write(payload)
        self._dirty = True
        self.records_written += 1
        self.bytes_written += HEADER.size + len(payload)

    def commit(self) -> None:
        """Flush and fsync what ``append`` wrote: from here on it is accepted."""
        if self._file is not None and self._dirty:
            self._file.flush()
            if self.fsync:
                os.fsync(self._file.fileno())
            self._dirty = False

    def _rotate(self, first_index: int) -> None:
        if self._file is not None:
            self.commit()
            self._file.close()
        self._path = self.folder / f"seg-{first_index:020d}.log"
        self._file = open(self._path, "ab")
        if self.fsync:  # the new file's name must survive a crash too
            fd = os.open(self.folder, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def drop_before(self, index: int) -> int:
        """Delete segments whose transitions, and the next segment's, are all older than
        ``index`` (the first transition still in the table). Returns segments deleted."""
        segments = self.segments()
        dropped = 0
        for n in range(len(segments) - 2):
            if segments[n + 2][0] <= index and segments[n][1] != self._path:
                segments[n][1].unlink(missing_ok=True)
                dropped += 1
        return dropped

    def size_bytes(self) -> int:
        return sum(p.stat().st_size for _, p in self.segments())

    def close(self) -> None:
        if self._file is not None:
            self.commit()
            self._file.close()
            self._file = None
