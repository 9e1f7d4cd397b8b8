"""Random start/goal pairs on the C-space grid, and the check that a world can have any.

A world with ``random_pairs`` draws its pairs with that setting; a world with neither ``pairs``
nor ``random_pairs`` (a plain ROS SLAM map) draws them with ``default_random_pairs``: at least
``DEFAULT_MIN_DISTANCE`` apart, or half the extent of its largest free region when that is
smaller (never under ``MIN_PAIR_DISTANCE``), with ``RandomPairs``' default clearance.

Clearance is measured from a cell's centre to the nearest *edge* of an obstacle cell (a lower
bound: centre distance minus half a cell diagonal), and the map's outer edge counts as an
obstacle. A start is kept only if the robot's footprint rectangle (plus ``FOOTPRINT_MARGIN``) at
the drawn yaw overlaps no obstacle cell and stays inside the map, so no episode starts touching
a wall, whatever the clearance setting.

``check_pairs_possible`` raises the one-line ``WorldError`` for a world with no connected free
space (no pair possible) without building any PyBullet scene; ``NamoEnv`` calls it when it is
constructed or switches worlds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy import ndimage

from curlnav.worlds.core.world import RandomPairs, StartGoal, World, WorldError

DEFAULT_MIN_DISTANCE = 4.0  # m, pairs of a plain map
MIN_PAIR_DISTANCE = 1.0  # m; closer pairs are not a task (the goal tolerance is 0.8 m)
FOOTPRINT_MARGIN = 0.05  # m added to each side of the footprint rectangle
HUSKY_FOOTPRINT = (0.99, 0.67)  # m, length x width (RobotConfig's default)
MAX_TRIES = 1000


def pair_key(x: float, y: float, gx: float, gy: float) -> tuple[float, float, float, float]:
    """A start/goal pair's identity for ``NamoEnv.excluded_pairs`` (positions rounded to 1 mm)."""
    return (round(x, 3), round(y, 3), round(gx, 3), round(gy, 3))


def draws_random_pairs(world: World) -> bool:
    """True when resets without an assigned pair draw random pairs (``random_pairs`` is set or
    the world has no pairs of its own)."""
    return world.random_pairs is not None or not world.pairs


def default_random_pairs() -> RandomPairs:
    """The setting a world with neither pairs nor ``random_pairs`` draws with (its
    ``min_distance`` may shrink to the map, see the module docstring)."""
    return RandomPairs(min_distance=DEFAULT_MIN_DISTANCE)


def clearance_map(world: World) -> np.ndarray:
    """Per cell (shape of the grid), the distance (m) from its centre to the nearest obstacle
    cell's edge or the map's outer edge (a lower bound: centre distance minus half a cell
    diagonal); 0 or less on obstacle cells."""
    occ = np.pad(np.asarray(world.occupancy, dtype=bool), 1, constant_values=True)
    dist = ndimage.distance_transform_edt(~occ)[1:-1, 1:-1] * world.resolution
    return dist - world.resolution * math.sqrt(0.5)


def cspace_free(world: World, clearance: float) -> np.ndarray:
    """Cells whose centre is more than ``clearance`` (m) from every obstacle cell's edge and
    from the map's outer edge."""
    return clearance_map(world) > clearance


class PairSampler:
    """Draws start/goal pairs of one world. Construction measures the C-space and raises
    ``WorldError`` (one line) when no pair is possible."""

    def __init__(self, world: World, spec: RandomPairs | None = None,
                 footprint: tuple[float, float] = HUSKY_FOOTPRINT) -> None:
        self.world = world
        self.footprint = footprint
        own = spec is not None or world.random_pairs is not None
        spec = spec or world.random_pairs or default_random_pairs()
        free = cspace_free(world, spec.clearance)
        labels, count = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        extents = np.zeros(count + 1)
        for k, box in enumerate(ndimage.find_objects(labels), start=1):
            if box is not None:
                h, w = box[0].stop - box[0].start - 1, box[1].stop - box[1].start - 1
                extents[k] = math.hypot(h, w) * world.resolution  # bounds the farthest pair inside
        largest = float(extents.max()) if count else 0.0
        if not own:
            spec = replace(spec, min_distance=max(min(spec.min_distance, 0.5 * largest), MIN_PAIR_DISTANCE))
        if count == 0 or largest < spec.min_distance:
            what = "no free cell" if count == 0 else f"no two connected free cells {spec.min_distance:g} m apart"
            raise WorldError(f"{world.source}: world {world.name!r} has no connected free space for a start/goal pair: "
                             f"{what} once the map is inflated by {spec.clearance:g} m")
        self.spec = spec
        self.labels = labels
        eligible = np.isin(labels, np.nonzero(extents >= spec.min_distance)[0])
        self.starts = np.argwhere(eligible)
        self._members: dict[int, np.ndarray] = {}

    def _component(self, label: int) -> np.ndarray:
        if label not in self._members:
            self._members[label] = np.argwhere(self.labels == label)
        return self._members[label]

    def draw(self, rng: np.random.Generator, excluded: set | frozenset = frozenset(),
             name: str = "random", max_distance: float = math.inf) -> StartGoal:
        """A seeded pair: start and goal on connected free C-space cells at least
        ``spec.min_distance`` and at most ``max_distance`` (m, straight line) apart, the footprint
        free at the start's yaw, not in ``excluded`` (``pair_key`` tuples)."""
        world, spec = self.world, self.spec
        for _ in range(MAX_TRIES):
            sy, sx = self.starts[rng.integers(len(self.starts))]
            if math.isfinite(max_distance):  # only the cells within reach: the same cells, in the same order
                reach = int(math.ceil(max_distance / world.resolution))
                y0, x0 = max(int(sy) - reach, 0), max(int(sx) - reach, 0)
                near = self.labels[y0:sy + reach + 1, x0:sx + reach + 1] == self.labels[sy, sx]
                same = np.argwhere(near) + (y0, x0)
            else:
                same = self._component(int(self.labels[sy, sx]))
            d = np.hypot(same[:, 0] - sy, same[:, 1] - sx) * world.resolution
            far = same[(d >= spec.min_distance) & (d <= max_distance)]
            if len(far) == 0:
                continue
            gy, gx = far[rng.integers(len(far))]
            start = world.cell_centre(int(sy), int(sx))
            goal = world.cell_centre(int(gy), int(gx))
            if pair_key(start[0], start[1], goal[0], goal[1]) in excluded:
                continue
            yaw = float(rng.uniform(-math.pi, math.pi))
            if not footprint_free(world, start[0], start[1], yaw, *self.footprint, margin=FOOTPRINT_MARGIN):
                continue
            return StartGoal(name, start[0], start[1], yaw, goal[0], goal[1])
        apart = f"{spec.min_distance:g}-{max_distance:g} m" if math.isfinite(max_distance) else f"{spec.min_distance:g} m"
        raise WorldError(f"{world.source}: world {world.name!r}: found no start/goal pair {apart} apart "
                         f"in {MAX_TRIES} tries")


def footprint_cells(world: World, x: float, y: float, yaw: float, length: float, width: float,
                    margin: float = 0.0) -> np.ndarray:
    """``(iy, ix)`` of every grid cell (possibly outside the grid) that the rectangle
    ``length x width`` (+ ``margin`` on each side) centred at map point ``(x, y)`` with heading
    ``yaw`` overlaps (separating axes; touching edges do not count)."""
    res = world.resolution
    a, b = length / 2 + margin, width / 2 + margin
    u0, v0 = world.grid_from_map(x, y)
    theta = yaw - world.origin_yaw
    c, s = abs(math.cos(theta)), abs(math.sin(theta))
    reach = math.hypot(a, b) + res
    iy0, iy1 = int(math.floor((v0 - reach) / res)), int(math.floor((v0 + reach) / res))
    ix0, ix1 = int(math.floor((u0 - reach) / res)), int(math.floor((u0 + reach) / res))
    iy, ix = np.mgrid[iy0:iy1 + 1, ix0:ix1 + 1]
    du, dv = (ix + 0.5) * res - u0, (iy + 0.5) * res - v0
    h = res / 2
    ct, st = math.cos(theta), math.sin(theta)
    hit = ((np.abs(du) < h + a * c + b * s) & (np.abs(dv) < h + a * s + b * c)
           & (np.abs(du * ct + dv * st) < a + h * (c + s)) & (np.abs(-du * st + dv * ct) < b + h * (c + s)))
    return np.stack([iy[hit], ix[hit]], axis=1)


def footprint_free(world: World, x: float, y: float, yaw: float, length: float, width: float,
                   margin: float = 0.0) -> bool:
    """True when the footprint rectangle overlaps no obstacle cell and lies inside the map."""
    cells = footprint_cells(world, x, y, yaw, length, width, margin)
    rows, cols = world.occupancy.shape
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < rows) & (cells[:, 1] >= 0) & (cells[:, 1] < cols)
    if not inside.all():
        return False
    return not world.occupancy[cells[:, 0], cells[:, 1]].any()


def check_pairs_possible(world: World, footprint: tuple[float, float] = HUSKY_FOOTPRINT) -> PairSampler | None:
    """The world's ``PairSampler`` when it draws random pairs (``None`` when it only uses its own
    pairs); ``WorldError`` (one line) when no pair is possible. Builds no PyBullet scene."""
    if not draws_random_pairs(world):
        return None
    return PairSampler(world, footprint=footprint)


def sample_pairs(world: World, count: int, seed: int = 0, footprint: tuple[float, float] = HUSKY_FOOTPRINT,
                 prefix: str = "p") -> tuple[StartGoal, ...]:
    """``count`` seeded random pairs named ``<prefix>1..`` (same seed, same pairs)."""
    sampler = PairSampler(world, footprint=footprint)
    rng = np.random.default_rng(seed)
    return tuple(sampler.draw(rng, name=f"{prefix}{i + 1}") for i in range(count))
