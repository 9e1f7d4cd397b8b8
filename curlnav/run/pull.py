"""``curlnav pull``: download a policy artefact from a learner's HTTP server, checking sha256.

The learner is not trusted with the local disk (issue 26 H5): only plain file names that the
artefact's own ``metadata.json`` lists (plus ``metadata.json``), each with a sha256; downloads
streamed to disk with a size cap; no redirect to another origin; metadata.json fetched first and
its every field checked (``check_metadata``) before any other file; the artefact built and checked
(checksums, ONNX model) in a temporary folder beside ``--out``, which is replaced only then, and
only if it is a policy artefact folder itself (or empty).

A pull has a total (issue 35): at most ``max_bytes`` of files in all (``--max-bytes``), at most
``max_files`` files (``--max-files``), and an overall deadline (``--deadline-s``) that a server
trickling a byte at a time cannot stretch: every connection is shut down when it passes. Whatever
ends a pull early, nothing of it is kept."""

from __future__ import annotations

import hashlib
import http.client
import math
import re
import shutil
import socket
import tempfile
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from curlnav.files import FileRefused, is_plain_file_name, loads_json, read_json, shown

MAX_FILE_BYTES = 256 << 20  # one artefact file (an actor of 1024 x 1024 layers is a few MB)
MAX_LISTING_BYTES = 4 << 20  # the JSON listing of a version
DEFAULT_MAX_BYTES = 256 << 20  # all files of one artefact (the largest allowed networks: about 160 MB)
DEFAULT_MAX_FILES = 16  # files of one artefact, metadata.json included (curlnav writes 3)
DEFAULT_DEADLINE_S = 300.0  # one whole pull
_CHUNK = 1 << 20


class PullBudget:
    """What one pull may still spend: ``bytes_left`` of files, and time until ``deadline_s``
    after it was made. ``watch(sock)`` shuts a connection down at the deadline (a read blocked
    on a trickling server returns then); ``close()`` stops the watches."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES, max_files: int = DEFAULT_MAX_FILES,
                 deadline_s: float = DEFAULT_DEADLINE_S) -> None:
        for flag, value, whole in (("--max-bytes", max_bytes, True), ("--max-files", max_files, True),
                                   ("--deadline-s", deadline_s, False)):
            number = isinstance(value, int) if whole else isinstance(value, (int, float))
            if isinstance(value, bool) or not number or not (math.isfinite(value) and value > 0):
                raise ValueError(f"{flag} must be a positive {'whole ' if whole else ''}number, got {shown(value)}")
        self.max_bytes, self.max_files, self.deadline_s = max_bytes, max_files, float(deadline_s)
        self.bytes_left = max_bytes
        self.deadline = time.monotonic() + self.deadline_s
        self._timers: list[threading.Timer] = []

    def time_left(self) -> float:
        return self.deadline - time.monotonic()

    def expired(self) -> bool:
        return self.time_left() <= 0

    def refuse_late(self, what: str) -> ValueError:
        return ValueError(f"{what}: gave up at the --deadline-s of {self.deadline_s:g} s (the server is too slow)")

    def watch(self, sock: socket.socket) -> None:
        def shut() -> None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass  # closed already

        timer = threading.Timer(max(0.0, self.time_left()), shut)
        timer.daemon = True
        timer.start()
        self._timers.append(timer)

    def close(self) -> None:
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()


def _origin(url: str) -> tuple[str, str, int | None]:
    parts = urllib.parse.urlsplit(url)
    return parts.scheme, (parts.hostname or "").lower(), parts.port or {"http": 80, "https": 443}.get(parts.scheme)


class _SameOriginRedirects(urllib.request.HTTPRedirectHandler):
    """Follows redirects on the learner's own origin only."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):
        if _origin(newurl) != _origin(req.full_url):
            raise ValueError(f"{req.full_url}: HTTP {code} redirect to another origin ({shown(newurl, 80)[1:-1]}); "
                             "refused")
        return super().redirect_request(req, fp, code, msg, headers, newurl)


def _watched(connection_class, budget: PullBudget):
    """A factory of ``connection_class`` whose sockets ``budget`` shuts down at its deadline."""
    def make(*args, **kwargs):
        connection = connection_class(*args, **kwargs)
        connect = connection.connect

        def connect_and_watch() -> None:
            connect()
            budget.watch(connection.sock)

        connection.connect = connect_and_watch
        return connection
    return make


class _DeadlineHTTPHandler(urllib.request.HTTPHandler):
    def __init__(self, budget: PullBudget) -> None:
        super().__init__()
        self.budget = budget

    def http_open(self, req):
        return self.do_open(_watched(http.client.HTTPConnection, self.budget), req)


class _DeadlineHTTPSHandler(urllib.request.HTTPSHandler):
    def __init__(self, budget: PullBudget) -> None:
        super().__init__()
        self.budget = budget

    def https_open(self, req):
        return self.do_open(_watched(http.client.HTTPSConnection, self.budget), req, context=self._context)


_opener = urllib.request.build_opener(_SameOriginRedirects)


#: tries of a GET whose connection the server closed before any reply (a learner restarting, or
#: dropping a request it could not read in time), and the pause before each retry (s)
DROPPED_TRIES = 3
DROPPED_PAUSE_S = 0.5


def _download(url: str, max_bytes: int, sink, timeout: float, budget: PullBudget | None = None,
              cap: str = "") -> int:
    """Stream ``GET url`` into ``sink(chunk)``, refusing more than ``max_bytes`` (``cap`` names
    that cap in the refusal) and, with a ``budget``, anything past its deadline; returns the size.
    A connection the server closed (or reset) before any reply is tried again, up to
    ``DROPPED_TRIES`` in all: nothing reached ``sink`` then. Raises ``ValueError`` on an HTTP error
    status, the cap or the deadline, ``OSError`` when unreachable."""
    for attempt in range(1, DROPPED_TRIES + 1):
        try:
            return _download_once(url, max_bytes, sink, timeout, budget, cap)
        except _Dropped as exc:
            if attempt == DROPPED_TRIES or budget is not None and budget.time_left() <= DROPPED_PAUSE_S * attempt:
                raise exc.error from None
            time.sleep(DROPPED_PAUSE_S * attempt)
    raise AssertionError("unreachable")


class _Dropped(Exception):
    """The server closed or reset the connection before any byte of a reply (``error``: what
    urllib raised)."""

    def __init__(self, error: OSError) -> None:
        super().__init__(str(error))
        self.error = error


def _download_once(url: str, max_bytes: int, sink, timeout: float, budget: PullBudget | None, cap: str) -> int:
    """One try of ``_download``; ``_Dropped`` when the connection went before any reply."""
    cap = cap or f"the {max_bytes >> 20} MiB cap"
    opener = _opener
    if budget is not None:
        if budget.expired():
            raise budget.refuse_late(url)
        timeout = max(0.001, min(timeout, budget.time_left()))
        opener = urllib.request.build_opener(_SameOriginRedirects, _DeadlineHTTPHandler(budget),
                                             _DeadlineHTTPSHandler(budget))
    try:
        try:
            response = opener.open(url, timeout=timeout)
        except (http.client.RemoteDisconnected, ConnectionResetError) as exc:
            raise _Dropped(exc) from None
        except urllib.error.URLError as exc:
            if isinstance(exc.reason, (http.client.RemoteDisconnected, ConnectionResetError)):
                raise _Dropped(exc) from None
            raise
        with response:
            declared = response.headers.get("Content-Length", "")
            if declared.strip().isdigit() and int(declared) > max_bytes:
                raise ValueError(f"{url}: {int(declared)} bytes, above {cap}; refused")
            size = 0
            while chunk := response.read(_CHUNK):
                size += len(chunk)
                if size > max_bytes:
                    raise ValueError(f"{url}: above {cap}; refused")
                sink(chunk)
            if budget is not None and budget.expired():  # a shut-down connection reads as an early end
                raise budget.refuse_late(url)
            return size
    except urllib.error.HTTPError as exc:
        detail = exc.read(2000).decode(errors="replace").strip()
        raise ValueError(f"{url}: HTTP {exc.code} {shown(detail, 200)[1:-1]}") from None
    except urllib.error.URLError as exc:
        if isinstance(exc.reason, ValueError):  # a refused redirect
            raise exc.reason from None
        if budget is not None and budget.expired():
            raise budget.refuse_late(url) from None
        raise
    except (OSError, http.client.HTTPException):
        if budget is not None and budget.expired():
            raise budget.refuse_late(url) from None
        raise


def http_get(url: str, timeout: float = 30.0, max_bytes: int = MAX_LISTING_BYTES, budget: PullBudget | None = None) -> bytes:
    """The body of ``GET url`` (at most ``max_bytes``, and within ``budget``'s deadline when
    given). Raises ``ValueError`` on an HTTP error status (with the server's reply), a
    cross-origin redirect, a body above the cap or the deadline, ``OSError`` when the server
    cannot be reached (see ``unreachable_reason``)."""
    parts: list[bytes] = []
    _download(url, max_bytes, parts.append, timeout, budget)
    return b"".join(parts)


def unreachable_reason(exc: OSError) -> str:
    """Why a connection failed, in a few words ("Connection refused", "timed out")."""
    reason = exc.reason if isinstance(exc, urllib.error.URLError) else exc
    if isinstance(reason, OSError) and reason.strerror:
        return reason.strerror
    return str(reason) or type(reason).__name__


def _checked_listing(raw: bytes, where: str) -> dict[str, tuple[str, str]]:
    """``{name: (sha256, url path)}`` from a learner's listing, or ``ValueError`` in one line."""
    try:
        listing = loads_json(raw, where)
    except FileRefused as exc:
        raise ValueError(f"listing {exc}") from None
    files = listing.get("files") if isinstance(listing, dict) else None
    if not isinstance(files, dict) or not files:
        raise ValueError(f"listing {where}: no 'files' mapping; is it a curlnav learner?")
    out = {}
    for name, info in files.items():
        if not is_plain_file_name(name):
            raise ValueError(f"listing {where}: names {shown(name)}, not a plain file name; refused")
        sha, url = (info.get("sha256"), info.get("url")) if isinstance(info, dict) else (None, None)
        if not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
            raise ValueError(f"listing {where}: {name} has no sha256 (got {shown(sha)}); refused")
        if not (isinstance(url, str) and url.startswith("/") and not url.startswith("//")):
            raise ValueError(f"listing {where}: {name} has url {shown(url)}, not a path on the learner")
        out[name] = (sha, url)
    if "metadata.json" not in out:
        raise ValueError(f"listing {where}: no metadata.json")
    return out


def _fetch_file(base: str, name: str, sha: str, url: str, folder: Path, timeout: float, budget: PullBudget) -> None:
    digest = hashlib.sha256()
    if budget.bytes_left < MAX_FILE_BYTES:
        max_bytes, cap = budget.bytes_left, f"the --max-bytes of {budget.max_bytes} bytes for the whole artefact"
    else:
        max_bytes, cap = MAX_FILE_BYTES, f"the {MAX_FILE_BYTES >> 20} MiB cap of one file"
    with open(folder / name, "xb") as f:
        def sink(chunk: bytes) -> None:
            digest.update(chunk)
            f.write(chunk)

        try:
            budget.bytes_left -= _download(base + url, max_bytes, sink, timeout, budget, cap)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
    if digest.hexdigest() != sha:
        raise ValueError(f"{name}: sha256 mismatch (download corrupted)")


def _replaceable(out_dir: Path) -> bool:
    """``out_dir`` may be replaced: absent, an empty folder, or a policy artefact folder."""
    if not out_dir.exists() and not out_dir.is_symlink():
        return True
    if out_dir.is_symlink() or not out_dir.is_dir():
        return False
    return not any(out_dir.iterdir()) or (out_dir / "metadata.json").is_file()


def pull_policy(base_url: str, out_dir: str | Path, version: str = "latest", timeout: float = 30.0,
                max_bytes: int = DEFAULT_MAX_BYTES, max_files: int = DEFAULT_MAX_FILES,
                deadline_s: float = DEFAULT_DEADLINE_S) -> Path:
    """Write the artefact of ``version`` ("latest" or a number) to ``out_dir``; returns it.
    At most ``max_bytes`` of files and ``max_files`` files, all within ``deadline_s``; ``timeout``
    bounds each read. Raises ``ValueError`` on a hostile or malformed listing, a checksum
    mismatch, an artefact that does not load, an HTTP error, a cap or the deadline, or an
    ``out_dir`` that is not an artefact folder; ``OSError`` when unreachable."""
    budget = PullBudget(max_bytes, max_files, deadline_s)
    try:
        return _pull(base_url, Path(out_dir), version, timeout, budget)
    finally:
        budget.close()


def _pull(base_url: str, out_dir: Path, version: str, timeout: float, budget: PullBudget) -> Path:
    from curlnav.policy import PolicyArtefact, check_metadata

    base = base_url.rstrip("/")
    if not _replaceable(out_dir):
        raise ValueError(f"--out {out_dir} exists and is not a policy artefact folder; pull into a new folder")
    where = f"{base}/policy/{version}"
    files = _checked_listing(http_get(where, timeout, budget=budget), where)
    if len(files) > budget.max_files:
        raise ValueError(f"listing {where}: {len(files)} files, above the --max-files of {budget.max_files}; refused")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    old = None
    try:
        _fetch_file(base, "metadata.json", *files["metadata.json"], tmp, timeout, budget)
        listed = PolicyArtefact.listed_files(tmp)  # the artefact's own list (plain names, checked)
        # every field checked now: an inf/NaN artefact is refused before any other file comes down
        check_metadata(read_json(tmp / "metadata.json", what="metadata.json"), tmp / "metadata.json")
        unlisted = sorted(set(files) - set(listed) - {"metadata.json"})
        if unlisted:
            raise ValueError(f"listing {where}: {shown(unlisted)} not in the artefact's metadata.json; refused")
        for name, expected in listed.items():
            if name not in files:
                raise ValueError(f"listing {where}: {name} (in metadata.json) is not listed")
            if files[name][0] != expected:
                raise ValueError(f"listing {where}: {name}: the listing's sha256 differs from metadata.json's")
            _fetch_file(base, name, *files[name], tmp, timeout, budget)
        PolicyArtefact(tmp)  # checksums and the ONNX model, before --out is touched
        if out_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old.", dir=out_dir.parent))
            out_dir.rename(old / "artefact")
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and not out_dir.exists():
            (old / "artefact").rename(out_dir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return out_dir
