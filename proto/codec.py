"""msgpack codec for curlnav messages: explicit schemas, versions and validation. No pickle.

Every message is a msgpack map ``{"kind": str, "v": int, ...fields}``. Arrays travel as
``{"dtype": str, "shape": [int, ...], "data": bytes}`` and are checked against the schema's
dtype and shape pattern (``None`` = any length) on decoding. Decoding raises ``ProtoError``
with a short ``reason`` (for rejection counters) and a readable message.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

MAX_MESSAGE_BYTES = 64 * 1024 * 1024  # 64 MiB: a weights message of the paper preset is ~35 MB


class ProtoError(ValueError):
    """A message was refused; ``reason`` is one of: oversize, malformed, kind, version, field,
    dtype, shape, non_finite, range."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason


def pack_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def unpack_array(obj: Any, name: str, dtype: str, shape: tuple, finite: bool = True) -> np.ndarray:
    """Check and rebuild one array field. ``dtype`` is a numpy dtype string such as ``"<f4"``;
    ``shape`` entries are ints or None (any); the first None dimensions may be shared via
    named strings (e.g. ``"F"``) checked by the caller."""
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise ProtoError("field", f"{name} is not an array record")
    if obj["dtype"] != np.dtype(dtype).str:
        raise ProtoError("dtype", f"{name} has dtype {obj['dtype']!r}, expected {np.dtype(dtype).str!r}")
    got = obj["shape"]
    if not isinstance(got, list) or len(got) != len(shape) or not all(isinstance(n, int) and n >= 0 for n in got):
        raise ProtoError("shape", f"{name} has shape {got!r}, expected {len(shape)} dimensions")
    for n, want in zip(got, shape):
        if isinstance(want, int) and n != want:
            raise ProtoError("shape", f"{name} has shape {got}, expected {list(shape)}")
    data = obj["data"]
    itemsize = np.dtype(dtype).itemsize
    if not isinstance(data, (bytes, bytearray)) or len(data) != itemsize * math.prod(got):
        raise ProtoError("shape", f"{name} has {len(data) if isinstance(data, (bytes, bytearray)) else 'no'} bytes "
                                  f"for shape {got}")
    array = np.frombuffer(data, dtype=dtype).reshape(got)
    if finite and array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise ProtoError("non_finite", f"{name} contains NaN or infinity")
    return array


def dumps(payload: dict) -> bytes:
    return msgpack.packb(payload, use_bin_type=True)


def loads(data: bytes | bytearray | memoryview, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
    """Raw msgpack map with size and type checks (no schema yet)."""
    if len(data) > max_bytes:
        raise ProtoError("oversize", f"message of {len(data)} bytes exceeds {max_bytes}")
    try:
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, max_bin_len=max_bytes,
                              max_str_len=1 << 20, max_array_len=1 << 20, max_map_len=1 << 16)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise ProtoError("malformed", f"not msgpack: {type(exc).__name__}") from None
    if not isinstance(obj, dict):
        raise ProtoError("malformed", "a message must be a msgpack map")
    return obj


def check_header(obj: dict, kind: str, version: int) -> None:
    if obj.get("kind") != kind:
        raise ProtoError("kind", f"expected a {kind!r} message, got {obj.get('kind')!r}")
    if obj.get("v") != version:
        raise ProtoError("version", f"{kind} version {obj.get('v')!r} is not supported (expected {version})")


def field(obj: dict, name: str, types: type | tuple, kind: str) -> Any:
    if name not in obj:
        raise ProtoError("field", f"{kind} lacks field {name!r}")
    value = obj[name]
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise ProtoError("field", f"{kind}.{name} has type bool")
    if not isinstance(value, types):
        raise ProtoError("field", f"{kind}.{name} has type {type(value).__name__}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ProtoError("non_finite", f"{kind}.{name} is not finite")
    return value
