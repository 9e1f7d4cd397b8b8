"""Real buildings as SLAM stacks mapped them (downloaded into ``curlnav/worlds/data/real``), and the tasks of
``curlnav eval AGENT... --suite real`` on them.

Each map in ``MAPS`` is a ROS ``map_server`` map (YAML + PGM) that a robot with a laser scanner built
in a real building (gmapping-style SLAM, by the source's own account), from a repository under an
open licence. The maps are not in this repository: ``scripts/vendor-real-maps.py`` downloads them
once from their sources at pinned commits into ``data/real/<name>/`` (ignored by git): the YAML and
the licence file byte for byte, the image xz-compressed (decompressed: byte for byte). Committed are
each map's ``SOURCE.md`` (repository, commit, paths, licence, why the map is real) and
``data/real/MANIFEST.sha256``, the sha256 of every original file, which the loader and the tests
check. Maps are used whole, never cropped.

**Unknown cells.** ``map_server`` gives a pixel between the thresholds the value -1 (unknown), and
``curlnav.worlds.core.world`` makes every cell that is not free (0) an obstacle in the simulator: a wall
for the LiDAR and the base, like an occupied cell. Space that no scan saw free is not space the
robot knows, so it never starts, plans or drives there (AMCL and a cost map's static layer read a
map the same way). Beyond a SLAM map's outer walls everything is unknown, so the building is closed.

**The suite's task on a map** (``task(name)``, the world ``real:<name>``): ``PAIRS`` start/goal pairs
drawn from ``SEED`` with ``curlnav.worlds.core.pairs.PairSampler`` on the C-space grid (the map's own
cells whose centre lies more than ``CLEARANCE`` m from every obstacle cell: the Husky's half-width
0.335 m plus a margin), start and goal in one connected region, ``MIN_DISTANCE``-``MAX_DISTANCE`` m
apart in a straight line, the Husky's footprint free at the start, and a shortest path on that grid
(8-connected) of at most ``MAX_PATH_M``, so that a trial fits the evaluation's 60 s at 1 m/s with
room to turn; then ``BALLS`` balls (0.25 m, 0.5 kg) scattered on the pairs' shortest paths by
``curlnav.worlds.procedural.scatter.scatter_balls`` from the same seed. Same code, same maps: same tasks.

**Reading the vendored files** (anyone may have put them there): each is read only if it is a regular
file (a link is refused), at most ``MAX_TEXT_BYTES`` for a YAML or licence, ``MAX_PACKED_BYTES`` for
an image's ``.xz``, which must be one whole xz stream decompressing to at most ``MAX_IMAGE_BYTES``
(decompressed incrementally: a 520 KB xz bomb took 2.5 GB, then MemoryError); ``MANIFEST.sha256``
at most ``MAX_MANIFEST_BYTES``, every line ``<sha256>  <name>/<file>``. Every refusal is a
``WorldError``, one line naming the file and the limit. ``scripts/vendor-real-maps.py`` fetches
with the same caps.
"""

from __future__ import annotations

import hashlib
import lzma
import math
import os
import re
import stat
import tempfile
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from scipy.sparse import csgraph

from curlnav.files import FileRefused, read_capped, shown
from curlnav.worlds.core.heldout import REAL_PREFIX
from curlnav.worlds.core.pairs import PairSampler, cspace_free, pair_key
from curlnav.worlds.core.world import RandomPairs, StartGoal, World, WorldError, load_world
from curlnav.worlds.difficulty.metrics import GridGraph
from curlnav.worlds.procedural.scatter import scatter_balls

DATA = Path(__file__).resolve().parent.parent / "data" / "real"
MANIFEST = DATA / "MANIFEST.sha256"
SPEC_PREFIX = REAL_PREFIX  # a world argument ``real:<name>`` is ``task(name)``, never trained on (heldout)
SEED = 2026  # draws every map's pairs and balls
PAIRS = 6  # start/goal pairs per map (trials per map and agent)
BALLS = 8  # balls per map, on the pairs' shortest paths
CLEARANCE = 0.5  # m from a C-space cell's centre to the nearest obstacle cell's edge
MIN_DISTANCE = 6.0  # m, start to goal in a straight line
MAX_DISTANCE = 20.0  # m
MAX_PATH_M = 30.0  # m, the longest shortest path (8-connected, on the C-space grid)
MAX_DRAWS = 400  # pairs drawn per map before giving up
# caps on what is read (the real maps' largest: a 2.7 MB image, ipa-office's map.pgm; a 159 KB .xz,
# willow-garage's; an 11 KB licence; a 2.5 KB manifest)
MAX_IMAGE_BYTES = 32 << 20  # a map image (PGM) decompressed: above 100 m x 100 m at 0.02 m (25 MB)
MAX_PACKED_BYTES = 4 << 20  # an image's .xz as vendored
MAX_TEXT_BYTES = 1 << 20  # a map's YAML or licence file
MAX_MANIFEST_BYTES = 64 << 10  # MANIFEST.sha256
_MANIFEST_LINE = re.compile(r"([0-9a-f]{64})  ([^/\s]+/[^/]+)")


@dataclass(frozen=True)
class RealMap:
    """One vendored map: where it came from and what it shows. Paths are in the source repository."""

    name: str
    building: str  # what and where, one line
    kind: str  # office, lab, hall, corridor, basement
    repository: str  # owner/name on GitHub
    commit: str
    image: str  # the map image (PGM)
    yaml: str | None  # the map_server YAML; None: the source runs map_server without one (see ``yaml_text``)
    licence: str  # SPDX identifier (or the source's own words)
    licence_file: str  # the licence text, or the package manifest that declares the licence
    why_real: str  # the source's own account of how the map was made
    licence_commit: str | None = None  # the licence file's commit when not ``commit``
    yaml_text: str | None = None  # the YAML written here when the source has none (the same values)

    @property
    def folder(self) -> Path:
        return DATA / self.name

    @property
    def yaml_name(self) -> str:
        return Path(self.yaml).name if self.yaml else Path(self.image).stem + ".yaml"

    @property
    def originals(self) -> tuple[str, ...]:
        """The names of the map's original files: its YAML, its image and its licence file."""
        return (self.yaml_name, Path(self.image).name, Path(self.licence_file).name)

    @property
    def files(self) -> tuple[str, ...]:
        """The files of ``data/real/<name>/`` besides ``SOURCE.md`` (the image as ``.xz``)."""
        yaml_name, image, licence = self.originals
        return (yaml_name, image + ".xz", licence)


_JSK = "jsk-ros-pkg/jsk_demos"
_JSK_COMMIT = "b3f43475740f58402adcc24ee89bbcca6b692367"
_JSK_WHY = ("jsk_maps/README.md (as of 2024) says how the lab's floor maps are made: with their PR2 (pr2_2dnav, "
            "map_saver while driven by joystick), partial maps merged with GIMP")


def _jsk(floor: str, building: str, kind: str) -> RealMap:
    return RealMap(f"jsk-{floor}", building, kind, _JSK, _JSK_COMMIT, f"jsk_maps/raw_maps/{floor}-0.05.pgm",
                   f"jsk_maps/raw_maps/{floor}.yaml", "BSD", "jsk_maps/manifest.xml", _JSK_WHY)


#: the maps of the ``real`` suite, in its order
MAPS: dict[str, RealMap] = {m.name: m for m in (
    RealMap("willow-garage", "Willow Garage's office building, Menlo Park, CA (the ROS navigation tutorials' map)",
            "office", "ros-planning/navigation_tutorials", "115e46ec9e65d49756b5d2155326ad2c1694d1e6",
            "navigation_stage/stage_config/maps/willow-full-0.05.pgm", None, "BSD",
            "navigation_stage/package.xml",
            "the map of Willow Garage's building that the navigation stack's tutorials localise in (amcl) "
            "and Stage renders, served by launch/move_base_amcl_5cm.launch as `map_server willow-full-0.05.pgm "
            "0.05`; the source does not say how it was made, the map shows a laser SLAM map's marks (rays "
            "through doorways and windows, ragged walls, clutter)",
            yaml_text="image: willow-full-0.05.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
                      "occupied_thresh: 0.65\nfree_thresh: 0.196\n"),
    RealMap("ipa-office", "Fraunhofer IPA, office floor (4th floor), Stuttgart", "office", "ipa320/cob_environments",
            "dfe43be239523f513ea488f5a2980e1f7eb4c4e3", "cob_default_env_config/envs/ipa-office/map.pgm",
            "cob_default_env_config/envs/ipa-office/map.yaml", "Apache-2.0", "LICENSE",
            "commit c43c5cd (2014-03-18): 'added new high resolution map that is verified with laser "
            "tracker', the Care-O-bot's map of the IPA office at 0.025 m",
            licence_commit="72ae32d85bef0fde67714ee90bc00fdf33fd8fbc"),
    RealMap("yujin-rnd", "Yujin Robot's R&D office, Seoul", "office", "yujinrobot/yujin_maps",
            "fad652d07cd14b89dea473b63e5ab500327c7b7c", "maps/yujin_rnd_hokuyo.pgm", "maps/yujin_rnd_hokuyo.yaml",
            "BSD", "package.xml",
            "maps/yujin_rnd_hokuyo: the R&D office mapped with a Hokuyo laser (commit c3445fd: 'cropped "
            "version of yujin_rnd map')"),
    _jsk("eng2-2f", "University of Tokyo, Engineering Building 2, 2nd floor: a large open hall with pillars", "hall"),
    _jsk("eng2-3f", "University of Tokyo, Engineering Building 2, 3rd floor", "office"),
    _jsk("eng2-7f", "University of Tokyo, Engineering Building 2, 7th floor (the JSK lab's floor)", "lab"),
    _jsk("eng8-1f", "University of Tokyo, Engineering Building 8, ground floor", "office"),
    _jsk("eng8-6f", "University of Tokyo, Engineering Building 8, 6th floor: a long corridor", "corridor"),
    _jsk("eng8-b1f", "University of Tokyo, Engineering Building 8, basement", "basement"),
)}


def check_name(name: str) -> RealMap:
    """The map ``name``, else ``WorldError`` (one line) naming the maps."""
    if name not in MAPS:
        raise WorldError(f"unknown real map {name!r}; choose from {', '.join(MAPS)}")
    return MAPS[name]


def missing(name: str | None = None) -> list[Path]:
    """The vendored files that are not here (of one map, or of every map)."""
    maps = [check_name(name)] if name else list(MAPS.values())
    return [m.folder / f for m in maps for f in m.files if not (m.folder / f).is_file()]


def read_vendored(path: Path, max_bytes: int, what: str) -> bytes:
    """The bytes of a vendored file; ``WorldError`` (one line) when it is not a regular file (a link,
    a folder, a device), holds more than ``max_bytes`` or cannot be read."""
    try:
        if not stat.S_ISREG(os.lstat(path).st_mode):
            raise WorldError(f"{path}: not a regular file (a link, a folder or a device); refused")
        return read_capped(path, max_bytes, what)
    except FileRefused as exc:
        raise WorldError(str(exc)) from None
    except OSError as exc:
        raise WorldError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def unxz(packed: bytes, source: Path | str, max_bytes: int = MAX_IMAGE_BYTES, what: str = "a map image") -> bytes:
    """The bytes of one whole xz stream, decompressed incrementally (at most ``max_bytes`` + 1 bytes
    ever held). ``WorldError`` (one line naming ``source``) when the stream is not whole (empty,
    truncated, not xz, bytes after its end) or decompresses to more than ``max_bytes`` (``what``'s
    cap; ``curlnav.worlds.real.sdf`` reads a packed Gazebo world with it too)."""
    unpacker = lzma.LZMADecompressor(format=lzma.FORMAT_XZ)
    try:
        data = unpacker.decompress(packed, max_length=max_bytes + 1)
    except lzma.LZMAError as exc:
        raise WorldError(f"{source}: not a whole xz file ({exc}); refused") from None
    if len(data) > max_bytes:
        raise WorldError(f"{source}: decompresses to more than {max_bytes >> 20} MiB ({what}'s cap); refused")
    if not unpacker.eof:
        raise WorldError(f"{source}: not a whole xz file (it ends early); refused")
    if unpacker.unused_data:
        raise WorldError(f"{source}: not a whole xz file ({len(unpacker.unused_data)} bytes after its end); refused")
    return data


def manifest() -> dict[str, str]:
    """``<name>/<file>`` -> the sha256 of the original bytes (the committed ``MANIFEST.sha256``).
    ``WorldError`` (one line naming the file, and the line) when it is above ``MAX_MANIFEST_BYTES``,
    not UTF-8, or a line is not ``<sha256>  <name>/<file>``."""
    try:
        text = read_vendored(MANIFEST, MAX_MANIFEST_BYTES, "manifest").decode("utf-8")
    except UnicodeDecodeError as exc:
        raise WorldError(f"{MANIFEST}: not UTF-8 text (byte {exc.start})") from None
    digests = {}
    for number, line in enumerate(text.splitlines(), 1):
        match = _MANIFEST_LINE.fullmatch(line)
        if match is None and line.strip():
            raise WorldError(f"{MANIFEST}: line {number} is not '<sha256>  <name>/<file>': {shown(line)}")
        if match is not None:
            digests[match[2]] = match[1]
    return digests


def original_bytes(name: str, file: str) -> bytes:
    """A downloaded file's original bytes (``file`` as in the source: the image decompressed), checked
    against the committed manifest; ``WorldError`` (one line) when they differ, or when a file is
    refused (see the module docstring: links, caps, xz that is not whole)."""
    m = check_name(name)
    packed = m.folder / (file + ".xz")
    if os.path.lexists(packed):
        data = unxz(read_vendored(packed, MAX_PACKED_BYTES, "packed map image"), packed)
    else:
        data = read_vendored(m.folder / file, MAX_IMAGE_BYTES if file == m.originals[1] else MAX_TEXT_BYTES,
                             "map file")
    digest, expected = hashlib.sha256(data).hexdigest(), manifest().get(f"{name}/{file}")
    if digest != expected:
        raise WorldError(f"real map {name}: {file} is not the source's (sha256 {digest[:12]}..., MANIFEST.sha256 says "
                         f"{str(expected)[:12]}...); scripts/vendor-real-maps.py downloads it again")
    return data


def map_world(name: str) -> World:
    """The downloaded map as a ``World`` (no pairs, no balls), named ``real-<name>``."""
    m = check_name(name)
    absent = missing(name)
    if absent:
        raise WorldError(f"real map {name!r} is not downloaded here ({absent[0]} is missing); "
                         f"scripts/vendor-real-maps.py downloads the real maps once (needs GitHub)")
    with tempfile.TemporaryDirectory(prefix="curlnav-real-") as tmp:
        yaml_path = Path(tmp) / m.yaml_name
        yaml_path.write_bytes(original_bytes(name, m.yaml_name))
        image = m.originals[1]
        (Path(tmp) / image).write_bytes(original_bytes(name, image))
        world = load_world(yaml_path)
    return world.with_changes(name=f"real-{name}", source=f"{SPEC_PREFIX}{name}")


def cspace_graph(world: World) -> tuple[np.ndarray, GridGraph]:
    """The C-space grid of the suite (True: free, at ``CLEARANCE``) and its 8-connected graph."""
    free = cspace_free(world, CLEARANCE)
    return free, GridGraph(~free)


def path_length(world: World, graph: GridGraph, pair: StartGoal, limit: float = math.inf) -> float:
    """The shortest path (m) from the pair's start cell to its goal cell on ``graph`` (8-connected,
    cell centres); ``inf`` when there is none within ``limit`` (m)."""
    (sy, sx), (gy, gx) = world.cell_of(pair.x, pair.y), world.cell_of(pair.gx, pair.gy)
    cols = graph.shape[1]
    dist = csgraph.dijkstra(graph.graph, directed=False, indices=sy * cols + sx,
                            limit=limit / world.resolution if math.isfinite(limit) else np.inf)
    return float(dist[gy * cols + gx]) * world.resolution


def draw_pairs(world: World, count: int = PAIRS, seed: int = SEED) -> tuple[StartGoal, ...]:
    """``count`` pairs of the suite (see the module docstring), named ``p1..``; same world and
    seed, same pairs. ``WorldError`` (one line) when ``MAX_DRAWS`` draws do not find them."""
    sampler = PairSampler(world, RandomPairs(min_distance=MIN_DISTANCE, clearance=CLEARANCE))
    _, graph = cspace_graph(world)
    rng = np.random.default_rng(seed)
    pairs: list[StartGoal] = []
    seen: set = set()
    for _ in range(MAX_DRAWS):
        pair = sampler.draw(rng, excluded=seen, name=f"p{len(pairs) + 1}", max_distance=MAX_DISTANCE)
        seen.add(pair_key(pair.x, pair.y, pair.gx, pair.gy))
        if path_length(world, graph, pair, MAX_PATH_M) <= MAX_PATH_M:
            pairs.append(pair)
            if len(pairs) == count:
                return tuple(pairs)
    raise WorldError(f"{world.source}: found {len(pairs)} of {count} start/goal pairs {MIN_DISTANCE:g}-"
                     f"{MAX_DISTANCE:g} m apart with a path of at most {MAX_PATH_M:g} m in {MAX_DRAWS} draws")


@cache
def task(name: str) -> World:
    """The suite's world ``real:<name>``: the map with its ``PAIRS`` pairs and ``BALLS`` balls."""
    world = map_world(name)
    return scatter_balls(world.with_changes(pairs=draw_pairs(world)), BALLS, seed=SEED)


def specs() -> tuple[str, ...]:
    """The suite's world arguments, ``real:<name>`` for every map in ``MAPS``."""
    return tuple(SPEC_PREFIX + name for name in MAPS)
