"""Raw contiguous buffers with a small versioned header: the codec for bulk arrays.

msgpack (``codec.py``) suits small messages; for a sampled batch (about 1.5 MB for 256
transitions) it costs a copy per array on each side. Here a message is one buffer::

    header   magic b"CNRB", kind (u16), version (u16), arrays (u16), 0 (u16), total bytes (u64)
    table    per array: dtype (4 ASCII bytes, e.g. "<f2 "), ndim (u8), 3 zero bytes,
             4 dims (u32), offset (u64), bytes (u64)
    data     each array C-contiguous at its offset, offsets 64-byte aligned

The writer allocates the whole buffer first and hands out writable views (``RawWriter``), so a
producer gathers straight into the message (no copy after the gather). The reader
(``read_raw``) checks everything against the schema it expects before it looks at data: magic,
kind, version, number of arrays, each dtype and shape, each offset and size, the total length.
A mismatch is a ``ProtoError`` (reasons as in ``codec.py``), never an exception from numpy.
The arrays it returns are read-only views of the received buffer (no copy).
"""

from __future__ import annotations

import math
import struct

import numpy as np

from .codec import MAX_MESSAGE_BYTES, ProtoError

MAGIC = b"CNRB"
_HEAD = struct.Struct("<4sHHHHQ")  # magic, kind, version, arrays, reserved, total bytes
_ENTRY = struct.Struct("<4sB3x4IQQ")  # dtype, ndim, dims, offset, bytes
ALIGN = 64
MAX_DIMS = 4

# kinds of raw messages (the first two bytes after the magic)
KIND_SAMPLED_BATCH = 1
KIND_PRIORITY_UPDATE = 2


def _dtype_code(dtype: str) -> bytes:
    code = np.dtype(dtype).str.encode()
    return code.ljust(4)


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


class RawWriter:
    """A message being built: ``view(name)`` is a writable array inside the final buffer.

    ``schema`` is an ordered mapping ``name -> (dtype, shape)``; ``payload()`` returns the
    buffer (a ``bytearray``) once every array is filled."""

    def __init__(self, kind: int, version: int, schema: dict[str, tuple[str, tuple[int, ...]]],
                 buffer: bytearray | memoryview | None = None) -> None:
        self.schema = schema
        table_end = _HEAD.size + _ENTRY.size * len(schema)
        offset = _align(table_end)
        entries = []
        self._places: dict[str, tuple[int, int]] = {}
        for name, (dtype, shape) in schema.items():
            if len(shape) > MAX_DIMS:
                raise ValueError(f"{name}: at most {MAX_DIMS} dimensions")
            nbytes = np.dtype(dtype).itemsize * math.prod(shape)
            entries.append((_dtype_code(dtype), len(shape), *(tuple(shape) + (0,) * (MAX_DIMS - len(shape))),
                            offset, nbytes))
            self._places[name] = (offset, nbytes)
            offset = _align(offset + nbytes)
        self.size = offset
        self.buffer = bytearray(offset) if buffer is None else buffer
        if len(self.buffer) < offset:
            raise ValueError(f"buffer of {len(self.buffer)} bytes, the message needs {offset}")
        _HEAD.pack_into(self.buffer, 0, MAGIC, kind, version, len(schema), 0, offset)
        for i, entry in enumerate(entries):
            _ENTRY.pack_into(self.buffer, _HEAD.size + i * _ENTRY.size, *entry)
        self._np = np.frombuffer(self.buffer, np.uint8, count=offset)

    def view(self, name: str) -> np.ndarray:
        dtype, shape = self.schema[name]
        offset, nbytes = self._places[name]
        return self._np[offset:offset + nbytes].view(dtype).reshape(shape)

    def payload(self) -> bytearray | memoryview:
        return self.buffer if len(self.buffer) == self.size else memoryview(self.buffer)[:self.size]


def peek_raw(data: bytes | bytearray | memoryview) -> tuple[int, int, int]:
    """``(kind, version, arrays)`` of a raw message, after checking magic and length."""
    if len(data) < _HEAD.size:
        raise ProtoError("malformed", f"{len(data)} bytes: shorter than a raw header")
    if len(data) > MAX_MESSAGE_BYTES:
        raise ProtoError("oversize", f"message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    magic, kind, version, count, _, total = _HEAD.unpack_from(data, 0)
    if magic != MAGIC:
        raise ProtoError("malformed", "not a raw curlnav message (bad magic)")
    if total != len(data):
        raise ProtoError("shape", f"header says {total} bytes, {len(data)} arrived")
    return kind, version, count


def first_dim(data: bytes | bytearray | memoryview) -> int:
    """The first dimension of a raw message's first array (its batch size), after ``peek_raw``."""
    peek_raw(data)
    if len(data) < _HEAD.size + _ENTRY.size:
        raise ProtoError("malformed", "a raw message without arrays")
    return struct.unpack_from("<I", data, _HEAD.size + 8)[0]


def read_raw(data: bytes | bytearray | memoryview, kind: int, version: int,
             schema: dict[str, tuple[str, tuple[int, ...]]], what: str) -> dict[str, np.ndarray]:
    """Check ``data`` against ``schema`` (as ``RawWriter``'s) and return read-only views."""
    got_kind, got_version, count = peek_raw(data)
    if got_kind != kind:
        raise ProtoError("kind", f"expected a raw {what} (kind {kind}), got kind {got_kind}")
    if got_version != version:
        raise ProtoError("version", f"{what} version {got_version} is not supported (expected {version})")
    if count != len(schema):
        raise ProtoError("field", f"{what} has {count} arrays, expected {len(schema)}")
    table_end = _HEAD.size + _ENTRY.size * count
    if len(data) < table_end:
        raise ProtoError("malformed", f"{what}: truncated array table")
    buf = np.frombuffer(data, np.uint8)
    out = {}
    previous_end = table_end
    for i, (name, (dtype, shape)) in enumerate(schema.items()):
        code, ndim, d0, d1, d2, d3, offset, nbytes = _ENTRY.unpack_from(data, _HEAD.size + i * _ENTRY.size)
        if code != _dtype_code(dtype):
            raise ProtoError("dtype", f"{what}.{name} has dtype {code.strip()!r}, expected {np.dtype(dtype).str!r}")
        dims = (d0, d1, d2, d3)[:ndim]
        if ndim != len(shape) or dims != tuple(shape) or any((d0, d1, d2, d3)[ndim:]):
            raise ProtoError("shape", f"{what}.{name} has shape {list(dims)}, expected {list(shape)}")
        if nbytes != np.dtype(dtype).itemsize * math.prod(shape):
            raise ProtoError("shape", f"{what}.{name}: {nbytes} bytes for shape {list(shape)}")
        if offset % ALIGN or offset < previous_end or offset + nbytes > len(data):
            raise ProtoError("shape", f"{what}.{name}: bytes {offset}..{offset + nbytes} out of place")
        previous_end = offset + nbytes
        out[name] = buf[offset:offset + nbytes].view(dtype).reshape(shape)
    return out
