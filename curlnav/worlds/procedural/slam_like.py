"""Worlds that look like SLAM maps: ``slam-office`` (a large floor, the static-geometry stress
case), ``slam-floor`` (NAMO office floors of real widths) and ``slam-namo-*`` (the NAMO floors
degraded).

``slam-office``: a large office floor as a SLAM stack would map it, at 0.05 m per cell.

Real maps from ROS SLAM (gmapping, Cartographer, slam_toolbox) are fine-grained and ragged:
thin walls with bumps where the laser grazed them, furniture, and isolated specks of noise.
Such a map merges into thousands of rectangles, where a clean generated world has a few
hundred. This family is the stress case for the static geometry and the LiDAR (about
92 m x 72 m, several thousand rectangles), and a stand-in for a user's own map.

Layout: the floor is split recursively (binary space partition) into rooms of 4-12 m; every
dividing wall gets a doorway of 1.1-1.6 m, so every room is reachable (the partition is a tree);
then desks, round tables and columns, bumps along the walls, and specks of noise.

``slam-floor``: an office or lab floor about 27 m x 19.5 m (``floor_plan``) at 0.05 m cells,
degraded (``curlnav.worlds.procedural.degrade``): a corridor along x and a cross corridor north of it, each
``corridor_min``-``corridor_max`` wide (1.2-2.4 m: the building codes' 1.12-1.83 m minimum egress
widths up to a hospital's 2.44 m), rooms of 3-6 m off them, doorways ``door_min``-``door_max``
wide (0.8-1.0 m: a Husky is 0.67 m wide) with hinged doors opening toward +x or +y (a share
``open_doorways`` of the lower rooms' doorways and inner doorways are open, with no panel; every
upper room is entered through a door), deep upper rooms split front and back by a wall with a
doorway, neighbouring rooms joined now and then, one or two closed shafts (stairs, lifts, ducts:
unknown once degraded), unmapped ground round the building, desks and tables. As the NAMO floors:
12 pairs from the lower rooms or the corridor's west end to the upper rooms whose shortest path
crosses a door, every door on it the way it opens (``curlnav.worlds.procedural.namo.door_pairs``, on the plan
coarsened to 0.15 m, whose doorways sit on that grid so none closes), and 8 balls on their paths.

``slam-namo-office``, ``slam-namo-indoor``, ``slam-namo-auditorium``: the NAMO floors at 0.05 m,
degraded. Every ``slam-*`` family but ``slam-office`` takes its source generator's parameters and
``degrade``'s (``SLAM_FAMILY_DEFAULTS`` the latter's defaults there); its seed seeds both.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from curlnav.worlds.core.world import RandomPairs, Region, World
from curlnav.worlds.difficulty.rank import resample
from curlnav.worlds.procedural.degrade import degrade
from curlnav.worlds.procedural.namo import RESOLUTION, WALL, FloorPlan, door_pairs, namo_auditorium, namo_indoor, namo_office
from curlnav.worlds.procedural.scatter import scatter_balls

SLAM_RESOLUTION = 0.05  # m per cell, a common SLAM map resolution (gmapping's delta, slam_toolbox's default)


def slam_office(seed: int = 0, width: float = 92.0, height: float = 72.0, resolution: float = SLAM_RESOLUTION,
                min_room: float = 4.0, max_room: float = 12.0, wall: float = 0.15, furniture_per_room: float = 3.0,
                bump_probability: float = 0.25, speck_density: float = 0.0004) -> World:
    """A seeded office floor (see the module docstring); lengths in m, densities per cell."""
    if width <= 2 * max_room or height <= 2 * max_room:
        raise ValueError(f"slam-office needs width and height above 2 x max_room ({2 * max_room} m)")
    if not 0 < min_room < max_room:
        raise ValueError("slam-office needs 0 < min_room < max_room")
    rng = np.random.default_rng(seed)

    def cells(metres: float) -> int:
        return int(round(metres / resolution))

    rows, cols = cells(height), cells(width)
    grid = np.zeros((rows, cols), dtype=bool)
    t = max(cells(wall), 1)
    grid[:t, :] = grid[-t:, :] = grid[:, :t] = grid[:, -t:] = True
    keep_free = np.zeros_like(grid)  # doorways: no furniture or bumps in front of them
    rooms: list[tuple[int, int, int, int]] = []

    def split(r0: int, c0: int, r1: int, c1: int) -> None:
        h, w = r1 - r0, c1 - c0
        can_rows, can_cols = h > 2 * cells(min_room), w > 2 * cells(min_room)
        if (h <= cells(max_room) and w <= cells(max_room)) or not (can_rows or can_cols):
            rooms.append((r0, c0, r1, c1))
            return
        along_rows = can_rows and (not can_cols or h >= w)
        if along_rows:
            cut = int(rng.integers(r0 + cells(min_room), r1 - cells(min_room)))
            grid[cut:cut + t, c0:c1] = True
            door = cells(rng.uniform(1.1, 1.6))
            at = int(rng.integers(c0 + t + 1, max(c1 - door - 1, c0 + t + 2)))
            grid[cut:cut + t, at:at + door] = False
            keep_free[max(cut - cells(1.0), 0):cut + t + cells(1.0), at:at + door] = True
            split(r0, c0, cut, c1)
            split(cut + t, c0, r1, c1)
        else:
            cut = int(rng.integers(c0 + cells(min_room), c1 - cells(min_room)))
            grid[r0:r1, cut:cut + t] = True
            door = cells(rng.uniform(1.1, 1.6))
            at = int(rng.integers(r0 + t + 1, max(r1 - door - 1, r0 + t + 2)))
            grid[at:at + door, cut:cut + t] = False
            keep_free[at:at + door, max(cut - cells(1.0), 0):cut + t + cells(1.0)] = True
            split(r0, c0, r1, cut)
            split(r0, cut + t, r1, c1)

    split(t, t, rows - t, cols - t)
    furniture = np.zeros_like(grid)
    for r0, c0, r1, c1 in rooms:
        for _ in range(int(rng.poisson(furniture_per_room))):
            kind = rng.random()
            if kind < 0.6:  # a desk or shelf along no particular wall
                fh, fw = (cells(rng.uniform(0.5, 0.8)), cells(rng.uniform(1.0, 1.8)))
                if rng.random() < 0.5:
                    fh, fw = fw, fh
                if r1 - r0 <= fh + 2 * t or c1 - c0 <= fw + 2 * t:
                    continue
                fr = int(rng.integers(r0 + t, r1 - fh - t))
                fc = int(rng.integers(c0 + t, c1 - fw - t))
                furniture[fr:fr + fh, fc:fc + fw] = True
            else:  # a round table or a column
                radius = rng.uniform(0.2, 0.6)
                cy = rng.uniform(r0 + cells(1.0), r1 - cells(1.0))
                cx = rng.uniform(c0 + cells(1.0), c1 - cells(1.0))
                rr = cells(radius)
                y0, y1 = int(max(cy - rr - 1, 0)), int(min(cy + rr + 2, rows))
                x0, x1 = int(max(cx - rr - 1, 0)), int(min(cx + rr + 2, cols))
                yy, xx = np.ogrid[y0:y1, x0:x1]
                furniture[y0:y1, x0:x1] |= (yy + 0.5 - cy) ** 2 + (xx + 0.5 - cx) ** 2 <= rr * rr
    grid |= furniture & ~keep_free
    # bumps where the laser grazed a surface: free cells touching an obstacle, at random
    rim = ndimage.binary_dilation(grid) & ~grid & ~keep_free
    grid |= rim & (rng.random(grid.shape) < bump_probability)
    # isolated specks of noise
    grid |= (rng.random(grid.shape) < speck_density) & ~keep_free
    return World(name=f"slam-office-{seed}", occupancy=grid, resolution=resolution,
                 random_pairs=RandomPairs(min_distance=10.0, clearance=0.6),
                 source=f"generated:slam-office seed={seed}")


# -- slam-floor ----------------------------------------------------------------------------
LATTICE = RESOLUTION  # m; doorways start on this grid, so the 0.15 m C-space grid keeps every one open
OUTSIDE = 0.6  # m of unmapped ground round the building
ROOM_MIN, ROOM_MAX = 3.0, 6.0  # m, a room's width along its corridor
DOOR_MARGIN = 0.3  # m from a doorway to the room's corner
PLAN_ATTEMPTS = 8  # draws of a plan before a seed is given up


def floor_plan(seed: int = 0, width: float = 27.0, height: float = 19.5, corridor_min: float = 1.2,
               corridor_max: float = 2.4, door_min: float = 0.8, door_max: float = 1.0, open_doorways: float = 0.3,
               furniture: float = 2.0, resolution: float = SLAM_RESOLUTION, pairs: int = 12,
               balls: int = 8) -> World:
    """``slam-floor``'s clean plan (see the module docstring): lengths in m, ``open_doorways`` a
    probability, ``furniture`` pieces per room on average. ``resolution`` must divide 0.15 m."""
    if width < 18.0 or height < 14.0:
        raise ValueError(f"slam-floor needs at least 18 m x 14 m, got {width} x {height}")
    if not 1.0 <= corridor_min <= corridor_max <= 3.0:
        raise ValueError(f"slam-floor needs 1.0 <= corridor_min <= corridor_max <= 3.0 m, got {corridor_min}, "
                         f"{corridor_max}")
    if not 0.8 <= door_min <= door_max <= 1.5:
        raise ValueError(f"slam-floor needs 0.8 <= door_min <= door_max <= 1.5 m (a Husky is 0.67 m wide), got "
                         f"{door_min}, {door_max}")
    ratio = LATTICE / resolution
    if not (resolution > 0 and abs(ratio - round(ratio)) < 1e-6):
        raise ValueError(f"slam-floor's resolution must divide {LATTICE} m, got {resolution}")
    width, height = _on(width, LATTICE), _on(height, LATTICE)
    for attempt in range(PLAN_ATTEMPTS):  # a plan that leaves too few pairs through doors is drawn again
        rng = np.random.default_rng(seed if attempt == 0 else [seed, 100 + attempt])
        grid, doors, starts, goals = _draw_plan(rng, width, height, corridor_min, corridor_max, door_min, door_max,
                                                open_doorways, furniture, resolution)
        world = World(name=f"slam-floor-plan-{seed}", occupancy=grid, resolution=resolution, doors=doors,
                      source=f"generated:slam-floor plan seed={seed}")
        coarse = world.with_changes(occupancy=resample(world.occupancy, resolution, LATTICE), resolution=LATTICE)
        try:
            chosen = door_pairs(coarse, starts, goals, pairs, np.random.default_rng([seed, 1]))
        except ValueError:  # too few pairs through doors
            continue
        world = world.with_changes(pairs=chosen)
        return scatter_balls(world, balls, seed=seed) if balls else world
    raise ValueError(f"slam-floor seed {seed}: none of {PLAN_ATTEMPTS} plans has {pairs} pairs through doors")


def _draw_plan(rng: np.random.Generator, width: float, height: float, corridor_min: float, corridor_max: float,
               door_min: float, door_max: float, open_doorways: float, furniture: float, resolution: float):
    """One draw of ``floor_plan``'s layout: ``(grid, doors, start regions, goal regions)``."""
    plan = FloorPlan(width, height, resolution)
    layout = _Layout(plan, rng, resolution, door_min, door_max, open_doorways)
    x0, y0, x1, y1 = OUTSIDE + WALL, OUTSIDE + WALL, width - OUTSIDE - WALL, height - OUTSIDE - WALL  # inside
    plan.fill(x0 - WALL, y0 - WALL, x1 + WALL, y0)
    plan.fill(x0 - WALL, y1, x1 + WALL, y1 + WALL)
    plan.fill(x0 - WALL, y0, x0, y1)
    plan.fill(x1, y0, x1 + WALL, y1)
    # the corridor along x, [yc, yt] clear; the cross corridor north of it, [xc, xc + c2] clear
    yc = _on(y0 + rng.uniform(4.0, 6.0) + WALL, resolution)
    yt = yc + _on(rng.uniform(corridor_min, corridor_max), resolution)
    c2 = _on(rng.uniform(corridor_min, corridor_max), resolution)
    xc = _on(rng.uniform(x0 + 0.35 * (x1 - x0), x0 + 0.6 * (x1 - x0)), resolution)
    plan.fill(x0, yc - WALL, x1, yc)
    plan.fill(x0, yt, xc, yt + WALL)
    plan.fill(xc + c2, yt, x1, yt + WALL)
    plan.fill(xc - WALL, yt, xc, y1)
    plan.fill(xc + c2, yt, xc + c2 + WALL, y1)
    lower = layout.rooms(x0, y0, x1, yc - WALL)
    for room in lower:  # each onto the corridor, its door swinging into it
        layout.door_y(yc - WALL / 2, room.x_min, room.x_max, panel=rng.random() >= open_doorways)
    layout.neighbours(lower)
    upper_left = layout.rooms(x0, yt + WALL, xc - WALL, y1)
    upper_right = layout.rooms(xc + c2 + WALL, yt + WALL, x1, y1)
    fronts, goals = [], []
    for room in upper_left + upper_right:  # deep rooms split front and back
        if room.y_max - room.y_min >= 7.0 and rng.random() < 0.6:
            split = _on(room.y_min + rng.uniform(3.0, room.y_max - room.y_min - 3.0), resolution)
            plan.fill(room.x_min, split - WALL / 2, room.x_max, split + WALL / 2)
            layout.door_y(split, room.x_min, room.x_max, panel=rng.random() >= open_doorways)
            fronts.append(Region(room.x_min, room.y_min, room.x_max, split - WALL / 2))
            goals += [fronts[-1], Region(room.x_min, split + WALL / 2, room.x_max, room.y_max)]
        else:
            fronts.append(room)
            goals.append(room)
    for k, room in enumerate(fronts):  # each upper room through a door that swings into it
        if k == len(upper_left) and rng.random() < 0.5:  # the first room east of the cross corridor: from it
            layout.door_x(xc + c2 + WALL / 2, room.y_min, room.y_max)
        else:
            layout.door_y(yt + WALL / 2, room.x_min, room.x_max)
    layout.neighbours(fronts[:len(upper_left)])
    layout.neighbours(fronts[len(upper_left):])
    rooms = lower + goals
    shafts = {int(k) for k in rng.choice(len(rooms), size=int(rng.integers(1, 3)), replace=False)}
    for k, room in enumerate(rooms):
        if k in shafts:
            layout.shaft(room)
        layout.furnish(room, int(rng.poisson(furniture)))
    inset = 0.5
    starts = [Region(r.x_min + inset, r.y_min + inset, r.x_max - inset, r.y_max - inset) for r in lower]
    starts.append(Region(x0 + inset, yc + 0.4, x0 + 3.0, yt - 0.4))  # the corridor's west end
    goals = [Region(r.x_min + inset, r.y_min + inset, r.x_max - inset, r.y_max - inset) for r in goals]
    return plan.grid, tuple(plan.doors), starts, goals


def _on(value: float, step: float) -> float:
    """``value`` rounded to a multiple of ``step``."""
    return round(round(value / step) * step, 6)


class _Layout:
    """Rooms, doorways, shafts and furniture of a ``floor_plan`` on its ``FloorPlan``."""

    def __init__(self, plan: FloorPlan, rng: np.random.Generator, resolution: float, door_min: float,
                 door_max: float, open_doorways: float) -> None:
        self.plan, self.rng, self.res = plan, rng, resolution
        self.door_min, self.door_max, self.open_doorways = door_min, door_max, open_doorways
        self.clear: list[tuple[float, float, float]] = []  # (x, y, radius) kept free of furniture and shafts

    def rooms(self, x0: float, y0: float, x1: float, y1: float) -> list[Region]:
        """``[x0, x1] x [y0, y1]`` split along x by walls into rooms ``ROOM_MIN``-``ROOM_MAX`` wide."""
        cuts = [x0]
        while x1 - cuts[-1] > ROOM_MAX:
            cuts.append(_on(cuts[-1] + self.rng.uniform(ROOM_MIN, min(ROOM_MAX, x1 - cuts[-1] - ROOM_MIN)), self.res))
        cuts.append(x1)
        for x in cuts[1:-1]:
            self.plan.fill(x - WALL / 2, y0, x + WALL / 2, y1)
        return [Region(a + (WALL / 2 if k else 0.0), y0, b - (WALL / 2 if k < len(cuts) - 2 else 0.0), y1)
                for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:]))]

    def _doorway(self, lo: float, hi: float) -> tuple[float, float] | None:
        """A doorway's width and its low edge on the ``LATTICE`` within ``[lo, hi]`` (None: no room)."""
        gap = _on(self.rng.uniform(self.door_min, self.door_max), self.res)
        first = math.ceil((lo + DOOR_MARGIN) / LATTICE - 1e-9)
        last = math.floor((hi - DOOR_MARGIN - gap) / LATTICE + 1e-9)
        if last < first:
            return None
        return gap, _on(LATTICE * int(self.rng.integers(first, last + 1)), self.res)

    def door_y(self, y: float, x_lo: float, x_hi: float, panel: bool = True) -> None:
        """A doorway in the wall along y = ``y`` between ``x_lo`` and ``x_hi``; its door opens toward +y."""
        found = self._doorway(x_lo, x_hi)
        if found:
            gap, edge = found
            self.plan.door_y(y, edge + gap / 2, gap, panel)
            self.clear.append((edge + gap / 2, y, gap + 0.6))

    def door_x(self, x: float, y_lo: float, y_hi: float, panel: bool = True) -> None:
        """A doorway in the wall along x = ``x`` between ``y_lo`` and ``y_hi``; its door opens toward +x."""
        found = self._doorway(y_lo, y_hi)
        if found:
            gap, edge = found
            self.plan.door_x(x, edge + gap / 2, gap, panel)
            self.clear.append((x, edge + gap / 2, gap + 0.6))

    def neighbours(self, rooms: list[Region]) -> None:
        """Doorways between neighbouring rooms of a row, now and then (their doors open toward +x)."""
        for west, east in zip(rooms[:-1], rooms[1:]):
            if self.rng.random() < 0.35:
                self.door_x((west.x_max + east.x_min) / 2, east.y_min, east.y_max,
                            panel=self.rng.random() >= self.open_doorways)

    def _free_of_doorways(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        return all(math.hypot(max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1)) > r for x, y, r in self.clear)

    def shaft(self, room: Region) -> None:
        """A closed shaft (stairs, a lift, a duct) in a corner of ``room``: walls all round, no door."""
        w, h = self.rng.uniform(1.2, 2.0), self.rng.uniform(1.2, 2.0)
        for _ in range(8):
            x0 = room.x_min if self.rng.random() < 0.5 else room.x_max - w
            y0 = room.y_min if self.rng.random() < 0.5 else room.y_max - h
            x0, y0 = _on(x0, self.res), _on(y0, self.res)
            if self._free_of_doorways(x0, y0, x0 + w, y0 + h):
                inner = (x0 + WALL, y0 + WALL, x0 + w - WALL, y0 + h - WALL)
                self.plan.fill(x0, y0, x0 + w, y0 + h)
                self.plan.fill(*inner, value=False)
                self.clear.append((x0 + w / 2, y0 + h / 2, math.hypot(w, h) / 2 + 0.3))
                return

    def furnish(self, room: Region, count: int) -> None:
        """``count`` pieces in ``room``: desks against its walls, tables in its middle; none in
        front of a doorway or on a shaft."""
        for _ in range(count):
            for _ in range(8):
                if self.rng.random() < 0.7:  # a desk against one of the walls
                    depth, length = self.rng.uniform(0.6, 0.8), self.rng.uniform(1.2, 1.8)
                    side = int(self.rng.integers(4))
                    if side < 2:  # against the south or north wall
                        x0 = room.x_min + self.rng.random() * (room.x_max - length - room.x_min)
                        y0 = room.y_min if side == 0 else room.y_max - depth
                        box = (x0, y0, x0 + length, y0 + depth)
                    else:
                        y0 = room.y_min + self.rng.random() * (room.y_max - length - room.y_min)
                        x0 = room.x_min if side == 2 else room.x_max - depth
                        box = (x0, y0, x0 + depth, y0 + length)
                else:  # a table with room to walk round it
                    a, b = self.rng.uniform(1.2, 2.0), self.rng.uniform(0.8, 1.0)
                    a, b = (a, b) if self.rng.random() < 0.5 else (b, a)
                    x0 = room.x_min + 1.0 + self.rng.random() * (room.x_max - 2.0 - a - room.x_min)
                    y0 = room.y_min + 1.0 + self.rng.random() * (room.y_max - 2.0 - b - room.y_min)
                    box = (x0, y0, x0 + a, y0 + b)
                inside = room.x_min <= box[0] and box[2] <= room.x_max and room.y_min <= box[1] and box[3] <= room.y_max
                if inside and self._free_of_doorways(*box):
                    self.plan.fill(*(_on(v, self.res) for v in box))
                    self.clear.append(((box[0] + box[2]) / 2, (box[1] + box[3]) / 2, 0.0))
                    break


# -- the slam-* families -------------------------------------------------------------------
SLAM_FAMILY_DEFAULTS = {"resolution": SLAM_RESOLUTION}  # degrade's defaults that a slam-* family changes


def slam_version(base: Callable[..., World], family: str) -> Callable[..., World]:
    """A family generator ``(seed=0, **params)``: ``base``'s world of ``seed``, degraded with that
    seed (``curlnav.worlds.procedural.degrade``), named ``FAMILY-SEED``. Its signature lists ``base``'s
    parameters and ``degrade``'s (a ``resolution`` of ``base`` is base's, and ``degrade`` keeps it)
    as keyword arguments, so world distributions and ``curlnav worlds generate`` see them all."""
    base_params = [p for name, p in inspect.signature(base).parameters.items() if name != "seed"]
    own = {p.name for p in base_params}
    extra = [p.replace(default=SLAM_FAMILY_DEFAULTS.get(p.name, p.default))
             for p in inspect.signature(degrade).parameters.values()
             if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in own]
    signature = inspect.Signature([inspect.Parameter("seed", inspect.Parameter.POSITIONAL_OR_KEYWORD, default=0)]
                                  + [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in base_params] + extra,
                                  return_annotation=World)

    def generator(*args, **kwargs) -> World:
        bound = signature.bind(*args, **kwargs)  # TypeError names an unknown parameter
        bound.apply_defaults()
        values = dict(bound.arguments)
        seed = values.pop("seed")
        world = base(seed=seed, **{name: values.pop(name) for name in own})
        return degrade(world, seed, **values).with_changes(name=f"{family}-{seed}",
                                                           source=f"generated:{family} seed={seed}")

    generator.__signature__ = signature
    generator.__name__ = generator.__qualname__ = family.replace("-", "_")
    generator.__doc__ = f"``{family}``: {base.__name__} degraded as a SLAM map (``curlnav.worlds.procedural.degrade``)."
    return generator


slam_floor = slam_version(floor_plan, "slam-floor")
slam_namo_office = slam_version(namo_office, "slam-namo-office")
slam_namo_indoor = slam_version(namo_indoor, "slam-namo-indoor")
slam_namo_auditorium = slam_version(namo_auditorium, "slam-namo-auditorium")
