"""Issue 55: ``scripts/vendor-real-maps.py --mirrors DIR`` against hostile git mirrors. A mirror is
files someone else made: git runs nothing its config names (a ``gpg.program`` ran through
``log.showSignature`` and a replace ref), follows none of its replace refs, reads no blob above the
caps of ``curlnav.worlds.real.real_maps`` (a 3.5 GB blob took 2.7 GB, then MemoryError), and every
refusal is one line, exit 2, with nothing written (a later map's failure left the earlier maps
written).

Mirrors are built here with git plumbing. A commit whose id ``MAPS`` pins is forged as a loose
object under that id (git does not check a loose object's id when it reads one), so the script
runs unchanged against them; elsewhere the script's ``MAPS`` is a fake map's."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import lzma
import os
import subprocess
import sys
import time
import zlib
from pathlib import Path

import pytest

from curlnav.worlds.real import real_maps
from curlnav.worlds.real.real_maps import RealMap

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "vendor-real-maps.py"
#: git for building mirrors, blind to the user's and the system's config
GIT_ENV = {**{k: v for k, v in os.environ.items() if not k.startswith("GIT_")}, "GIT_CONFIG_NOSYSTEM": "1",
           "GIT_CONFIG_GLOBAL": os.devnull}
GPGSIG = "gpgsig -----BEGIN PGP SIGNATURE-----\n \n iQEzBAABCAAdFiEE\n -----END PGP SIGNATURE-----\n"
OCT_13_IN_TOKYO = "1318435200 +0900"  # 2011-10-12 16:00 UTC: the committer's date (git's %cs) is the 13th


# -- mirrors ---------------------------------------------------------------------------------------
def git(repo: Path, *args: str, data: bytes = b"", **env: str) -> str:
    return subprocess.run(["git", f"--git-dir={repo}", *args], input=data, capture_output=True, check=True,
                          env={**GIT_ENV, **env}).stdout.decode().strip()


def bare_repo(mirrors: Path, repository: str) -> Path:
    """An empty bare repository where ``--mirrors`` looks for ``repository``."""
    repo = mirrors / repository.replace("/", "+") / "repo"
    subprocess.run(["git", "init", "--quiet", "--bare", str(repo)], check=True, env=GIT_ENV)
    return repo


def commit_body(repo: Path, files: dict[str, bytes], when: str = OCT_13_IN_TOKYO, headers: str = "") -> bytes:
    """A commit's text whose tree holds ``files`` (path in the repository -> bytes), blobs written."""
    index = {"GIT_INDEX_FILE": str(repo / "scratch-index")}
    for path, data in files.items():
        blob = git(repo, "hash-object", "-w", "--stdin", data=data)
        git(repo, "update-index", "--add", "--cacheinfo", f"100644,{blob},{path}", **index)
    tree = git(repo, "write-tree", **index)
    (repo / "scratch-index").unlink()
    return f"tree {tree}\nauthor m <m@example.org> {when}\ncommitter m <m@example.org> {when}\n{headers}\nmaps\n".encode()


def commit(repo: Path, files: dict[str, bytes], when: str = OCT_13_IN_TOKYO, headers: str = "") -> str:
    return git(repo, "hash-object", "-t", "commit", "-w", "--stdin", data=commit_body(repo, files, when, headers))


def forge(repo: Path, sha: str, body: bytes, kind: bytes = b"commit") -> None:
    """A loose object stored under the id ``sha``, whatever its bytes hash to."""
    path = repo / "objects" / sha[:2] / sha[2:]
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(zlib.compress(kind + b" %d\0" % len(body) + body))


def fake_map(name: str, commit_id: str, repository: str = "hostile/maps") -> RealMap:
    return dataclasses.replace(real_maps.MAPS["yujin-rnd"], name=name, repository=repository, commit=commit_id,
                               image=f"maps/{name}.pgm", yaml=f"maps/{name}.yaml", licence_file="package.xml",
                               licence_commit=None)


def files_of(name: str) -> dict[str, bytes]:
    """A fake map's files in its repository: a 4 x 4 PGM, its YAML, a licence manifest."""
    return {f"maps/{name}.pgm": b"P5\n4 4\n255\n" + name.encode().ljust(16, b"\xfe"),
            f"maps/{name}.yaml": f"image: {name}.pgm\nresolution: 0.05\n".encode(),
            "package.xml": b"<package><license>BSD</license></package>\n"}


def digests(m: RealMap, files: dict[str, bytes]) -> dict[str, str]:
    """The manifest's lines for ``m`` when its files are ``files``."""
    return {f"{m.name}/{Path(path).name}": hashlib.sha256(data).hexdigest() for path, data in files.items()}


@pytest.fixture
def vendor(monkeypatch):
    """The script as a module (its ``main`` reads ``sys.argv``; its ``MAPS`` is patchable)."""
    spec = importlib.util.spec_from_file_location("vendor_real_maps", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def run_main(vendor, monkeypatch, *args: str) -> int:
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *args])
    try:
        return vendor.main()
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1


def written(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in out.rglob("*")) if out.exists() else []


# -- finding 1: nothing runs, no replace ref is followed -------------------------------------------
def test_a_hostile_mirror_runs_nothing_it_configures_and_its_replace_refs_are_not_followed(
        tmp_path, monkeypatch, vendor):
    mirrors, marker, program = tmp_path / "mirrors", tmp_path / "ran", tmp_path / "program.sh"
    repo = bare_repo(mirrors, "hostile/maps")
    m = fake_map("hall", "")
    original = files_of("hall")
    m = dataclasses.replace(m, commit=commit(repo, original))
    # a replace ref to a signed commit with another image, dated 1999
    signed = commit(repo, {**original, m.image: b"P5\n1 1\n255\n\0"}, when="915148800 +0000", headers=GPGSIG)
    git(repo, "update-ref", f"refs/replace/{m.commit}", signed)
    program.write_text(f'#!/bin/sh\necho "$0 $*" >> {marker}\n')
    program.chmod(0o755)
    for key in ("gpg.program", "gpg.openpgp.program", "gpg.x509.program", "gpg.ssh.program", "core.pager",
                "pager.log", "pager.show", "pager.cat-file", "core.fsmonitor", "core.sshCommand", "core.hooksPath"):
        git(repo, "config", key, str(program))
    git(repo, "config", "log.showSignature", "true")
    monkeypatch.setattr(vendor, "MAPS", {m.name: m})
    out = tmp_path / "out"

    assert run_main(vendor, monkeypatch, "--mirrors", str(mirrors), "--out", str(out), "--update") == 0
    assert not marker.exists(), f"the mirror's program ran: {marker.read_text()}"
    assert lzma.decompress((out / "hall" / "hall.pgm.xz").read_bytes()) == original[m.image]
    assert f"commit `{m.commit}` (2011-10-13)" in (out / "hall" / "SOURCE.md").read_text()


# -- finding 2: caps, one line, exit 2, nothing written --------------------------------------------
FIRST = next(iter(real_maps.MAPS.values()))
HOSTILE = {  # what the mirror of the first map's repository holds -> what the refusal names
    "a blob of 40 MiB as the image": (Path(FIRST.image).name, "MiB cap"),
    "a corrupt object as the commit": (FIRST.commit[:12], "inflate"),
    "a commit without the image": (FIRST.image, "missing"),
    "no commit": (FIRST.commit[:12], "missing"),
    "no git directory": ("no git directory", FIRST.repository),
}


@pytest.mark.parametrize("case", HOSTILE)
def test_a_hostile_mirror_is_one_line_exit_2_within_10_s_and_nothing_written(tmp_path, case):
    mirrors, out = tmp_path / "mirrors", tmp_path / "out"
    if case == "no git directory":
        (mirrors / FIRST.repository.replace("/", "+") / "repo").mkdir(parents=True)
    else:
        repo = bare_repo(mirrors, FIRST.repository)
        files = {FIRST.licence_file: b"<package/>\n", **({FIRST.yaml: b"image: x.pgm\n"} if FIRST.yaml else {})}
        if case == "a blob of 40 MiB as the image":
            forge(repo, FIRST.commit, commit_body(repo, {**files, FIRST.image: bytes(40 << 20)}))
        elif case == "a corrupt object as the commit":
            (repo / "objects" / FIRST.commit[:2]).mkdir()
            (repo / "objects" / FIRST.commit[:2] / FIRST.commit[2:]).write_bytes(b"not zlib at all" * 10)
        elif case == "a commit without the image":
            forge(repo, FIRST.commit, commit_body(repo, files))
    start = time.monotonic()
    result = subprocess.run([sys.executable, str(SCRIPT), "--mirrors", str(mirrors), "--out", str(out)],
                            capture_output=True, text=True, timeout=120, cwd=tmp_path)
    elapsed = time.monotonic() - start

    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr and len(lines[0]) < 600, result.stderr[-2000:]
    assert lines[0].endswith("nothing written"), lines[0]
    for fragment in HOSTILE[case]:
        assert fragment in lines[0], (fragment, lines[0])
    assert written(out) == []
    assert elapsed < 10, f"{elapsed:.1f} s"
    assert 40 << 20 > real_maps.MAX_IMAGE_BYTES


@pytest.mark.parametrize("second", ["its image absent", "a tree as its image"])
def test_a_later_maps_failure_writes_nothing_of_the_maps_before_it(tmp_path, monkeypatch, vendor, capsys, second):
    mirrors, out = tmp_path / "mirrors", tmp_path / "out"
    repo = bare_repo(mirrors, "hostile/maps")
    hall, lab = files_of("hall"), files_of("lab")
    broken = {path: data for path, data in lab.items() if not path.endswith(".pgm")}
    if second == "a tree as its image":
        broken["maps/lab.pgm/inside"] = b"a file in a folder named like the image"
    maps = (fake_map("hall", commit(repo, hall)), fake_map("lab", commit(repo, broken)))
    monkeypatch.setattr(vendor, "MAPS", {m.name: m for m in maps})
    monkeypatch.setattr(real_maps, "manifest", lambda: {**digests(maps[0], hall), **digests(maps[1], lab)})
    (out / "hall").mkdir(parents=True)
    (out / "hall" / "SOURCE.md").write_text("committed\n")

    assert run_main(vendor, monkeypatch, "--mirrors", str(mirrors), "--out", str(out)) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "maps/lab.pgm" in lines[0] and lines[0].endswith("nothing written"), lines
    assert written(out) == ["hall", "hall/SOURCE.md"]
    assert (out / "hall" / "SOURCE.md").read_text() == "committed\n"


def test_every_map_whole_is_written_byte_for_byte_and_nothing_else(tmp_path, monkeypatch, vendor, capsys):
    mirrors, out = tmp_path / "mirrors", tmp_path / "out"
    repo = bare_repo(mirrors, "hostile/maps")
    files = {name: files_of(name) for name in ("hall", "lab")}
    maps = [fake_map(name, commit(repo, files[name])) for name in files]
    monkeypatch.setattr(vendor, "MAPS", {m.name: m for m in maps})
    monkeypatch.setattr(real_maps, "manifest", lambda: {k: v for m in maps for k, v in digests(m, files[m.name]).items()})
    (out / "hall").mkdir(parents=True)
    (out / "hall" / "SOURCE.md").write_text("committed\n")

    assert run_main(vendor, monkeypatch, "--mirrors", str(mirrors), "--out", str(out)) == 0
    assert "wrote 2 maps" in capsys.readouterr().out
    assert written(out) == ["hall", "hall/SOURCE.md", "hall/hall.pgm.xz", "hall/hall.yaml", "hall/package.xml",
                            "lab", "lab/lab.pgm.xz", "lab/lab.yaml", "lab/package.xml"]
    for m in maps:
        assert lzma.decompress((out / m.name / f"{m.name}.pgm.xz").read_bytes()) == files[m.name][m.image]
        assert (out / m.name / f"{m.name}.yaml").read_bytes() == files[m.name][m.yaml]
    assert (out / "hall" / "SOURCE.md").read_text() == "committed\n"
