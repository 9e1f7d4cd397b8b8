"""``curlnav pull``: download a policy artefact from a learner's HTTP server, checking sha256."""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import urllib.error
import urllib.request
from pathlib import Path


def http_get(url: str, timeout: float = 30.0) -> bytes:
    """The body of ``GET url``. Raises ``ValueError`` on an HTTP error status (with the server's
    reply), ``OSError`` when the server cannot be reached (see ``unreachable_reason``)."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.read()
    except urllib.error.HTTPError as exc:
        detail = exc.read().decode(errors="replace").strip()
        raise ValueError(f"{url}: HTTP {exc.code} {detail}") from None


def unreachable_reason(exc: OSError) -> str:
    """Why a connection failed, in a few words ("Connection refused", "timed out")."""
    reason = exc.reason if isinstance(exc, urllib.error.URLError) else exc
    if isinstance(reason, OSError) and reason.strerror:
        return reason.strerror
    return str(reason) or type(reason).__name__


def pull_policy(base_url: str, out_dir: str | Path, version: str = "latest") -> Path:
    """Write the artefact of ``version`` ("latest" or a number) to ``out_dir``; returns it.
    Raises ``ValueError`` on a checksum mismatch or an HTTP error, ``OSError`` when unreachable."""
    base = base_url.rstrip("/")
    listing = json.loads(http_get(f"{base}/policy/{version}"))
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=out_dir.name + ".", dir=out_dir.parent))
    try:
        for name, info in listing["files"].items():
            data = http_get(base + info["url"])
            expected = info.get("sha256")
            if expected and hashlib.sha256(data).hexdigest() != expected:
                raise ValueError(f"{name}: sha256 mismatch (download corrupted)")
            (tmp / name).write_bytes(data)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir
