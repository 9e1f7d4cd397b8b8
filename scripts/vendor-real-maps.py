#!/usr/bin/env python3
"""Vendor the real buildings' SLAM maps of ``curlnav.worlds.real_maps.MAPS`` into ``curlnav/worlds/data/real/``.

For every map, from its repository at its commit (``git show COMMIT:PATH``, bytes as stored):

- ``<name>/<map>.yaml``: the map_server YAML, byte for byte; where the source has none (Willow
  Garage: its launch files run ``map_server IMAGE RESOLUTION``), the YAML of ``RealMap.yaml_text``,
  the same values (origin 0, negate 0, thresholds 0.65 and 0.196: map_server's defaults then);
- ``<name>/<image>.pgm.xz``: the image, xz-compressed (decompressed: byte for byte);
- ``<name>/<licence file>``: the licence text, or the package manifest that declares the licence,
  byte for byte (from ``licence_commit`` when set);
- ``<name>/SOURCE.md`` (``--update`` only): repository, commit and date, paths, licence, why the map is real;
- ``MANIFEST.sha256`` (``--update`` only): the sha256 of every original file (``<name>/<file>``, the image as the PGM).

Each map is loaded once written (``curlnav.worlds.real_maps.map_world``), and the suite's pairs and
balls drawn (``task``), so a map that cannot hold the suite stops the script.

Every fetched file is checked against the committed ``MANIFEST.sha256`` before anything is written
(a mismatch writes nothing); ``--update`` (a maintainer adding or moving a map) writes the manifest
and every ``SOURCE.md`` anew instead.

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
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from curlnav.worlds import real_maps  # noqa: E402
from curlnav.worlds.real_maps import MAPS, RealMap  # noqa: E402


def git(git_dir: Path, *args: str) -> bytes:
    return subprocess.run(["git", f"--git-dir={git_dir}", *args], capture_output=True, check=True).stdout


def git_dir_of(repository: str, mirrors: Path | None, scratch: Path) -> Path:
    """A git directory holding ``repository``'s history: the mirror's, or a fresh bare clone."""
    if mirrors is not None:
        base = mirrors / repository.replace("/", "+") / "repo"
        for candidate in (base / ".git", base):
            if (candidate / "objects").is_dir():
                return candidate
        raise SystemExit(f"no git directory for {repository} under {mirrors}")
    target = scratch / repository.replace("/", "+")
    if not target.exists():
        subprocess.run(["git", "clone", "--quiet", "--bare", "--filter=blob:none",
                        f"https://github.com/{repository}.git", str(target)], check=True)
    return target


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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mirrors", type=Path, default=None,
                        help="folder of git snapshots named owner+name/repo (default: clone from GitHub)")
    parser.add_argument("--out", type=Path, default=real_maps.DATA)
    parser.add_argument("--update", action="store_true",
                        help="a maintainer's: write MANIFEST.sha256 and every SOURCE.md anew from what was fetched "
                             "(by default the downloads are checked against the committed manifest and nothing "
                             "committed is touched)")
    args = parser.parse_args()
    today = datetime.date.today().isoformat()
    expected = {} if args.update else real_maps.manifest()
    manifest = []
    with tempfile.TemporaryDirectory(prefix="vendor-real-maps-") as scratch:
        for m in MAPS.values():
            git_dir = git_dir_of(m.repository, args.mirrors, Path(scratch))
            folder = args.out / m.name
            folder.mkdir(parents=True, exist_ok=True)
            image = git(git_dir, "show", f"{m.commit}:{m.image}")
            yaml_bytes = git(git_dir, "show", f"{m.commit}:{m.yaml}") if m.yaml else m.yaml_text.encode()
            licence = git(git_dir, "show", f"{m.licence_commit or m.commit}:{m.licence_file}")
            outputs = {m.yaml_name: yaml_bytes, Path(m.image).name: image, Path(m.licence_file).name: licence}
            for file, data in outputs.items():
                key = f"{m.name}/{file}"
                if not args.update and hashlib.sha256(data).hexdigest() != expected.get(key):
                    raise SystemExit(f"{key}: the fetched bytes do not match MANIFEST.sha256 (sha256 "
                                     f"{hashlib.sha256(data).hexdigest()}, expected {expected.get(key)}); nothing written")
            (folder / m.yaml_name).write_bytes(yaml_bytes)
            (folder / (Path(m.image).name + ".xz")).write_bytes(lzma.compress(image, preset=9 | lzma.PRESET_EXTREME))
            (folder / Path(m.licence_file).name).write_bytes(licence)
            date = git(git_dir, "log", "-1", "--format=%cs", m.commit).decode().strip()
            licence_date = (git(git_dir, "log", "-1", "--format=%cs", m.licence_commit).decode().strip()
                            if m.licence_commit else date)
            if args.update:
                (folder / "SOURCE.md").write_text(source_md(m, date, licence_date, today))
            manifest += [f"{hashlib.sha256(data).hexdigest()}  {m.name}/{file}" for file, data in outputs.items()]
            if args.out == real_maps.DATA:
                world = real_maps.task(m.name)
                print(f"{m.name}: {world.occupancy.shape[1]} x {world.occupancy.shape[0]} cells at "
                      f"{world.resolution:g} m, {len(world.pairs)} pairs, {len(world.balls)} balls")
    if args.update:
        (args.out / "MANIFEST.sha256").write_text("\n".join(manifest) + "\n")
    print(f"wrote {len(MAPS)} maps in {args.out}" + (" and MANIFEST.sha256, SOURCE.md anew" if args.update else
                                                       ", every file as MANIFEST.sha256 says"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
