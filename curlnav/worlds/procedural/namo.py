"""Unseen NAMO worlds for evaluation: auditorium-, office- and indoor-like floors with hinged
doors in their passages and balls on their paths. No curriculum trains on them.

Families (``curlnav.worlds.families.FAMILIES``), each 22-24 m x 14-18 m at 0.15 m cells:

- ``namo-office``: a corridor with four rooms on each side; every room opens onto the corridor
  through a door; desks against the room walls.
- ``namo-indoor``: 3 x 3 rooms; neighbouring rooms are joined by doors (each room has at least
  one from its left or lower neighbour); tables and columns inside.
- ``namo-auditorium``: a lobby joined by three doors to a hall of seat rows with aisles in front
  of a stage.

A door turns one way only (a hinge with limits), so the doors of a floor all open toward +x or
+y, and a pair is kept only when the shortest path on the static grid (C-space: the map
inflated by 0.3 m, doors open, as every generated world) crosses at least one door, and every
door on it in the direction the door opens (``door_crossings``). Each world has ``pairs`` (12)
such pairs at least 6 m apart, starts facing along their path; then ``balls`` (8) fixed balls on
the pairs' paths (``curlnav.worlds.procedural.scatter``: clear of walls, starts, goals and door swings).
Same family, parameters and seed: the same world, bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from curlnav.worlds.core.pairs import HUSKY_FOOTPRINT, footprint_free
from curlnav.worlds.core.world import Door, Region, StartGoal, World
from curlnav.worlds.difficulty.metrics import GridGraph, inflate
from curlnav.worlds.difficulty.rank import CSPACE_RADIUS_M
from curlnav.worlds.procedural.scatter import scatter_balls

RESOLUTION = 0.15  # m per cell
WALL = 0.15  # m, nominal wall thickness (one or two cells once on the grid)
DOOR_GAP = 1.2  # m; the panel is 4 cm shorter
MIN_PAIR_DISTANCE = 6.0  # m, start to goal in a straight line
START_CLEAR_OF_DOOR = 0.9  # m beyond a door's swing for a start (the Husky's half-diagonal is 0.6 m)
GOAL_CLEAR_OF_DOOR = 0.4  # m beyond a door's swing for a goal


def door_segment(door: Door) -> tuple[np.ndarray, np.ndarray]:
    """The closed panel's line: hinge and tip, map-frame metres."""
    hinge = np.array([door.hinge_x, door.hinge_y])
    return hinge, hinge + door.width * np.array([math.cos(door.closed_angle), math.sin(door.closed_angle)])


def opening_direction(door: Door) -> np.ndarray:
    """Unit vector, normal to the closed panel, toward which the panel swings open: a robot
    that crosses the doorway along it pushes the door open."""
    a = door.closed_angle
    left = np.array([-math.sin(a), math.cos(a)])  # a counter-clockwise turn moves the tip this way
    return left if door.swing == "left" else -left


def door_crossings(world: World, points: np.ndarray) -> list[tuple[int, bool]]:
    """Where the polyline ``points`` ``(n, 2)`` (map metres) crosses a doorway, in order along it:
    ``(door index, True when it crosses the way the door opens)``."""
    p = np.asarray(points, dtype=np.float64)
    start, step = p[:-1], np.diff(p, axis=0)
    hits: list[tuple[int, int, bool]] = []
    for i, door in enumerate(world.doors):
        hinge, tip = door_segment(door)
        span = tip - hinge
        denom = step[:, 0] * span[1] - step[:, 1] * span[0]
        rel = hinge - start
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rel[:, 0] * span[1] - rel[:, 1] * span[0]) / denom  # along the path's step
            u = (rel[:, 0] * step[:, 1] - rel[:, 1] * step[:, 0]) / denom  # along the panel
        crossing = (denom != 0) & (t >= 0) & (t < 1) & (u >= -0.05) & (u <= 1.05)
        forward = step @ opening_direction(door) > 0
        hits += [(int(k), i, bool(forward[k])) for k in np.nonzero(crossing)[0]]
    return [(i, forward) for _, i, forward in sorted(hits)]


def closed_door_grid(world: World) -> np.ndarray:
    """The static occupancy grid with every door panel drawn closed (each cell the closed panel's
    line from hinge to tip passes through is an obstacle): the map a robot that never pushes a
    door would see."""
    grid = world.occupancy.copy()
    rows, cols = grid.shape
    for door in world.doors:
        hinge, tip = door_segment(door)
        for t in np.linspace(0.0, 1.0, int(math.ceil(door.width / world.resolution * 4)) + 2):
            iy, ix = world.cell_of(*(hinge + t * (tip - hinge)))
            if 0 <= iy < rows and 0 <= ix < cols:
                grid[iy, ix] = True
    return grid


def reachable(world: World, pair: StartGoal, doors_closed: bool = False,
              radius_m: float = CSPACE_RADIUS_M) -> bool:
    """Whether ``pair``'s goal can be reached from its start on the C-space grid (the map
    inflated by ``radius_m``), with the doors open (the static map: door gaps are free) or
    closed (``closed_door_grid``)."""
    grid = closed_door_grid(world) if doors_closed else world.occupancy
    cs = inflate(grid, int(round(radius_m / world.resolution)))
    s, g = world.cell_of(pair.x, pair.y), world.cell_of(pair.gx, pair.gy)
    if cs[s] or cs[g]:
        return False
    return GridGraph(cs).shortest_paths([s], [g])[0] is not None


class FloorPlan:
    """A floor plan being drawn on a walled grid of ``resolution`` m cells (``RESOLUTION`` for the
    NAMO floors): walls, door gaps with their doors, furniture."""

    def __init__(self, width: float, height: float, resolution: float = RESOLUTION) -> None:
        self.width, self.height, self.resolution = width, height, resolution
        self.grid = np.zeros((int(round(height / resolution)), int(round(width / resolution))), dtype=bool)
        self.grid[0, :] = self.grid[-1, :] = self.grid[:, 0] = self.grid[:, -1] = True
        self.doors: list[Door] = []

    def fill(self, x0: float, y0: float, x1: float, y1: float, value: bool = True) -> None:
        """Every cell that overlaps ``[x0, x1] x [y0, y1]`` (m)."""
        res = self.resolution
        r0, r1 = max(int(math.floor(y0 / res + 1e-9)), 0), int(math.ceil(y1 / res - 1e-9))
        c0, c1 = max(int(math.floor(x0 / res + 1e-9)), 0), int(math.ceil(x1 / res - 1e-9))
        self.grid[r0:r1, c0:c1] = value

    def wall_x(self, x: float, y0: float, y1: float) -> None:
        self.fill(x - WALL / 2, y0, x + WALL / 2, y1)

    def wall_y(self, y: float, x0: float, x1: float) -> None:
        self.fill(x0, y - WALL / 2, x1, y + WALL / 2)

    def door_x(self, x: float, y_centre: float, gap: float = DOOR_GAP, panel: bool = True) -> None:
        """A doorway ``gap`` m wide in the wall along x = ``x``, its door (``panel``; else an open
        doorway) opening toward +x."""
        y0 = y_centre - gap / 2
        self.fill(x - WALL, y0, x + WALL, y0 + gap, value=False)
        if panel:
            self.doors.append(Door(hinge_x=x, hinge_y=y0, width=gap - 0.04, closed_angle=math.pi / 2,
                                   swing="right", mass=1.0, hinge_friction=0.3))

    def door_y(self, y: float, x_centre: float, gap: float = DOOR_GAP, panel: bool = True) -> None:
        """A doorway ``gap`` m wide in the wall along y = ``y``, its door (``panel``; else an open
        doorway) opening toward +y."""
        x0 = x_centre - gap / 2
        self.fill(x0, y - WALL, x0 + gap, y + WALL, value=False)
        if panel:
            self.doors.append(Door(hinge_x=x0, hinge_y=y, width=gap - 0.04, closed_angle=0.0, swing="left",
                                   mass=1.0, hinge_friction=0.3))

    def world(self, family: str, seed: int, starts: list[Region], goals: list[Region], pairs: int,
              balls: int) -> World:
        """The finished world: ``pairs`` pairs from ``starts`` to ``goals`` through doors, then
        ``balls`` balls on their paths."""
        world = World(name=f"{family}-{seed}", occupancy=self.grid, resolution=self.resolution,
                      doors=tuple(self.doors), source=f"generated:{family} seed={seed}")
        rng = np.random.default_rng([seed, 1])
        world = world.with_changes(pairs=door_pairs(world, starts, goals, pairs, rng))
        return scatter_balls(world, balls, seed=seed) if balls else world


def _cells_in(world: World, free: np.ndarray, regions: list[Region]) -> np.ndarray:
    """``(iy, ix)`` of the ``free`` cells inside any of ``regions``, clear of the door swings."""
    rows, cols = free.shape
    iy, ix = np.mgrid[:rows, :cols]
    x, y = (ix + 0.5) * RESOLUTION, (iy + 0.5) * RESOLUTION
    inside = np.zeros_like(free)
    for r in regions:
        inside |= (x >= r.x_min) & (x <= r.x_max) & (y >= r.y_min) & (y <= r.y_max)
    for door in world.doors:  # away from the door swings
        inside &= np.hypot(x - door.hinge_x, y - door.hinge_y) > door.width + GOAL_CLEAR_OF_DOOR
    return np.argwhere(inside & free)


def door_pairs(world: World, starts: list[Region], goals: list[Region], count: int,
               rng: np.random.Generator) -> tuple[StartGoal, ...]:
    """``count`` pairs, start in ``starts`` and goal in ``goals``, whose shortest path crosses a
    door and every door on it the way it opens (see the module docstring). ``world`` has
    ``RESOLUTION`` cells and its origin at (0, 0); a finer plan passes its coarsened copy
    (``curlnav.worlds.difficulty.rank.resample``), whose pairs hold on the fine grid too."""
    cs = inflate(world.occupancy, int(round(CSPACE_RADIUS_M / RESOLUTION)))
    graph = GridGraph(cs)
    start_cells, goal_cells = _cells_in(world, ~cs, starts), _cells_in(world, ~cs, goals)
    chosen: list[StartGoal] = []
    for _ in range(100 * count):
        if len(chosen) == count:
            break
        s = tuple(int(v) for v in start_cells[rng.integers(len(start_cells))])
        g = tuple(int(v) for v in goal_cells[rng.integers(len(goal_cells))])
        (sx, sy), (gx, gy) = world.cell_centre(*s), world.cell_centre(*g)
        if math.hypot(gx - sx, gy - sy) < MIN_PAIR_DISTANCE:
            continue
        if any(math.hypot(sx - d.hinge_x, sy - d.hinge_y) < d.width + START_CLEAR_OF_DOOR for d in world.doors):
            continue
        if any(math.hypot(sx - p.x, sy - p.y) < 1.5 or math.hypot(gx - p.gx, gy - p.gy) < 1.5 for p in chosen):
            continue  # pairs spread over the floor
        path = graph.shortest_paths([s], [g], duplicate_start=False)[0]
        if path is None:
            continue
        points = np.array([world.cell_centre(int(r), int(c)) for r, c in path])
        crossings = door_crossings(world, points)
        if not crossings or not all(forward for _, forward in crossings):
            continue
        ahead = points[min(len(points) - 1, int(round(1.0 / RESOLUTION)))]
        yaw = math.atan2(ahead[1] - sy, ahead[0] - sx)
        if not footprint_free(world, sx, sy, yaw, *HUSKY_FOOTPRINT, margin=0.1):
            continue
        chosen.append(StartGoal(f"p{len(chosen) + 1}", sx, sy, round(yaw, 6), gx, gy))
    if len(chosen) < count:
        raise ValueError(f"{world.name}: found only {len(chosen)} of {count} pairs through doors")
    return tuple(chosen)


def namo_office(seed: int = 0, width: float = 22.0, height: float = 14.0, corridor: float = 2.4, pairs: int = 12,
                balls: int = 8) -> World:
    """A corridor along x with four rooms below and four above, each entered through a door;
    desks against the room walls. Pairs go from the lower rooms or the corridor's west end
    upward through one or two doors."""
    rng = np.random.default_rng(seed)
    floor = FloorPlan(width, height)
    y_low = (height - corridor) / 2 + rng.uniform(-0.8, 0.8)
    y_high = y_low + corridor
    floor.wall_y(y_low, 0, width)
    floor.wall_y(y_high, 0, width)
    bounds = [0.0] + [k * width / 4 + rng.uniform(-0.6, 0.6) for k in (1, 2, 3)] + [width]
    for x in bounds[1:-1]:
        floor.wall_x(x, 0, y_low)
        floor.wall_x(x, y_high, height)
    for x0, x1 in zip(bounds[:-1], bounds[1:]):
        for door_wall, far in ((y_low, 0.0), (y_high, height - 0.8)):
            floor.door_y(door_wall, rng.uniform(x0 + 1.4, x1 - 1.4))
            dx = rng.uniform(x0 + 0.5, x1 - 1.9)
            floor.fill(dx, far, dx + 1.4, far + 0.8)  # a desk against the wall across from the door
    lower = [Region(0.5, 0.5, width - 0.5, y_low - 0.8), Region(0.5, y_low + 0.6, 3.0, y_high - 0.6)]
    upper = [Region(0.5, y_high + 0.8, width - 0.5, height - 0.5)]
    return floor.world("namo-office", seed, lower, upper, pairs, balls)


def namo_indoor(seed: int = 0, width: float = 24.0, height: float = 18.0, pairs: int = 12, balls: int = 8) -> World:
    """3 x 3 rooms; a door between two neighbours with probability 0.6, and every room but the
    south-west one has one from its west or south neighbour, so all are reachable going east
    and north. A table and a column in each room. Pairs go east and north through doors."""
    rng = np.random.default_rng(seed)
    floor = FloorPlan(width, height)
    xs = [0.0, width / 3 + rng.uniform(-0.8, 0.8), 2 * width / 3 + rng.uniform(-0.8, 0.8), width]
    ys = [0.0, height / 3 + rng.uniform(-0.6, 0.6), 2 * height / 3 + rng.uniform(-0.6, 0.6), height]
    for x in xs[1:-1]:
        floor.wall_x(x, 0, height)
    for y in ys[1:-1]:
        floor.wall_y(y, 0, width)
    for i in range(3):
        for j in range(3):
            west = i > 0 and rng.random() < 0.6
            south = j > 0 and rng.random() < 0.6
            if (i or j) and not (west or south):
                west, south = (True, False) if (i and (not j or rng.random() < 0.5)) else (False, True)
            if west:
                floor.door_x(xs[i], rng.uniform(ys[j] + 1.3, ys[j + 1] - 1.3))
            if south:
                floor.door_y(ys[j], rng.uniform(xs[i] + 1.3, xs[i + 1] - 1.3))
            cx, cy = rng.uniform(xs[i] + 2.6, xs[i + 1] - 2.6), rng.uniform(ys[j] + 2.2, ys[j + 1] - 2.2)
            floor.fill(cx - 0.6, cy - 0.4, cx + 0.6, cy + 0.4)  # a table mid-room
            corner_x = xs[i] + 0.5 if rng.random() < 0.5 else xs[i + 1] - 0.9
            corner_y = ys[j] + 0.5 if rng.random() < 0.5 else ys[j + 1] - 0.9
            floor.fill(corner_x, corner_y, corner_x + 0.4, corner_y + 0.4)  # a column near a corner
    rooms = [Region(xs[i] + 0.6, ys[j] + 0.6, xs[i + 1] - 0.6, ys[j + 1] - 0.6) for i in range(3) for j in range(3)]
    return floor.world("namo-indoor", seed, rooms[:-1], rooms[1:], pairs, balls)


def namo_auditorium(seed: int = 0, width: float = 24.0, height: float = 16.0, pairs: int = 12,
                    balls: int = 8) -> World:
    """A lobby along the south wall joined by three doors to a hall: rows of seats broken by
    two aisles, a stage along the north wall. Pairs go from the lobby into the hall."""
    rng = np.random.default_rng(seed)
    floor = FloorPlan(width, height)
    lobby = 3.6 + rng.uniform(-0.3, 0.3)
    floor.wall_y(lobby, 0, width)
    for k in range(3):
        floor.door_y(lobby, (k + 0.5) * width / 3 + rng.uniform(-1.5, 1.5))
    stage = height - 2.2
    floor.fill(width * 0.25, stage, width * 0.75, height)
    aisles = sorted(rng.uniform(width * 0.25, width * 0.75, 2))
    if aisles[1] - aisles[0] < 4.0:
        aisles = [width / 2 - 3.0, width / 2 + 3.0]
    row_y = lobby + 2.4
    while row_y < stage - 2.2:
        for x0, x1 in ((1.8, aisles[0] - 0.9), (aisles[0] + 0.9, aisles[1] - 0.9), (aisles[1] + 0.9, width - 1.8)):
            floor.fill(x0, row_y, x1, row_y + 0.5)
        row_y += 1.9
    lobby_region = [Region(0.5, 0.5, width - 0.5, lobby - 0.6)]
    hall = [Region(0.5, lobby + 0.8, width - 0.5, height - 0.5)]
    return floor.world("namo-auditorium", seed, lobby_region, hall, pairs, balls)


NAMO_FAMILIES = {"namo-auditorium": namo_auditorium, "namo-office": namo_office, "namo-indoor": namo_indoor}
