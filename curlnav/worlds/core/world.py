"""World model: an occupancy grid plus movable objects and start/goal pairs.

A world is stored on disk as a ROS ``map_server`` map (a YAML file next to a PGM or PNG image,
with ``image``, ``resolution``, ``origin``, ``negate``, ``occupied_thresh`` and ``free_thresh``)
extended with curlnav's own keys (``wall_height``, ``balls``, ``doors``, ``boxes``, ``pairs``,
``held_out_pairs``, ``ball_regions``, ``random_pairs``). A map written by any ROS SLAM stack loads
as a world with no movable objects and no pairs; add those keys to train on it.

Conventions (all lengths in metres, angles in radians):

- ``occupancy[iy, ix]`` is True for an obstacle cell. Row ``iy = 0`` is the *bottom* of the map
  (smallest y), so cell ``(iy, ix)`` has its centre at
  ``origin + ((ix + 0.5) * resolution, (iy + 0.5) * resolution)``. Image files store the top row
  first, as ROS does; loading and saving flip rows.
- ``origin: [x, y, yaw]`` is the map-frame pose of cell (0, 0)'s outer corner; a non-zero yaw
  (3.14 and -1.57 are common in SLAM maps) rotates the grid about that point
  (``World.origin_yaw``). Poses, pairs, balls, doors and pictures are always in the map frame.
- Image values are read as ROS ``map_server`` reads them (the ROS 2 / Nav2 ``map_io`` rules, which
  ROS 1's ``image_loader`` shares except where noted), giving each pixel the ``OccupancyGrid``
  value 0 (free), 100 (occupied), 1..99 (a probability) or -1 (unknown). A pixel's *shade* is
  the mean of its R, G, B channels scaled to [0, 1] (a grey image: the grey level), and
  ``occ = shade`` if ``negate`` else ``1 - shade``. Then, by ``mode`` (default ``trinary``):

  - ``trinary``: in an image with an alpha channel the alpha is averaged into the shade (as both
    ROS versions do); ``occ > occupied_thresh`` is 100, ``occ < free_thresh`` is 0, else -1.
  - ``scale``: alpha is not averaged in; a pixel that is not fully opaque is -1 (Nav2; ROS 1
    calls only alpha 0 unknown, and only between the thresholds); else 100 / 0 as in trinary,
    and between the thresholds the linear 1..99 probability.
  - ``raw``: the value is the rounded mean of the channels (0..255) itself, ``negate`` and the
    thresholds ignored (Nav2; ROS 1 applies ``negate`` first); 0..100 are kept, anything above
    100 is -1 (unknown; in ROS 1 255 wraps to -1 as well).

  Boolean occupancy (our policy, the same for every mode): a cell is free only when the map
  server gives it 0; occupied (100), unknown (-1) and any probability 1..99 are obstacles, as
  AMCL reads a map (0 free, 100 occupied, anything else unknown): the robot must not plan or
  drive through space nobody has seen free. For an image without alpha, trinary and scale
  therefore give the same grid (free iff ``occ < free_thresh``; scale also frees a pixel exactly
  at ``free_thresh``, which Nav2 rounds to 0). Any other ``mode`` is refused, naming the file.
- Door gaps are *free* in the occupancy grid: the grid is the static map, and the door is a
  movable object on top of it (the same prior map the paper's baseline used).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from curlnav.files import FileRefused, read_yaml, shown


class WorldError(ValueError):
    """A world file or world description is malformed; the message names the file and field."""


@dataclass(frozen=True)
class Ball:
    """A movable ball. ``x, y`` centre (m), ``radius`` (m), ``mass`` (kg).

    ``region``: index into ``World.ball_regions``; when set, the ball is re-placed uniformly at
    random inside that region on every reset (away from walls, other balls, start and goal).
    """

    x: float
    y: float
    radius: float = 0.25
    mass: float = 0.5
    region: int | None = None


@dataclass(frozen=True)
class Door:
    """A hinged door panel on a vertical hinge.

    ``hinge_x, hinge_y``: hinge axis position (m). ``width``: panel length from the hinge (m).
    ``closed_angle``: direction of the closed panel from the hinge, measured from +x (rad).
    ``swing``: ``"left"`` opens counter-clockwise (seen from above), ``"right"`` clockwise.
    ``max_open``: how far it opens from closed (rad). ``mass`` (kg). ``hinge_friction``: the
    torque the hinge resists with (N m); 0 is a free hinge.
    """

    hinge_x: float
    hinge_y: float
    width: float = 1.1
    closed_angle: float = 0.0
    swing: str = "left"
    max_open: float = math.radians(110.0)
    mass: float = 2.0
    hinge_friction: float = 0.5
    thickness: float = 0.05


@dataclass(frozen=True)
class Box:
    """A movable box: centre ``x, y`` (m), full sizes ``size_x, size_y`` (m), ``yaw`` (rad),
    ``mass`` (kg)."""

    x: float
    y: float
    size_x: float = 0.5
    size_y: float = 0.5
    yaw: float = 0.0
    mass: float = 5.0


@dataclass(frozen=True)
class StartGoal:
    """A start pose ``(x, y, yaw)`` (m, m, rad) and a goal point ``(gx, gy)`` (m).

    ``step``: optional curriculum sub-step index (the paper's p1..p4 are steps 1..4).
    """

    name: str
    x: float
    y: float
    yaw: float
    gx: float
    gy: float
    step: int | None = None

    @property
    def distance(self) -> float:
        """Straight-line start-goal distance (m)."""
        return math.hypot(self.gx - self.x, self.gy - self.y)


@dataclass(frozen=True)
class Region:
    """An axis-aligned rectangle ``[x_min, x_max] x [y_min, y_max]`` (m)."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float


@dataclass(frozen=True)
class RandomPairs:
    """Draw a random start/goal pair on reset when none is assigned.

    Both points lie on free cells of the C-space grid (the static map inflated by
    ``clearance``, m) and are at least ``min_distance`` (m) apart.
    """

    min_distance: float = 4.0
    clearance: float = 0.6


@dataclass(frozen=True)
class World:
    """A navigation world. See the module docstring for the conventions."""

    name: str
    occupancy: np.ndarray  # bool, shape (rows, cols), row 0 = smallest y
    resolution: float  # m per cell
    origin: tuple[float, float] = (0.0, 0.0)  # map position of cell (0, 0)'s outer corner (m)
    origin_yaw: float = 0.0  # rad; the grid's rotation in the map frame (ROS map_server origin[2])
    wall_height: float = 1.0  # m
    balls: tuple[Ball, ...] = ()
    doors: tuple[Door, ...] = ()
    boxes: tuple[Box, ...] = ()
    pairs: tuple[StartGoal, ...] = ()
    ball_regions: tuple[Region, ...] = ()
    random_pairs: RandomPairs | None = None
    # evaluation pairs, never trained on: the evaluation protocol scores these instead of drawing its own
    # (``curlnav train --world MAP.yaml`` writes them, ``curlnav.worlds.real.own_map``); training draws ``pairs``
    held_out: tuple[StartGoal, ...] = ()
    source: str = "<memory>"

    def __post_init__(self) -> None:
        occ = np.asarray(self.occupancy)
        if occ.ndim != 2 or occ.shape[0] < 1 or occ.shape[1] < 1:
            raise WorldError(f"{self.source}: occupancy must be a non-empty 2-D grid, got shape {occ.shape}")
        object.__setattr__(self, "occupancy", occ.astype(bool))
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise WorldError(f"{self.source}: resolution must be a positive number of metres, got {self.resolution}")
        if not math.isfinite(self.origin_yaw):
            raise WorldError(f"{self.source}: origin yaw must be a finite angle in radians, got {self.origin_yaw}")
        if not (math.isfinite(self.wall_height) and self.wall_height > 0):
            raise WorldError(f"{self.source}: wall_height must be positive, got {self.wall_height}")
        for i, ball in enumerate(self.balls):
            if ball.radius <= 0 or ball.mass <= 0:
                raise WorldError(f"{self.source}: balls[{i}] needs a positive radius and mass")
            if ball.region is not None and not 0 <= ball.region < len(self.ball_regions):
                raise WorldError(f"{self.source}: balls[{i}].region {ball.region} names no entry of ball_regions")
        for i, door in enumerate(self.doors):
            if door.swing not in ("left", "right"):
                raise WorldError(f"{self.source}: doors[{i}].swing must be 'left' or 'right', got {door.swing!r}")
            if door.width <= 0 or door.mass <= 0:
                raise WorldError(f"{self.source}: doors[{i}] needs a positive width and mass")
        names = [pair.name for pair in (*self.pairs, *self.held_out)]
        if len(set(names)) != len(names):
            repeated = sorted({name for name in names if names.count(name) > 1})
            raise WorldError(f"{self.source}: pair names (pairs and held_out_pairs) must be unique, "
                             f"{shown(repeated)} repeated")
        for pair in (*self.pairs, *self.held_out):
            for label, (px, py) in (("start", (pair.x, pair.y)), ("goal", (pair.gx, pair.gy))):
                if not self.contains(px, py):
                    raise WorldError(f"{self.source}: pair {pair.name!r} {label} ({px:.2f}, {py:.2f}) lies outside the map")
                if self.is_occupied(px, py):
                    raise WorldError(f"{self.source}: pair {pair.name!r} {label} ({px:.2f}, {py:.2f}) lies inside an obstacle")

    # -- geometry -------------------------------------------------------------------------
    # Two frames: the *map* frame (poses, pairs, balls, doors, pictures, everything a user
    # sees; the frame of ROS map_server) and the *grid* frame (metres along the grid's columns
    # and rows from the outer corner of cell (0, 0)). With ``origin_yaw == 0`` the grid frame is
    # the map frame shifted by ``origin``.
    @property
    def size(self) -> tuple[float, float]:
        """Map extent ``(width, height)`` in metres along the grid's columns and rows."""
        rows, cols = self.occupancy.shape
        return cols * self.resolution, rows * self.resolution

    @property
    def rotated(self) -> bool:
        """True when the grid is rotated in the map frame (``origin_yaw != 0``)."""
        return self.origin_yaw != 0.0

    def grid_from_map(self, x, y):
        """Map-frame point(s) (m) to grid-frame point(s) (m from the corner of cell (0, 0)).
        Accepts floats or numpy arrays of the same shape."""
        dx, dy = x - self.origin[0], y - self.origin[1]
        if not self.origin_yaw:
            return dx, dy
        c, s = math.cos(self.origin_yaw), math.sin(self.origin_yaw)
        return c * dx + s * dy, -s * dx + c * dy

    def map_from_grid(self, u, v):
        """Grid-frame point(s) (m) to map-frame point(s) (m); inverse of ``grid_from_map``."""
        if not self.origin_yaw:
            return self.origin[0] + u, self.origin[1] + v
        c, s = math.cos(self.origin_yaw), math.sin(self.origin_yaw)
        return self.origin[0] + c * u - s * v, self.origin[1] + s * u + c * v

    def corners(self) -> list[tuple[float, float]]:
        """The map's four corners in the map frame (m), counter-clockwise from cell (0, 0)'s."""
        width, height = self.size
        return [self.map_from_grid(u, v) for u, v in ((0.0, 0.0), (width, 0.0), (width, height), (0.0, height))]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` of the map in the map frame (m); for a rotated grid,
        the axis-aligned box around it."""
        if not self.origin_yaw:
            width, height = self.size
            return self.origin[0], self.origin[1], self.origin[0] + width, self.origin[1] + height
        xs, ys = zip(*self.corners())
        return min(xs), min(ys), max(xs), max(ys)

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """The ``(iy, ix)`` cell containing map point ``(x, y)``; may lie outside the grid."""
        u, v = self.grid_from_map(x, y)
        return int(math.floor(v / self.resolution)), int(math.floor(u / self.resolution))

    def cells_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``cell_of`` for arrays of map points: the ``(iy, ix)`` int arrays; may lie outside the grid."""
        u, v = self.grid_from_map(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        return np.floor(v / self.resolution).astype(int), np.floor(u / self.resolution).astype(int)

    def cell_centre(self, iy: int, ix: int) -> tuple[float, float]:
        """Map coordinates (m) of the centre of cell ``(iy, ix)``."""
        return self.map_from_grid((ix + 0.5) * self.resolution, (iy + 0.5) * self.resolution)

    def contains(self, x: float, y: float) -> bool:
        iy, ix = self.cell_of(x, y)
        rows, cols = self.occupancy.shape
        return 0 <= iy < rows and 0 <= ix < cols

    def is_occupied(self, x: float, y: float) -> bool:
        """True on an obstacle cell or outside the map."""
        if not self.contains(x, y):
            return True
        iy, ix = self.cell_of(x, y)
        return bool(self.occupancy[iy, ix])

    def pair(self, key: int | str) -> StartGoal:
        """A start/goal pair by index (of ``pairs``) or by name (``pairs``, then ``held_out``);
        ``KeyError`` names the choices."""
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if 0 <= key < len(self.pairs):
                return self.pairs[int(key)]
        else:
            for pair in (*self.pairs, *self.held_out):
                if pair.name == key:
                    return pair
        raise KeyError(f"world {self.name!r} has no pair {key!r}; it has {[p.name for p in self.pairs] or 'none'}")

    def with_changes(self, **changes: Any) -> World:
        return dataclasses.replace(self, **changes)



# -- file format ---------------------------------------------------------------------------
MAP_MODES = ("trinary", "scale", "raw")
MAX_MAP_PIXELS = 25_000_000  # pixels of a map image (5000 x 5000); Pillow's own bomb limit is 179 M
MAX_MAP_BYTES = 256 << 20  # bytes of a map image file (a 16-bit 5000 x 5000 PGM is 50 MB)


def map_server_values(img, mode: str = "trinary", negate: bool = False, occupied_thresh: float = 0.65,
                      free_thresh: float = 0.196) -> np.ndarray:
    """The ``OccupancyGrid`` values (int8: 0 free, 100 occupied, 1..99, -1 unknown) that ROS
    ``map_server`` gives a PIL image, in image row order (top row first). See the module
    docstring for the rules of each ``mode``."""
    if mode not in MAP_MODES:
        raise ValueError(f"mode must be one of {', '.join(MAP_MODES)}, got {mode!r}")
    if img.mode in ("I", "I;16", "I;16B", "I;16L", "I;16N", "F"):
        full = 65535.0 if img.mode != "F" else 1.0
        rgb = np.asarray(img, dtype=np.float64)[..., None] / full
        alpha = None
    else:
        has_alpha = img.mode in ("RGBA", "LA", "PA", "La", "RGBa") or (img.mode == "P" and "transparency" in img.info)
        arr = np.asarray(img.convert("RGBA" if has_alpha else "RGB"), dtype=np.float64) / 255.0
        rgb, alpha = arr[..., :3], (arr[..., 3] if has_alpha else None)
    channels = rgb.shape[-1]
    if mode == "trinary" and alpha is not None:
        shade = (rgb.sum(axis=-1) + alpha) / (channels + 1)
    else:
        shade = rgb.mean(axis=-1)
    if mode == "raw":
        raw = np.rint(shade * 255.0)
        return np.where(raw <= 100, raw, -1).astype(np.int8)
    occ = shade if negate else 1.0 - shade
    out = np.full(occ.shape, -1, dtype=np.int8)
    if mode == "scale":
        span = max(occupied_thresh - free_thresh, 1e-12)
        out[:] = np.rint((occ - free_thresh) / span * 100.0).clip(-1, 100).astype(np.int8)
        out[occ > occupied_thresh] = 100
        out[occ < free_thresh] = 0
        if alpha is not None:
            out[alpha < 1.0] = -1
    else:
        out[occ > occupied_thresh] = 100
        out[occ < free_thresh] = 0
    return out




def _fail(path: Path | str, message: str) -> WorldError:
    return WorldError(f"{path}: {message}")


def _build_items(path: Path, key: str, raw: Any, cls: type) -> tuple:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise _fail(path, f"'{key}' must be a list, got {type(raw).__name__}")
    fields = {f.name for f in dataclasses.fields(cls)}
    items = []
    for i, entry in enumerate(raw):
        if not isinstance(entry, dict):
            raise _fail(path, f"{key}[{i}] must be a mapping, got {shown(entry)}")
        unknown = set(entry) - fields
        if unknown:
            raise _fail(path, f"{key}[{i}] has unknown keys {shown(sorted(map(str, unknown)))}; allowed: {sorted(fields)}")
        try:
            values = {k: v for k, v in entry.items()}
            for name, value in values.items():
                if name in ("name", "swing"):
                    values[name] = str(value)
                elif name in ("step", "region"):
                    values[name] = None if value is None else int(value)
                else:
                    values[name] = float(value)
                    if not math.isfinite(values[name]):
                        raise ValueError(f"{name} is not finite")
            if cls is StartGoal and "name" not in values:
                values["name"] = f"{'h' if key == 'held_out_pairs' else 'p'}{i + 1}"
            items.append(cls(**values))
        except (TypeError, ValueError) as exc:
            raise _fail(path, f"{key}[{i}] is invalid: {shown(str(exc), 160)[1:-1]}") from None
    return tuple(items)


def load_world(path: str | os.PathLike) -> World:
    """Load a world from a ROS ``map_server`` YAML (plus curlnav keys). Errors name the file."""
    path = Path(path)
    meta = _read_yaml_mapping(path)
    grid, resolution, origin = _read_map_server(path, meta)
    return World(name=str(meta.get("name", path.stem)), occupancy=grid, resolution=resolution,
                 origin=(origin[0], origin[1]), origin_yaw=origin[2] if len(origin) > 2 else 0.0,
                 source=str(path), **_read_curlnav_keys(path, meta))


def _read_yaml_mapping(path: Path) -> dict:
    try:
        meta = read_yaml(path, what="world file")
    except OSError as exc:
        raise _fail(path, f"cannot read world file: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise WorldError(str(exc)) from None
    if not isinstance(meta, dict):
        raise _fail(path, "a world file must be a YAML mapping")
    return meta


def _read_map_server(path: Path, meta: dict) -> tuple[np.ndarray, float, list[float]]:
    """The map_server part: occupancy grid (row 0 = bottom), resolution (m), origin [x, y(, yaw)]."""
    from PIL import Image, UnidentifiedImageError

    for key in ("image", "resolution", "origin"):
        if key not in meta:
            raise _fail(path, f"missing required key '{key}' (ROS map_server format)")
    def field(key: str, kind: type, default: Any = None):
        try:
            return kind(meta.get(key, default))
        except (TypeError, ValueError, OverflowError):
            raise _fail(path, f"bad map_server field {key}: {shown(meta.get(key))}") from None

    resolution = field("resolution", float)
    origin = field("origin", lambda raw: [float(v) for v in raw])
    negate = field("negate", int, 0)
    occupied_thresh = field("occupied_thresh", float, 0.65)
    free_thresh = field("free_thresh", float, 0.196)
    if len(origin) not in (2, 3) or not all(math.isfinite(v) for v in origin):
        raise _fail(path, f"origin must be [x, y, yaw] (m, m, rad), got {shown(meta['origin'])}")
    mode = meta.get("mode", "trinary")
    if not isinstance(mode, str) or mode.strip().lower() not in MAP_MODES:
        raise _fail(path, f"mode must be one of {', '.join(MAP_MODES)} (ROS map_server), got {shown(mode)}")
    image_path = (path.parent / str(meta["image"])).resolve()
    try:
        if image_path.is_file() and image_path.stat().st_size > MAX_MAP_BYTES:
            raise _fail(path, f"map image {image_path} is above {MAX_MAP_BYTES >> 20} MiB; refused")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(image_path) as img:  # reads the header only
                width, height = img.size
                if width * height > MAX_MAP_PIXELS:
                    raise _fail(path, f"map image {image_path} has {width} x {height} = {width * height} cells, above "
                                      f"the cap of {MAX_MAP_PIXELS} (5000 x 5000: 250 m square at 5 cm); crop or "
                                      f"coarsen the map")
                short = pnm_shortfall(image_path)
                if short:
                    raise _fail(path, f"map image {image_path} is truncated: {short}")
                values = map_server_values(img, mode.strip().lower(), bool(negate), occupied_thresh, free_thresh)
    except FileNotFoundError:
        raise _fail(path, f"map image {image_path} does not exist") from None
    except Image.DecompressionBombError:
        raise _fail(path, f"map image {image_path} has {_header_size(image_path)} pixels, above "
                          f"{MAX_MAP_PIXELS}") from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        if isinstance(exc, WorldError):
            raise
        raise _fail(path, f"map image {image_path} is unreadable: {shown(str(exc), 160)[1:-1]}") from None
    return np.flipud(values != 0), resolution, origin


_PNM_CHANNELS = {b"P4": 0, b"P5": 1, b"P6": 3}  # binary PBM (bits), PGM (grey), PPM (RGB)


def pnm_shortfall(image_path: Path) -> str:
    """For a binary PGM, PPM or PBM whose file holds fewer pixel bytes than its header's width,
    height and maxval call for (a map cut short in a copy or a download): what the header says
    and what the file holds, in words; else "" (another format, a whole file, or a header too
    malformed to say: the decoder reports that)."""
    try:
        with open(image_path, "rb") as f:
            head = f.read(4096)
            size = os.fstat(f.fileno()).st_size
    except OSError:
        return ""
    channels = _PNM_CHANNELS.get(head[:2])
    if channels is None:
        return ""
    numbers, at, wanted = [], 2, 2 if channels == 0 else 3
    while len(numbers) < wanted:
        while at < len(head) and (head[at:at + 1].isspace() or head[at:at + 1] == b"#"):
            if head[at:at + 1] == b"#":  # a comment runs to the end of its line
                end = head.find(b"\n", at)
                at = len(head) if end < 0 else end
            at += 1
        match = re.match(rb"\d+", head[at:])
        if match is None:
            return ""
        numbers.append(int(match[0]))
        at += len(match[0])
    at += 1  # the one whitespace character before the pixels
    width, height = numbers[0], numbers[1]
    if channels == 0:
        expected = (width + 7) // 8 * height
    else:
        expected = width * height * channels * (2 if numbers[2] > 255 else 1)
    held = max(size - at, 0)
    if held >= expected:
        return ""
    return (f"its header says {width} x {height} pixels ({expected} bytes of pixels), the file holds {held} "
            f"after the header")


def _header_size(image_path: Path) -> str:
    """"W x H" of a PGM/PPM whose header Pillow refuses (a decompression bomb); else "too many"."""
    try:
        with open(image_path, "rb") as f:
            head = f.read(64)
    except OSError:
        return "too many"
    numbers = re.findall(rb"\d+", head)
    return f"{int(numbers[1])} x {int(numbers[2])}" if head[:1] == b"P" and len(numbers) >= 3 else "too many"


def _read_curlnav_keys(path: Path, meta: dict) -> dict:
    """curlnav's own keys (movable objects, pairs, ball regions, random pairs, wall height) as
    ``World`` fields; all optional."""
    random_pairs = None
    if meta.get("random_pairs") is not None:
        raw = meta["random_pairs"]
        if not isinstance(raw, dict):
            raise _fail(path, "'random_pairs' must be a mapping")
        try:
            random_pairs = RandomPairs(**{k: float(v) for k, v in raw.items()})
        except (TypeError, ValueError) as exc:
            raise _fail(path, f"random_pairs is invalid: {shown(str(exc), 160)[1:-1]}") from None
    regions = []
    for i, raw in enumerate(meta.get("ball_regions") or []):
        try:
            x_min, y_min, x_max, y_max = (float(v) for v in raw)
        except (TypeError, ValueError):
            raise _fail(path, f"ball_regions[{i}] must be [x_min, y_min, x_max, y_max], got {shown(raw)}") from None
        if not (x_min < x_max and y_min < y_max):
            raise _fail(path, f"ball_regions[{i}] is empty: {shown(raw)}")
        regions.append(Region(x_min, y_min, x_max, y_max))
    try:
        wall_height = float(meta.get("wall_height", 1.0))
    except (TypeError, ValueError):
        raise _fail(path, "wall_height must be a number") from None
    return {"wall_height": wall_height, "balls": _build_items(path, "balls", meta.get("balls"), Ball),
            "doors": _build_items(path, "doors", meta.get("doors"), Door),
            "boxes": _build_items(path, "boxes", meta.get("boxes"), Box),
            "pairs": _build_items(path, "pairs", meta.get("pairs"), StartGoal),
            "held_out": _build_items(path, "held_out_pairs", meta.get("held_out_pairs"), StartGoal),
            "ball_regions": tuple(regions), "random_pairs": random_pairs}


def save_world(world: World, path: str | os.PathLike, image_format: str = "pgm", map_only: bool = False) -> Path:
    """Write ``world`` as ``path`` (YAML) plus ``<stem>.pgm`` or ``.png`` beside it, whole or not at
    all: both are written to temporary files beside them first, then renamed into place (the YAML
    last). A failure (``OSError``) leaves neither, nor a temporary file, nor the folders made for them.
    ``map_only``: map_server's fields alone, the walls as a SLAM map shows them (no pairs, balls,
    doors or boxes: what a robot team's map holds)."""
    from PIL import Image

    if image_format not in ("pgm", "png"):
        raise ValueError(f"image_format must be 'pgm' or 'png', got {image_format!r}")
    path = Path(path)
    made = [p for p in (path.parent, *path.parent.parents) if not p.exists()]  # deepest first
    image_name = f"{path.stem}.{image_format}"
    image_path = path.parent / image_name
    temporary: list[Path] = []
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        pixels = np.where(np.flipud(world.occupancy), 0, 254).astype(np.uint8)
        temporary.append(_temporary_beside(image_path))
        Image.fromarray(pixels, mode="L").save(temporary[-1], format=image_format.upper().replace("PGM", "PPM"))
        temporary.append(_temporary_beside(path))
        fields = _world_file_fields(world, image_name)
        if map_only:
            fields = {k: fields[k] for k in MAP_SERVER_FIELDS}
        temporary[-1].write_text(yaml.safe_dump(fields, sort_keys=False))
        os.replace(temporary[0], image_path)
        os.replace(temporary[1], path)
    except BaseException:
        for leftover in temporary:
            leftover.unlink(missing_ok=True)
        for folder in made:
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    return path


#: the fields of a ``map_server`` map's YAML, in the order ROS writes them
MAP_SERVER_FIELDS = ("image", "resolution", "origin", "mode", "negate", "occupied_thresh", "free_thresh")


def _temporary_beside(path: Path) -> Path:
    """A new empty file in ``path``'s folder, hidden, named after it, readable by all as a plain
    file would be (``mkstemp`` makes it the owner's alone)."""
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    os.close(handle)
    os.chmod(name, 0o644)
    return Path(name)


def _world_file_fields(world: World, image_name: str) -> dict[str, Any]:
    """The world file's mapping: map_server's fields, then curlnav's."""

    def as_dicts(items: tuple) -> list[dict]:
        out = []
        for obj in items:
            d = dataclasses.asdict(obj)
            out.append({k: (v.item() if isinstance(v, np.generic) else v) for k, v in d.items() if v is not None})
        return out

    meta: dict[str, Any] = {
        "image": image_name,
        "resolution": float(world.resolution),
        "origin": [float(world.origin[0]), float(world.origin[1]), float(world.origin_yaw)],
        "mode": "trinary",
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        "name": world.name,
        "wall_height": float(world.wall_height),
        "balls": as_dicts(world.balls),
        "doors": as_dicts(world.doors),
        "boxes": as_dicts(world.boxes),
        "pairs": as_dicts(world.pairs),
        **({"held_out_pairs": as_dicts(world.held_out)} if world.held_out else {}),
        "ball_regions": [[float(r.x_min), float(r.y_min), float(r.x_max), float(r.y_max)] for r in world.ball_regions],
    }
    if world.random_pairs is not None:
        meta["random_pairs"] = {k: float(v) for k, v in dataclasses.asdict(world.random_pairs).items()}
    return meta
