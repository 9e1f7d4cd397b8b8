"""Gazebo SDF worlds as curlnav worlds: static boxes and cylinders rasterised onto the grid.

``read_sdf(path)`` walks a ``.world`` / ``.sdf`` file's models (nested models and links
included), composes each collision's pose (model, link and collision ``<pose>``, with roll,
pitch and yaw) and keeps the upright **boxes** and **cylinders** whose vertical extent meets
``(0, MAX_HEIGHT]`` m (a ground robot meets nothing wholly underground or overhead). A file named
``*.xz`` (``world_7.world.xz``, as the BARN worlds are vendored) is decompressed first, under
``curlnav.worlds.real.real_maps``' caps for packed files (``MAX_PACKED_BYTES`` packed, ``unxz``) and
``MAX_SDF_BYTES`` unpacked. Everything else a collision may hold is *unsupported* and named
(``kind 'model/link/collision'``): meshes, heightmaps, spheres, capsules, ellipsoids, polylines,
images, planes other than the ground plane, tilted boxes and cylinders, models that are not
static, ``<include>`` (a model from Gazebo's model path), actors, populations and roads. The
ground plane (normal +z through z = 0) is dropped silently; so is the ``<state>`` snapshot (the
poses it repeats are not the world's definition).

``rasterise(shapes, resolution, origin, shape)`` marks a cell occupied when its centre lies inside
a shape's footprint. ``world_from_sdf`` makes the ``World`` (no pairs: a plain map, as a SLAM
map loads) at ``DEFAULT_RESOLUTION``, fine enough for the BARN Challenge's 0.075 m cylinders;
``import_sdf`` writes it as a world file, whole or not at all.

A file is anyone's, so its cost is bounded before the work (issue 55): at most ``MAX_SDF_BYTES``,
no DOCTYPE (SDF has none; its entities expand), ``MAX_NESTING`` levels of models, ``MAX_SHAPES``
collisions, footprints within ``MAX_COORDINATE`` of the origin, ``MAX_GRID_CELLS`` cells of grid
and ``MAX_RASTER_CELLS`` cells tested; names are cut to ``MAX_NAME`` characters. Each refusal is
an ``SdfError``: one line naming the file and the limit.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from curlnav.files import FileRefused, read_capped, shown
from curlnav.worlds.core.world import World, WorldError, save_world

DEFAULT_RESOLUTION = 0.025  # m per cell: a 0.075 m cylinder is a disc 6 cells across
DEFAULT_MARGIN = 1.0  # m of free space around the shapes
MAX_HEIGHT = 2.0  # m; a shape wholly above this (or wholly below the ground) blocks nothing
MAX_SDF_BYTES = 8 << 20  # 10 x the largest BARN world (0.77 MB); ElementTree holds up to 40 bytes per byte
MAX_COORDINATE = 100_000.0  # m from the origin that a footprint may reach (Gazebo worlds span metres to km)
MAX_NESTING = 32  # levels of <model> within <model>; a BARN world has 1, Gazebo's own worlds a few
MAX_SHAPES = 20_000  # <collision> elements, kept or not; a BARN world has at most 366
MAX_GRID_CELLS = 25_000_000  # cells of the occupancy grid (25 MB of bool; 5000 x 5000)
MAX_RASTER_CELLS = 50_000_000  # cells tested, summed over the shapes' bounding boxes (a few seconds)
MAX_NAME = 60  # characters of each model, link or collision name kept (nested paths stay short)
_CHUNK_CELLS = 1 << 20  # cells of one shape tested at once: a few 8 MB arrays, whatever its size
UPRIGHT_TOLERANCE = 1e-6  # |cos| of the shape's axis with the vertical, off 1
_UNSUPPORTED_GEOMETRY = ("mesh", "heightmap", "sphere", "capsule", "ellipsoid", "polyline", "image")


class SdfError(WorldError):
    """An SDF file curlnav cannot read or represent; the message is one line naming the file."""


class _NoDoctype(ET.TreeBuilder):
    """A tree builder that refuses a DOCTYPE before its entities are declared, let alone expanded."""

    def doctype(self, name: str, pubid: str, system: str) -> None:
        raise SdfError("declares a DOCTYPE (SDF has none, and its entities could expand far past the file's size)")


@dataclass(frozen=True)
class Shape:
    """A static obstacle's footprint: ``kind`` ``"box"`` (full sizes ``size_x, size_y`` along its own
    axes, turned by ``yaw``) or ``"cylinder"`` (``radius``); centre ``x, y`` (m, world frame);
    ``name``: ``model/link/collision``."""

    kind: str
    name: str
    x: float
    y: float
    yaw: float = 0.0
    size_x: float = 0.0
    size_y: float = 0.0
    radius: float = 0.0

    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` of the footprint (m)."""
        if self.kind == "cylinder":
            return self.x - self.radius, self.y - self.radius, self.x + self.radius, self.y + self.radius
        c, s = abs(math.cos(self.yaw)), abs(math.sin(self.yaw))
        hx, hy = (c * self.size_x + s * self.size_y) / 2, (s * self.size_x + c * self.size_y) / 2
        return self.x - hx, self.y - hy, self.x + hx, self.y + hy


@dataclass(frozen=True)
class SdfContents:
    """What ``read_sdf`` found: the shapes it keeps and the unsupported items (``kind 'name'``)."""

    shapes: tuple[Shape, ...]
    unsupported: tuple[str, ...]


@dataclass
class _Walk:
    """What ``read_sdf`` gathers from ``path`` as it walks the models."""

    path: Path
    shapes: list[Shape] = field(default_factory=list)
    unsupported: list[str] = field(default_factory=list)
    collisions: int = 0


def _name(element: ET.Element) -> str:
    """``element``'s name attribute, cut to ``MAX_NAME`` characters."""
    name = element.get("name", "?")
    return name if len(name) <= MAX_NAME else name[:MAX_NAME] + "..."


def _pose(element: ET.Element, path: Path, where: str) -> np.ndarray:
    """The 4 x 4 transform of ``element``'s ``<pose>`` (identity without one)."""
    pose = element.find("pose")
    if pose is None:
        return np.eye(4)
    relative_to = pose.get("relative_to") or pose.get("frame") or ""
    if relative_to:
        raise SdfError(f"{path}: {where} has a pose relative to frame {shown(relative_to)}; only poses relative to the "
                       "parent are supported")
    try:
        values = [float(v) for v in (pose.text or "").split()]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise SdfError(f"{path}: {where} has a malformed pose {(pose.text or '').strip()[:60]!r} (expected x y z roll pitch yaw)")
    x, y, z, roll, pitch, yaw = values
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    out = np.eye(4)
    out[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                   [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                   [-sp, cp * sr, cp * cr]]
    out[:3, 3] = (x, y, z)
    return out


def _numbers(element: ET.Element | None, count: int, path: Path, where: str) -> list[float]:
    try:
        values = [float(v) for v in ((element.text if element is not None else "") or "").split()]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) and v > 0 for v in values):
        shown = (element.text or "").strip()[:60] if element is not None else "nothing"
        raise SdfError(f"{path}: {where} needs {count} positive number{'s' * (count > 1)}, got {shown!r}")
    return values


def _is_ground_plane(geometry: ET.Element, transform: np.ndarray) -> bool:
    normal = geometry.find("normal")
    try:
        n = np.array([float(v) for v in (normal.text or "").split()]) if normal is not None else np.array([0, 0, 1.0])
    except ValueError:
        return False
    if n.shape != (3,) or not np.linalg.norm(n):
        return False
    world_normal = transform[:3, :3] @ (n / np.linalg.norm(n))
    return bool(world_normal[2] > 1 - UPRIGHT_TOLERANCE and abs(transform[2, 3]) < 1e-9)


def _shape(collision: ET.Element, transform: np.ndarray, name: str, path: Path) -> Shape | str | None:
    """The collision's ``Shape``, an unsupported item's description (``str``), or None (ignored:
    the ground plane, or nothing a ground robot meets)."""
    geometry = collision.find("geometry")
    if geometry is None or len(geometry) == 0:
        return None
    kind = geometry[0].tag
    if kind == "empty":
        return None
    if kind == "plane":
        return None if _is_ground_plane(geometry[0], transform) else f"plane {shown(name)} (not the ground)"
    if kind not in ("box", "cylinder"):
        return f"{kind[:MAX_NAME]} {shown(name)}"
    rotation = transform[:3, :3]
    if kind == "box":
        sx, sy, sz = _numbers(geometry[0].find("size"), 3, path, f"box {shown(name)} <size>")
        up = int(np.argmax(np.abs(rotation[2])))  # the box axis nearest the vertical
        if abs(rotation[2, up]) < 1 - UPRIGHT_TOLERANCE:
            return f"tilted box {shown(name)}"
        sizes = [sx, sy, sz]
        height = sizes.pop(up)
        axes = [i for i in range(3) if i != up]
        yaw = math.atan2(rotation[1, axes[0]], rotation[0, axes[0]])
        shape = Shape("box", name, float(transform[0, 3]), float(transform[1, 3]), yaw, sizes[0], sizes[1])
    else:
        radius, height = _numbers(geometry[0].find("radius"), 1, path, f"cylinder {shown(name)} <radius>")[0], \
            _numbers(geometry[0].find("length"), 1, path, f"cylinder {shown(name)} <length>")[0]
        if abs(rotation[2, 2]) < 1 - UPRIGHT_TOLERANCE:
            return f"tilted cylinder {shown(name)}"
        shape = Shape("cylinder", name, float(transform[0, 3]), float(transform[1, 3]), radius=radius)
    z = transform[2, 3]
    if z + height / 2 <= 0.0 or z - height / 2 > MAX_HEIGHT:
        return None
    return shape


def _walk_model(model: ET.Element, parent: np.ndarray, static: bool, prefix: str, walk: _Walk, depth: int = 1) -> None:
    path = walk.path
    name = f"{prefix}{_name(model)}"
    if depth > MAX_NESTING:
        raise SdfError(f"{path}: models nested more than {MAX_NESTING} deep (at {shown(name)}); refused")
    transform = parent @ _pose(model, path, f"model {shown(name)}")
    flag = model.find("static")
    if flag is not None:
        static = (flag.text or "").strip().lower() in ("1", "true")
    for child in model:
        if child.tag == "model":
            _walk_model(child, transform, static, f"{name}/", walk, depth + 1)
        elif child.tag == "include":
            walk.unsupported.append(f"include {shown(name + '/' + (child.findtext('uri') or '?').strip())}")
        elif child.tag == "link":
            link_name = f"{name}/{_name(child)}"
            link = transform @ _pose(child, path, f"link {shown(link_name)}")
            for collision in child.findall("collision"):
                walk.collisions += 1
                if walk.collisions > MAX_SHAPES:
                    raise SdfError(f"{path}: more than {MAX_SHAPES} collisions; refused (a BARN world has at most 366)")
                where = f"{link_name}/{_name(collision)}"
                found = _shape(collision, link @ _pose(collision, path, f"collision {shown(where)}"), where, path)
                if found is None:
                    continue
                if isinstance(found, str):
                    walk.unsupported.append(found)
                elif not static:
                    walk.unsupported.append(f"{found.kind} {shown(where)} (its model is not static)")
                else:
                    walk.shapes.append(found)


def read_sdf(path: str | Path) -> SdfContents:
    """The static boxes and cylinders of an SDF world (or model) file, and what it cannot represent.
    ``SdfError`` (one line) for a file that is not readable SDF."""
    path = Path(path)
    try:
        if path.suffix == ".xz":  # a packed world (the BARN worlds as vendored): the real maps' caps
            from curlnav.worlds.real.real_maps import MAX_PACKED_BYTES, unxz

            data = unxz(read_capped(path, MAX_PACKED_BYTES, "packed Gazebo SDF file"), path, MAX_SDF_BYTES,
                        "a Gazebo SDF file")
        else:
            data = read_capped(path, MAX_SDF_BYTES, "Gazebo SDF file")
        parser = ET.XMLParser(target=_NoDoctype())
        for start in range(0, len(data), 1 << 16):  # expat goes on to the end of a chunk after a refusal
            parser.feed(data[start:start + (1 << 16)])
        root = parser.close()
    except OSError as exc:
        raise SdfError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise SdfError(str(exc)) from None
    except SdfError as exc:
        raise SdfError(f"{path}: {exc}") from None
    except WorldError as exc:  # unxz's refusal, naming the file
        raise SdfError(str(exc)) from None
    except ET.ParseError as exc:
        raise SdfError(f"{path}: not well-formed XML ({exc})") from None
    if root.tag != "sdf":
        raise SdfError(f"{path}: not an SDF file (its root element is <{root.tag[:MAX_NAME]}>, expected <sdf>)")
    walk = _Walk(path)
    containers = root.findall("world") or [root]
    for container in containers:
        for child in container:
            if child.tag == "model":
                _walk_model(child, np.eye(4), False, "", walk)
            elif child.tag == "include":
                walk.unsupported.append(f"include {shown((child.findtext('uri') or '?').strip())}")
            elif child.tag in ("actor", "population", "road"):
                walk.unsupported.append(f"{child.tag} {shown(_name(child))}")
    return SdfContents(tuple(walk.shapes), tuple(walk.unsupported))


def _window(s: Shape, resolution: float, origin: tuple[float, float], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(r0, r1, c0, c1)``: the cells of the grid that ``s``'s bounding box covers (empty when outside)."""
    rows, cols = shape
    x0, y0, x1, y1 = s.bounds()
    c0, c1 = max(int(math.floor((x0 - origin[0]) / resolution)), 0), min(int(math.ceil((x1 - origin[0]) / resolution)), cols)
    r0, r1 = max(int(math.floor((y0 - origin[1]) / resolution)), 0), min(int(math.ceil((y1 - origin[1]) / resolution)), rows)
    return r0, max(r1, r0), c0, max(c1, c0)


def raster_cells(shapes: tuple[Shape, ...] | list[Shape], resolution: float, origin: tuple[float, float],
                 shape: tuple[int, int]) -> int:
    """The cells ``rasterise`` tests: its work, summed over the shapes' bounding boxes on the grid."""
    return sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in (_window(s, resolution, origin, shape) for s in shapes))


def rasterise(shapes: tuple[Shape, ...] | list[Shape], resolution: float, origin: tuple[float, float],
              shape: tuple[int, int]) -> np.ndarray:
    """Occupancy (bool, ``shape`` = (rows, cols), row 0 at the smallest y) with a cell occupied
    when its centre lies inside a footprint; cell (0, 0)'s outer corner at ``origin`` (m). A shape
    is tested a band of rows at a time (``_CHUNK_CELLS``), so memory stays bounded by the grid's."""
    occupancy = np.zeros(shape, bool)
    for s in shapes:
        r0, r1, c0, c1 = _window(s, resolution, origin, shape)
        if c0 >= c1 or r0 >= r1:
            continue
        dx = origin[0] + (np.arange(c0, c1) + 0.5) * resolution - s.x
        band = max(_CHUNK_CELLS // (c1 - c0), 1)
        for top in range(r0, r1, band):
            bottom = min(top + band, r1)
            dy = (origin[1] + (np.arange(top, bottom) + 0.5) * resolution - s.y)[:, None]
            if s.kind == "cylinder":
                inside = dx * dx + dy * dy <= s.radius * s.radius
            else:
                c, sn = math.cos(s.yaw), math.sin(s.yaw)
                inside = (np.abs(c * dx + sn * dy) <= s.size_x / 2) & (np.abs(-sn * dx + c * dy) <= s.size_y / 2)
            occupancy[top:bottom, c0:c1] |= inside
    return occupancy


def grid_frame(shapes: tuple[Shape, ...] | list[Shape], resolution: float, margin: float,
               include: tuple[tuple[float, float], ...] = ()) -> tuple[tuple[float, float], tuple[int, int]]:
    """``(origin, (rows, cols))`` of a grid holding every footprint and point of ``include`` with
    ``margin`` (m) around; the origin is a whole number of cells from (0, 0)."""
    xs = [v for s in shapes for v in s.bounds()[0::2]] + [p[0] for p in include]
    ys = [v for s in shapes for v in s.bounds()[1::2]] + [p[1] for p in include]
    c0, r0 = math.floor((min(xs) - margin) / resolution), math.floor((min(ys) - margin) / resolution)
    c1, r1 = math.ceil((max(xs) + margin) / resolution), math.ceil((max(ys) + margin) / resolution)
    return (c0 * resolution, r0 * resolution), (r1 - r0, c1 - c0)


def world_from_sdf(path: str | Path, resolution: float = DEFAULT_RESOLUTION, margin: float = DEFAULT_MARGIN,
                   skip_unsupported: bool = False) -> tuple[World, SdfContents]:
    """The ``World`` of an SDF file's static boxes and cylinders (``resolution`` m per cell, ``margin``
    m of free space around them) and what was read. Anything unsupported is refused
    (``SdfError``, one line naming it) unless ``skip_unsupported``."""
    path = Path(path)
    if not (math.isfinite(resolution) and 0.001 <= resolution <= 1.0):
        raise SdfError(f"{path}: --resolution must be 0.001-1 m, got {resolution}")
    if not (math.isfinite(margin) and 0 <= margin <= 100):
        raise SdfError(f"{path}: --margin must be 0-100 m, got {margin}")
    contents = read_sdf(path)
    if contents.unsupported and not skip_unsupported:
        more = f" (and {len(contents.unsupported) - 3} more)" if len(contents.unsupported) > 3 else ""
        raise SdfError(f"{path}: cannot represent {', '.join(contents.unsupported[:3])}{more}; curlnav reads static "
                       "boxes and cylinders (--skip-unsupported drops the rest)")
    if not contents.shapes:
        raise SdfError(f"{path}: no static box or cylinder to make a world of")
    far = max(abs(v) for s in contents.shapes for v in s.bounds())
    if not far <= MAX_COORDINATE:  # inf too: grid_frame's cells must be whole numbers
        raise SdfError(f"{path}: a shape reaches {far:.3g} m from the origin, beyond {MAX_COORDINATE:.0f} m; refused")
    origin, shape = grid_frame(contents.shapes, resolution, margin)
    if shape[0] * shape[1] > MAX_GRID_CELLS:
        raise SdfError(f"{path}: {shape[1]} x {shape[0]} cells at {resolution} m is above {MAX_GRID_CELLS // 10**6} "
                       "million; use a coarser --resolution")
    work = raster_cells(contents.shapes, resolution, origin, shape)
    if work > MAX_RASTER_CELLS:
        raise SdfError(f"{path}: its shapes cover {work / 1e6:.0f} million cells at {resolution} m, above "
                       f"{MAX_RASTER_CELLS // 10**6} million; use a coarser --resolution")
    occupancy = rasterise(contents.shapes, resolution, origin, shape)
    world = World(name=path.name.split(".")[0], occupancy=occupancy, resolution=resolution, origin=origin,
                  source=f"sdf:{path}")
    return world, contents


def check_output(source: Path, out: Path) -> None:
    """Refuse (``SdfError``, one line) a world file ``out`` that cannot be written whole, before any
    work: not a ``.yaml`` path, the input itself (as the YAML or the image beside it), a folder, or
    under something that is not a folder."""
    if out.suffix not in (".yaml", ".yml"):
        raise SdfError(f"--out must be a world YAML path (.yaml), got {str(out)!r}")
    try:
        for target in (out, out.with_suffix(".pgm")):
            if target.resolve() == source.resolve():
                raise SdfError(f"{source}: writing {target} would overwrite the input; name another world YAML with --out")
            if target.is_dir():
                raise SdfError(f"--out {out}: {target} is a folder; name a world YAML file to write")
        folder = out.parent
        while not folder.exists():  # False under a file too
            folder = folder.parent
    except (OSError, RuntimeError) as exc:  # RuntimeError: a symlink loop
        raise SdfError(f"--out {out}: cannot look there: {getattr(exc, 'strerror', None) or exc}") from None
    if not folder.is_dir():
        raise SdfError(f"--out {out}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise SdfError(f"--out {out}: cannot write in {folder}")


def import_sdf(source: str | Path, out: str | Path | None = None, resolution: float = DEFAULT_RESOLUTION,
               margin: float = DEFAULT_MARGIN, skip_unsupported: bool = False) -> tuple[Path, World, SdfContents]:
    """``world_from_sdf(source, ...)`` written as the world YAML ``out`` (default: ``source`` with
    ``.yaml``, its ``.xz`` dropped first) and its PGM beside it, named ``out``'s stem: ``(out,
    world, contents)``. The output is checked before any work (``check_output``) and written whole
    (``save_world``)."""
    source = Path(source)
    out = Path(out) if out else (source.with_suffix("") if source.suffix == ".xz" else source).with_suffix(".yaml")
    check_output(source, out)
    world, contents = world_from_sdf(source, resolution, margin, skip_unsupported)
    world = world.with_changes(name=out.stem)
    try:
        save_world(world, out)  # whole or not at all
    except OSError as exc:
        raise SdfError(f"--out {out}: cannot write it: {exc.strerror or exc}") from None
    return out, world, contents
