#!/usr/bin/env python3
"""Vendor the real buildings' SLAM maps of ``curlnav.worlds.real.real_maps.MAPS`` into ``curlnav/worlds/data/real/``.

For every map, from its repository at its commit (``git cat-file``, bytes as stored):

- ``<name>/<map>.yaml``: the map_server YAML, byte for byte; where the source has none (Willow
  Garage: its launch files run ``map_server IMAGE RESOLUTION``), the YAML of ``RealMap.yaml_text``,
  the same values (origin 0, negate 0, thresholds 0.65 and 0.196: map_server's defaults then);
- ``<name>/<image>.pgm.xz``: the image, xz-compressed (decompressed: byte for byte);
- ``<name>/<licence file>``: the licence text, or the package manifest that declares the licence,
  byte for byte (from ``licence_commit`` when set);
- ``<name>/SOURCE.md`` (``--update`` only): repository, commit and date, paths, licence, why the map is real;
- ``MANIFEST.sha256`` (``--update`` only): the sha256 of every original file (``<name>/<file>``, the image as the PGM).

Each map is loaded once written (``curlnav.worlds.real.real_maps.map_world``), and the suite's pairs and
balls drawn (``task``), so a map that cannot hold the suite stops the script.

Every map is fetched and every fetched file checked against the committed ``MANIFEST.sha256`` before
anything is written; then the files are written into a temporary folder in ``--out`` and moved into
place. ``--update`` (a maintainer adding or moving a map) writes the manifest and every ``SOURCE.md``
anew instead of checking.

A mirror is files someone else made, so git reads its objects and nothing else of it: each mirror is
read through an empty repository of this script's whose ``objects/info/alternates`` names the
mirror's object folder (the mirror's config, refs, replace refs, hooks and grafts are never read, so
no ``gpg.program``, pager or fsmonitor it names runs), with ``git cat-file`` alone (plumbing that
calls no helper), replace refs off, the system's and the user's git config ignored. A blob is sized
before it is read: a map image above ``curlnav.worlds.real.real_maps.MAX_IMAGE_BYTES``, a YAML or licence
above ``MAX_TEXT_BYTES`` is refused (a 3.5 GB blob in a 3.7 MB mirror took 2.7 GB, then MemoryError).
Each refusal (no git directory, a missing or corrupt object, a blob too large, a git failure with
git's own words, bytes not in the manifest) is one line on stderr and exit 2, with nothing written.

Usage: ``scripts/vendor-real-maps.py [--mirrors DIR] [--out DIR] [--update]``. With ``--mirrors``, repository
``owner/name`` is read from the git directory ``DIR/owner+name/repo`` (a bare snapshot or a work
tree's ``.git``); without it, each repository is cloned from GitHub (``git clone --bare
--filter=blob:none``, blobs fetched on demand) into a temporary folder.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import lzma
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from curlnav.files import shown  # noqa: E402
from curlnav.worlds.core.world import WorldError  # noqa: E402
from curlnav.worlds.real import real_maps  # noqa: E402
from curlnav.worlds.real.real_maps import MAPS, MAX_IMAGE_BYTES, MAX_TEXT_BYTES, RealMap  # noqa: E402

GIT_TIMEOUT_S = 300  # one git command, a clone's fetch of a blob on demand included
_COMMITTER = re.compile(rb"committer .*> (\d{1,12}) ([+-])(\d\d)(\d\d)")


class Refused(Exception):
    """A repository, object or fetched file this script will not use; one line naming it and the limit."""


class GitFailed(Refused):
    """A git command that failed; ``said``: its stderr, on one line, shortened."""

    def __init__(self, what: str, said: str) -> None:
        super().__init__(f"{what}: git failed: {said}")
        self.said = said


def git_env(home: Path) -> dict[str, str]:
    """The environment of every git command: no ``GIT_*`` variable from outside, the system's and the
    user's config ignored (``home`` is an empty folder), replace refs off, no pager, no prompt."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("GIT_")}
    return {**env, "HOME": str(home), "XDG_CONFIG_HOME": str(home), "GIT_CONFIG_NOSYSTEM": "1",
            "GIT_CONFIG_GLOBAL": os.devnull, "GIT_NO_REPLACE_OBJECTS": "1", "GIT_PAGER": "cat", "PAGER": "cat",
            "GIT_TERMINAL_PROMPT": "0", "GIT_OPTIONAL_LOCKS": "0"}


def run_git(args: list[str], env: dict[str, str], what: str, stdin: bytes = b"") -> bytes:
    """git's stdout; ``GitFailed`` (git's stderr) when it fails, ``Refused`` when it takes over ``GIT_TIMEOUT_S``."""
    try:
        done = subprocess.run(["git", *args], input=stdin, capture_output=True, env=env, timeout=GIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise Refused(f"{what}: git {args[-1] if args else ''} took more than {GIT_TIMEOUT_S} s") from None
    except OSError as exc:
        raise Refused(f"{what}: cannot run git ({exc.strerror or exc})") from None
    if done.returncode != 0:
        said = " ".join(done.stderr.decode("utf-8", "replace").split()) or f"exit status {done.returncode}"
        raise GitFailed(what, shown(said, 300)[1:-1])
    return done.stdout


@dataclass(frozen=True)
class GitObjects:
    """One repository's objects, read with ``git cat-file`` from ``git_dir``, a git directory this
    script made (a bare clone, or an empty repository whose alternates name a mirror's objects)."""

    repository: str  # owner/name
    git_dir: Path
    env: dict[str, str]

    def _git(self, *args: str, stdin: bytes = b"") -> bytes:
        return run_git(["--no-replace-objects", f"--git-dir={self.git_dir}", *args], self.env, self.repository,
                       stdin)

    def _object(self, spec: str, kind: str, max_bytes: int, what: str) -> tuple[str, int]:
        """The id and size (bytes) of the object ``spec`` (``COMMIT`` or ``COMMIT:PATH``), read from its
        header alone; ``Refused`` when it is missing, not a ``kind`` or above ``max_bytes``."""
        short = f"{spec[:12]}{spec[40:]}"
        if "\n" in spec:
            raise Refused(f"{self.repository}: {shown(spec)} is not an object name")
        line = self._git("cat-file", "--batch-check=%(objectname) %(objecttype) %(objectsize)",
                         stdin=spec.encode() + b"\n").decode("utf-8", "replace").strip()
        parts = line.split(" ")
        if len(parts) != 3 or not parts[2].isdigit():  # "<spec> missing", "<spec> ambiguous"
            try:  # git's own words on why (a corrupt object reads as missing here)
                self._git("cat-file", "-t", spec)
            except GitFailed as exc:
                raise Refused(f"{self.repository}: {short} is {parts[-1]} or unreadable (git: {exc.said})") from None
            raise Refused(f"{self.repository}: {short} is {parts[-1]}")
        oid, found, size = parts[0], parts[1], int(parts[2])
        if found != kind:
            raise Refused(f"{self.repository}: {short} is a {found}, not a {kind}")
        if size > max_bytes:
            raise Refused(f"{self.repository}: {short} is a {what} of {size:,} bytes, above the "
                          f"{max_bytes >> 20} MiB cap on a {what}")
        return oid, size

    def blob(self, commit: str, path: str, max_bytes: int, what: str) -> bytes:
        """The bytes of ``COMMIT:PATH``, sized before they are read (``Refused`` above ``max_bytes``)."""
        oid, size = self._object(f"{commit}:{path}", "blob", max_bytes, what)
        data = self._git("cat-file", "blob", oid)
        if len(data) != size:
            raise Refused(f"{self.repository}: {commit[:12]}:{path} gave {len(data)} bytes, its header says {size}")
        return data

    def commit_date(self, commit: str) -> str:
        """The commit's committer date (YYYY-MM-DD, in the committer's time zone: git's ``%cs``),
        parsed from the commit object itself."""
        oid, _ = self._object(commit, "commit", MAX_TEXT_BYTES, "commit")
        headers = self._git("cat-file", "commit", oid).split(b"\n\n", 1)[0]
        for line in headers.split(b"\n"):
            match = _COMMITTER.fullmatch(line)
            if match:
                seconds, sign, hours, minutes = int(match[1]), match[2], int(match[3]), int(match[4])
                offset = datetime.timedelta(hours=hours, minutes=minutes) * (-1 if sign == b"-" else 1)
                try:
                    when = datetime.datetime.fromtimestamp(seconds, datetime.timezone(offset))
                except (ValueError, OverflowError, OSError):
                    break
                return when.date().isoformat()
        raise Refused(f"{self.repository}: commit {commit[:12]} has no committer line with a date git writes")


def git_objects(repository: str, mirrors: Path | None, scratch: Path, env: dict[str, str]) -> GitObjects:
    """``repository``'s objects: the mirror's ``DIR/owner+name/repo`` (a bare snapshot or a work tree's
    ``.git``), read through an empty repository of ours; without mirrors, a fresh bare clone."""
    target = scratch / repository.replace("/", "+")
    if mirrors is None:
        if not target.exists():
            run_git(["clone", "--quiet", "--bare", "--filter=blob:none", f"https://github.com/{repository}.git",
                     str(target)], env, repository)
        return GitObjects(repository, target, env)
    base = mirrors / repository.replace("/", "+") / "repo"
    objects = next((c / "objects" for c in (base / ".git", base) if (c / "objects").is_dir()), None)
    if objects is None:
        raise Refused(f"no git directory for {repository} under {mirrors} (no objects/ in {base} or {base}/.git)")
    alternate = str(objects.resolve())
    if "\n" in alternate or alternate.startswith('"'):
        raise Refused(f"{shown(alternate)}: a mirror path git cannot name in alternates")
    run_git(["init", "--quiet", "--bare", "--template=", str(target)], env, repository)
    (target / "objects" / "info").mkdir(parents=True, exist_ok=True)
    (target / "objects" / "info" / "alternates").write_text(alternate + "\n")
    return GitObjects(repository, target, env)


@dataclass(frozen=True)
class Fetched:
    """One map as fetched: its original files (name -> bytes) and its commits' dates (YYYY-MM-DD)."""

    originals: dict[str, bytes]
    date: str
    licence_date: str


def fetch_map(objects: GitObjects, m: RealMap) -> Fetched:
    """The map's YAML, image and licence file at their commits, each within its cap (``Refused`` else)."""
    date = objects.commit_date(m.commit)
    image = objects.blob(m.commit, m.image, MAX_IMAGE_BYTES, "map image")
    yaml_bytes = objects.blob(m.commit, m.yaml, MAX_TEXT_BYTES, "map YAML") if m.yaml else m.yaml_text.encode()
    licence = objects.blob(m.licence_commit or m.commit, m.licence_file, MAX_TEXT_BYTES, "licence file")
    licence_date = objects.commit_date(m.licence_commit) if m.licence_commit else date
    return Fetched(dict(zip(m.originals, (yaml_bytes, image, licence))), date, licence_date)


def check(m: RealMap, fetched: Fetched, expected: dict[str, str]) -> None:
    """``Refused`` when a fetched file's sha256 is not the manifest's."""
    for file, data in fetched.originals.items():
        key, digest = f"{m.name}/{file}", hashlib.sha256(data).hexdigest()
        if digest != expected.get(key):
            raise Refused(f"{key}: the fetched bytes do not match MANIFEST.sha256 (sha256 {digest}, "
                          f"expected {expected.get(key)})")


def source_md(m: RealMap, date: str, licence_date: str, today: str) -> str:
    yaml_line = (f"- `{m.yaml_name}`: `{m.yaml}`, byte for byte." if m.yaml else
                 f"- `{m.yaml_name}`: written here (the source has no YAML; its launch files run map_server "
                 f"with the image and its resolution): the same values, map_server's defaults for the rest.")
    licence_from = (f" at commit `{m.licence_commit}` ({licence_date})" if m.licence_commit else "")
    return f"""# {m.name}: {m.building}

From https://github.com/{m.repository}, commit `{m.commit}` ({date}), vendored on {today} by
`scripts/vendor-real-maps.py`. Kind: {m.kind}.

- `{Path(m.image).name}.xz`: `{m.image}`, xz-compressed (decompressed: byte for byte).
{yaml_line}
- `{Path(m.licence_file).name}`: `{m.licence_file}`{licence_from}, byte for byte.

Licence: {m.licence} (`{Path(m.licence_file).name}`). `../MANIFEST.sha256` holds every original file's sha256.

A real building, mapped by a robot: {m.why_real}.
"""


def write_all(out: Path, maps: list[tuple[RealMap, Fetched]], update: bool, today: str) -> None:
    """Every map's files (the image xz-compressed; with ``update``, every ``SOURCE.md`` and
    ``MANIFEST.sha256`` too) written into a temporary folder in ``out``, then each moved into place
    (``os.replace``, the same file system): a failure while writing leaves ``out`` as it was."""
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".vendor-real-maps-", dir=out))
    try:
        files: dict[str, bytes] = {}  # path in out -> bytes
        for m, fetched in maps:
            yaml_name, image, licence = m.originals
            files[f"{m.name}/{yaml_name}"] = fetched.originals[yaml_name]
            files[f"{m.name}/{image}.xz"] = lzma.compress(fetched.originals[image], preset=9 | lzma.PRESET_EXTREME)
            files[f"{m.name}/{licence}"] = fetched.originals[licence]
            if update:
                files[f"{m.name}/SOURCE.md"] = source_md(m, fetched.date, fetched.licence_date, today).encode()
        if update:
            files["MANIFEST.sha256"] = "".join(f"{hashlib.sha256(data).hexdigest()}  {m.name}/{file}\n"
                                               for m, fetched in maps for file, data in fetched.originals.items()).encode()
        for path, data in files.items():
            (staging / path).parent.mkdir(parents=True, exist_ok=True)
            (staging / path).write_bytes(data)
        for path in files:
            (out / path).parent.mkdir(parents=True, exist_ok=True)
            os.replace(staging / path, out / path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def refuse(message: str) -> int:
    """Say ``message`` in one line on stderr; the exit status of a refusal (2)."""
    print(f"vendor-real-maps.py: error: {' '.join(message.split())}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mirrors", type=Path, default=None,
                        help="folder of git snapshots named owner+name/repo (default: clone from GitHub)")
    parser.add_argument("--out", type=Path, default=real_maps.DATA)
    parser.add_argument("--update", action="store_true",
                        help="a maintainer's: write MANIFEST.sha256 and every SOURCE.md anew from what was fetched "
                             "(by default the downloads are checked against the committed manifest and nothing "
                             "committed is touched)")
    args = parser.parse_args(argv)
    today = datetime.date.today().isoformat()
    fetched: list[tuple[RealMap, Fetched]] = []
    try:
        expected = {} if args.update else real_maps.manifest()
        with tempfile.TemporaryDirectory(prefix="vendor-real-maps-") as scratch:
            (Path(scratch) / "home").mkdir()
            env = git_env(Path(scratch) / "home")
            readers: dict[str, GitObjects] = {}
            for m in MAPS.values():
                if m.repository not in readers:
                    readers[m.repository] = git_objects(m.repository, args.mirrors, Path(scratch), env)
                fetched.append((m, fetch_map(readers[m.repository], m)))
                if not args.update:
                    check(m, fetched[-1][1], expected)
    except (Refused, WorldError, OSError) as exc:
        return refuse(f"{exc}; nothing written")
    try:
        write_all(args.out, fetched, args.update, today)
    except OSError as exc:
        return refuse(f"{args.out}: cannot write ({exc})")
    if args.out == real_maps.DATA:
        for m, _ in fetched:
            try:
                world = real_maps.task(m.name)
            except WorldError as exc:
                return refuse(str(exc))
            print(f"{m.name}: {world.occupancy.shape[1]} x {world.occupancy.shape[0]} cells at "
                  f"{world.resolution:g} m, {len(world.pairs)} pairs, {len(world.balls)} balls")
    print(f"wrote {len(fetched)} maps in {args.out}" + (" and MANIFEST.sha256, SOURCE.md anew" if args.update else
                                                          ", every file as MANIFEST.sha256 says"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
