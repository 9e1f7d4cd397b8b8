"""A user's own building map as a training task (``curlnav train --world MAP.yaml``): start/goal
pairs drawn apart into training and held-out ones, doors where the user marks them, balls on the
training pairs' shortest paths.

**The pairs** (``draw_task``): ``PairSampler``'s draws on the C-space grid (the map inflated by
``RandomPairs``' clearance, start and goal in one connected region, at least its ``min_distance``
apart, which shrinks to a small map's extent; the robot's footprint free at the start), at most
``MAX_DISTANCE`` apart in a straight line and with a shortest path of at most ``MAX_PATH_M`` on the
grid the balls are placed with (``curlnav.worlds.difficulty.rank.world_paths``: 0.15 m cells, the
map inflated by 0.3 m), so that a trial fits the evaluation's 60 s at 1 m/s, as in the real suite.
No start lies in a door's swing (``DOOR_START_KEEP_OUT`` beyond its width), no goal within
``DOOR_GOAL_KEEP_OUT`` of it. With balls, the first training pairs are drawn (one per ball), the
balls placed on their shortest paths by ``scatter_balls`` (clear of walls, doors, each other and
those pairs' ends), and every later pair keeps clear of the balls as scatter_balls keeps its own
(``START_KEEP_OUT``, ``GOAL_KEEP_OUT``). Each ball is re-placed at every reset within
``BALL_SPREAD_M`` of where it was drawn (its ``ball_regions`` square: ``World.balls``' ``region``,
clear of walls, the other balls, the start and the goal), so a policy learns to push balls, not
where they lie, and each evaluation episode of a pair meets another placement. The held-out pairs
come from one stream of the seed, the training pairs from another; no pair is drawn twice, nor the
reverse of one drawn before, so the two lists are disjoint. Same map, doors, seed, counts and balls:
the same pairs; without balls the first k held-out pairs do not depend on how many training pairs
are asked for.

**pairs.yaml** (``write_pairs`` / ``read_pairs``): the run's two lists in the map frame (m, rad),
``train`` and ``held_out``, each pair ``{name, start: [x, y, yaw], goal: [x, y]}``, and what they
were drawn from (``map``, ``seed``, ``doors``, ``balls``). A resumed run reads it back.

**The doors file** (``read_doors``): ``doors: [{hinge: [x, y], width: W, angle: A}, ...]`` in the
map frame: the hinge axis (m), the panel's length (m) and the closed panel's direction from the
hinge, from +x (rad); optional ``swing`` (``left``: opens counter-clockwise, the default, or
``right``), ``max_open`` (rad), ``mass`` (kg), ``hinge_friction`` (N m): the fields of
``curlnav.worlds.core.world.Door``. The doorway must be free on the map (the door is a movable
object on top of the static map): a panel lying mostly on walls or unknown space is refused.

Every refusal is a ``WorldError`` of one line naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from scipy.sparse import csgraph

from curlnav.files import FileRefused, read_yaml, shown
from curlnav.worlds.core.pairs import HUSKY_FOOTPRINT, PairSampler, pair_key
from curlnav.worlds.core.world import Door, Region, StartGoal, World, WorldError
from curlnav.worlds.difficulty.metrics import GridGraph, inflate
from curlnav.worlds.difficulty.rank import CSPACE_RADIUS_M, METRIC_RESOLUTION, resample
from curlnav.worlds.procedural.scatter import GOAL_KEEP_OUT, START_KEEP_OUT, scatter_balls
from curlnav.worlds.real.real_maps import MAX_DISTANCE, MAX_PATH_M

DEFAULT_HELD_OUT = 20  # held-out pairs (the evaluation scores each once)
DEFAULT_TRAIN = 100  # training pairs
MAX_PAIRS = 1000  # pairs in either list
MAX_BALLS = 200
MAX_DOORS = 200
DRAWS_PER_PAIR = 20  # draws per pair asked for before giving up (a draw may be too long or in a door's swing)
BALL_SPREAD_M = 1.0  # m: each ball is re-placed at every reset within this of where it was drawn (both axes)
PLACEMENTS_PER_PAIR = 2  # the evaluation beside training scores each held-out pair this often (ball placements)
DOOR_START_KEEP_OUT = 0.6  # m beyond a door's width from its hinge: no start (the Husky's half-diagonal)
DOOR_GOAL_KEEP_OUT = 0.3  # m beyond a door's width from its hinge: no goal
MAX_DOOR_WIDTH = 5.0  # m
DECIMALS = 4  # of the numbers in pairs.yaml (0.1 mm, 0.1 mrad)
_HELD_OUT_STREAM, _TRAIN_STREAM = 1, 2  # each list's random stream of the seed
_DOOR_KEYS = {"hinge", "width", "angle", "swing", "max_open", "mass", "hinge_friction"}


@dataclass(frozen=True)
class PairSplit:
    """A map's training pairs (named ``t1..``) and held-out pairs (``h1..``), disjoint."""

    train: tuple[StartGoal, ...]
    held_out: tuple[StartGoal, ...]


def _keys(pair: StartGoal) -> tuple[tuple, tuple]:
    """The pair's ``pair_key`` and its reverse's (start and goal swapped)."""
    return pair_key(pair.x, pair.y, pair.gx, pair.gy), pair_key(pair.gx, pair.gy, pair.x, pair.y)


class _PathCheck:
    """Shortest paths (m) on the C-space grid the balls are placed with (see the module docstring)."""

    def __init__(self, world: World) -> None:
        self.world = world
        grid = resample(world.occupancy, world.resolution, METRIC_RESOLUTION)
        self.cspace = inflate(grid, int(round(CSPACE_RADIUS_M / METRIC_RESOLUTION)))
        self.graph = GridGraph(self.cspace)

    def _cell(self, x: float, y: float) -> int | None:
        u, v = self.world.grid_from_map(x, y)
        r, c = int(math.floor(v / METRIC_RESOLUTION)), int(math.floor(u / METRIC_RESOLUTION))
        rows, cols = self.cspace.shape
        if not (0 <= r < rows and 0 <= c < cols) or self.cspace[r, c]:
            return None
        return r * cols + c

    def length(self, pair: StartGoal, limit: float) -> float:
        """The shortest path from start to goal (m); ``inf`` when none within ``limit`` (m)."""
        start, goal = self._cell(pair.x, pair.y), self._cell(pair.gx, pair.gy)
        if start is None or goal is None:
            return math.inf
        # the graph holds both directions of every edge: directed saves scipy symmetrising it at each call
        dist = csgraph.dijkstra(self.graph.graph, directed=True, indices=start, limit=limit / METRIC_RESOLUTION)
        return float(dist[goal]) * METRIC_RESOLUTION


def _rounded(pair: StartGoal, name: str) -> StartGoal:
    return StartGoal(name, *(round(float(v), DECIMALS) for v in (pair.x, pair.y, pair.yaw, pair.gx, pair.gy)))


def _clear_of_doors(pair: StartGoal, doors: tuple[Door, ...]) -> bool:
    return not any(math.hypot(pair.x - d.hinge_x, pair.y - d.hinge_y) < d.width + DOOR_START_KEEP_OUT
                   or math.hypot(pair.gx - d.hinge_x, pair.gy - d.hinge_y) < d.width + DOOR_GOAL_KEEP_OUT
                   for d in doors)


def draw_task(world: World, train: int = DEFAULT_TRAIN, held_out: int = DEFAULT_HELD_OUT, balls: int = 0,
              seed: int = 0, footprint: tuple[float, float] = HUSKY_FOOTPRINT) -> World:
    """``world`` (with its doors) made a task: ``held_out`` pairs (``World.held_out``), ``train`` pairs
    (``World.pairs``) and ``balls`` balls on the training paths (see the module docstring).
    ``WorldError`` (one line) when the map has no free space for a pair, too few pairs far enough
    apart, or no room for the balls."""
    for label, count, least, most in (("training pairs", train, 1, MAX_PAIRS), ("held-out pairs", held_out, 1, MAX_PAIRS),
                                      ("balls", balls, 0, MAX_BALLS)):
        if not least <= count <= most:
            raise WorldError(f"the number of {label} must be {least}..{most}, got {count}")
    sampler = PairSampler(world, footprint=footprint)  # no connected free space: WorldError here
    paths = _PathCheck(world)
    taken: set = set()
    placed: tuple = ()  # balls the pairs keep clear of

    def usable(pair: StartGoal) -> bool:
        for ball in world.balls + placed:
            if (math.hypot(pair.x - ball.x, pair.y - ball.y) < START_KEEP_OUT + ball.radius
                    or math.hypot(pair.gx - ball.x, pair.gy - ball.y) < GOAL_KEEP_OUT + ball.radius):
                return False
        return _clear_of_doors(pair, world.doors) and paths.length(pair, MAX_PATH_M) <= MAX_PATH_M

    def draw(out: list[StartGoal], count: int, total: int, prefix: str, rng: np.random.Generator, what: str) -> None:
        draws = 0
        while len(out) < count and draws < DRAWS_PER_PAIR * total:
            draws += 1
            try:
                drawn = sampler.draw(rng, excluded=taken, max_distance=MAX_DISTANCE)
            except WorldError:  # no new pair in the sampler's own tries: the map has no more
                break
            pair = _rounded(drawn, f"{prefix}{len(out) + 1}")
            taken.update(_keys(pair))
            taken.update(_keys(drawn))
            if usable(pair):
                out.append(pair)
        if len(out) < count:
            raise WorldError(
                f"{world.source}: found only {len(out)} of {total} {what} start/goal pairs in {draws} draws "
                f"({sampler.spec.min_distance:g}-{MAX_DISTANCE:g} m apart, a path of at most {MAX_PATH_M:g} m, none "
                f"drawn twice{', clear of the balls' if placed else ''}): too few free cells far enough apart once the "
                f"map is inflated by {sampler.spec.clearance:g} m; ask for fewer (--pairs-held-out, --pairs-train)")

    trained: list[StartGoal] = []
    rng = np.random.default_rng([seed, _TRAIN_STREAM])
    if balls:  # the first training pairs, one path per ball (scatter_balls places them in turn over the paths)
        draw(trained, min(balls, train), train, "t", rng, "training")
        placed = scatter_balls(world.with_changes(pairs=tuple(trained)), balls, seed=seed).balls[len(world.balls):]
    held: list[StartGoal] = []
    draw(held, held_out, held_out, "h", np.random.default_rng([seed, _HELD_OUT_STREAM]), "held-out")
    draw(trained, train, train, "t", rng, "training")  # the rest, clear of the balls
    regions = list(world.ball_regions)
    spread = []
    x0, y0, x1, y1 = world.bounds
    for ball in placed:  # each re-placed at every reset round where it was drawn
        regions.append(Region(max(x0, ball.x - BALL_SPREAD_M), max(y0, ball.y - BALL_SPREAD_M),
                              min(x1, ball.x + BALL_SPREAD_M), min(y1, ball.y + BALL_SPREAD_M)))
        spread.append(dataclasses.replace(ball, region=len(regions) - 1))
    return world.with_changes(pairs=tuple(trained), held_out=tuple(held), balls=world.balls + tuple(spread),
                              ball_regions=tuple(regions), random_pairs=None)


def split_of(task: World) -> PairSplit:
    """A task's training and held-out pairs."""
    return PairSplit(task.pairs, task.held_out)


# -- the doors file -----------------------------------------------------------------------------
def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where} must be a finite number, got {shown(value)}")
    return float(value)


def read_doors(path: str | os.PathLike, world: World) -> tuple[Door, ...]:
    """The doors of a doors file (see the module docstring) on ``world``; ``WorldError`` (one line
    naming the file and the entry) when it is unreadable, malformed, or a door lies off the map or
    in a wall."""
    path = Path(path)
    raw = _read_yaml_file(path, "doors file")
    if isinstance(raw, dict) and set(raw) == {"doors"}:
        raw = raw["doors"]
    if not isinstance(raw, list) or not raw:
        raise WorldError(f"{path}: a doors file is `doors: [{{hinge: [x, y], width: W, angle: A}}, ...]` (m, rad), "
                         f"at least one door")
    if len(raw) > MAX_DOORS:
        raise WorldError(f"{path}: {len(raw)} doors, above {MAX_DOORS}")
    doors = []
    for i, entry in enumerate(raw):
        where = f"{path}: doors[{i}]"
        if not isinstance(entry, dict):
            raise WorldError(f"{where} must be a mapping {{hinge: [x, y], width: W, angle: A}}, got {shown(entry)}")
        unknown = sorted(map(str, set(entry) - _DOOR_KEYS))
        missing = sorted({"hinge", "width", "angle"} - set(entry))
        if unknown or missing:
            raise WorldError(f"{where}: " + (f"unknown keys {shown(unknown)}" if unknown else f"missing {', '.join(missing)}")
                             + "; a door has hinge, width, angle and optionally swing, max_open, mass, hinge_friction")
        try:
            hinge = entry["hinge"]
            if not isinstance(hinge, list) or len(hinge) != 2:
                raise ValueError(f"hinge must be [x, y] (m), got {shown(hinge)}")
            x, y = (_number(v, "hinge") for v in hinge)
            width = _number(entry["width"], "width")
            if not 0 < width <= MAX_DOOR_WIDTH:
                raise ValueError(f"width must be in (0, {MAX_DOOR_WIDTH:g}] m, got {width:g}")
            extra = {key: _number(entry[key], key) for key in ("max_open", "mass", "hinge_friction") if key in entry}
            if not (0 < extra.get("max_open", 1.0) <= math.pi and extra.get("mass", 1.0) > 0
                    and extra.get("hinge_friction", 0.0) >= 0):
                raise ValueError(f"max_open must be in (0, pi] rad, mass positive, hinge_friction not negative, got "
                                 f"{shown(extra)}")
            swing = entry.get("swing", "left")
            if swing not in ("left", "right"):
                raise ValueError(f"swing must be left or right, got {shown(swing)}")
            door = Door(hinge_x=x, hinge_y=y, width=width, closed_angle=_number(entry["angle"], "angle"), swing=swing,
                        **extra)
        except ValueError as exc:
            raise WorldError(f"{where}: {' '.join(str(exc).split())}") from None
        if not world.contains(x, y):
            raise WorldError(f"{where}: the hinge ({x:g}, {y:g}) lies outside the map {shown(world.bounds)}")
        along = np.linspace(0.1 * width, 0.9 * width, 9)
        c, s = math.cos(door.closed_angle), math.sin(door.closed_angle)
        blocked = sum(world.is_occupied(x + t * c, y + t * s) for t in along)
        if blocked > len(along) // 2:
            raise WorldError(f"{where}: the closed panel from ({x:g}, {y:g}) at angle {door.closed_angle:g} rad lies on "
                             f"walls or unknown space ({blocked} of {len(along)} points): a door spans a doorway that is "
                             f"free on the map, its hinge at one side, its angle toward the other")
        doors.append(door)
    return tuple(doors)


# -- pairs.yaml ----------------------------------------------------------------------------------
def _number_text(value: float) -> str:
    return repr(round(float(value), DECIMALS))


def pairs_text(split: PairSplit, about: dict) -> str:
    """pairs.yaml's text: a comment, ``about`` (``map``, ``seed``, ``doors``, ``balls``), then the two
    lists, a pair a line."""
    lines = ["# Start/goal pairs of this run in the map frame (m, rad): `train` is what training draws from,",
             "# `held_out` what the evaluation scores, never trained on. A resumed run reads them back.",
             *(f"{key}: {_scalar(value)}" for key, value in about.items())]
    for key, pairs in (("train", split.train), ("held_out", split.held_out)):
        lines.append(f"{key}:")
        lines += [f"- {{name: {p.name}, start: [{_number_text(p.x)}, {_number_text(p.y)}, {_number_text(p.yaw)}], "
                  f"goal: [{_number_text(p.gx)}, {_number_text(p.gy)}]}}" for p in pairs]
    return "\n".join(lines) + "\n"


def _scalar(value) -> str:
    return "null" if value is None else json.dumps(value) if isinstance(value, str) else str(value)


def write_pairs(path: str | os.PathLike, split: PairSplit, about: dict) -> Path:
    """Write pairs.yaml whole or not at all (a temporary file beside it, then renamed)."""
    path = Path(path)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(handle, "w") as f:
            f.write(pairs_text(split, about))
        os.chmod(name, 0o644)
        os.replace(name, path)
    except BaseException:
        Path(name).unlink(missing_ok=True)
        raise
    return path


def doors_text(doors: tuple[Door, ...] | list[Door]) -> str:
    """A doors file (``read_doors``' format) holding ``doors``, every field written."""
    entries = [{"hinge": [round(float(d.hinge_x), DECIMALS), round(float(d.hinge_y), DECIMALS)],
                "width": round(float(d.width), DECIMALS), "angle": round(float(d.closed_angle), DECIMALS),
                "swing": d.swing, "max_open": round(float(d.max_open), DECIMALS), "mass": float(d.mass),
                "hinge_friction": float(d.hinge_friction)} for d in doors]
    return ("# doors on the map (curlnav train --doors): hinge [x, y] m, width m, angle of the closed panel rad\n"
            + yaml.safe_dump({"doors": entries}, sort_keys=False, default_flow_style=None))


def read_about(path: str | os.PathLike) -> dict:
    """pairs.yaml's ``map``, ``seed``, ``doors`` and ``balls`` (those it has); ``WorldError`` when unreadable."""
    data = _read_pairs_mapping(Path(path))
    return {key: data[key] for key in ("map", "seed", "doors", "balls") if key in data}


def _read_yaml_file(path: Path, what: str):
    """The YAML of ``path`` (a ``what``: "doors file", "pairs file"), every failure a ``WorldError`` in one line."""
    try:
        return read_yaml(path, what=what)
    except OSError as exc:
        raise WorldError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    except FileRefused as exc:
        raise WorldError(str(exc)) from None


def _read_pairs_mapping(path: Path) -> dict:
    data = _read_yaml_file(path, "pairs file")
    if not isinstance(data, dict):
        raise WorldError(f"{path}: a pairs file is a mapping with the lists train and held_out")
    return data


def _pair(entry, where: str) -> StartGoal:
    if not isinstance(entry, dict) or set(entry) != {"name", "start", "goal"}:
        raise ValueError(f"{where} must be {{name, start: [x, y, yaw], goal: [x, y]}}, got {shown(entry)}")
    start, goal = entry["start"], entry["goal"]
    if not (isinstance(start, list) and len(start) == 3 and isinstance(goal, list) and len(goal) == 2):
        raise ValueError(f"{where}: start is [x, y, yaw] (m, m, rad) and goal [x, y] (m), got {shown(start)} and "
                         f"{shown(goal)}")
    x, y, yaw = (_number(v, f"{where}'s start") for v in start)
    gx, gy = (_number(v, f"{where}'s goal") for v in goal)
    return StartGoal(str(entry["name"]), x, y, yaw, gx, gy)


def read_pairs(path: str | os.PathLike, world: World) -> PairSplit:
    """The run's pairs as pairs.yaml holds them, checked on ``world`` (inside the map, on free
    cells, names unique, the lists disjoint); ``WorldError`` (one line naming the file) otherwise."""
    path = Path(path)
    data = _read_pairs_mapping(path)
    lists = {}
    for key in ("train", "held_out"):
        raw = data.get(key)
        if not isinstance(raw, list) or not raw or len(raw) > MAX_PAIRS:
            raise WorldError(f"{path}: {key} must be a list of 1..{MAX_PAIRS} pairs, got {shown(raw)}")
        try:
            lists[key] = tuple(_pair(entry, f"{key}[{i}]") for i, entry in enumerate(raw))
        except ValueError as exc:
            raise WorldError(f"{path}: {' '.join(str(exc).split())}") from None
    split = PairSplit(lists["train"], lists["held_out"])
    seen = {key: p.name for p in split.train for key in _keys(p)}
    for p in split.held_out:
        if pair_key(p.x, p.y, p.gx, p.gy) in seen:
            raise WorldError(f"{path}: held-out pair {p.name} is training pair {seen[pair_key(p.x, p.y, p.gx, p.gy)]} "
                             f"(or its reverse): the lists must be disjoint")
    try:
        world.with_changes(pairs=split.train, held_out=split.held_out)
    except WorldError as exc:
        raise WorldError(f"{path}: {' '.join(str(exc).split())}") from None
    return split
