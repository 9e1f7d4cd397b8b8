"""Degrade a world into what a SLAM map of it looks like: ``degrade(world, seed, ...)``.

A map from gmapping, Cartographer or slam_toolbox is fine-grained (0.05 m cells) and ragged:
walls one or two cells thick with holes where the laser got no return (glass, dark or grazed
surfaces), bumps where it grazed a surface, specks of noise, furniture legs and shelves, and
unknown cells wherever the laser never looked (inside walls and furniture, behind closed walls,
outside the building). ``degrade`` applies those, in this order, to any world, deterministic per
``seed`` (an RNG stream of its own, ``[seed, 37]``, apart from the generators'):

1. ``resolution``: resample to finer cells (``None`` keeps the world's; coarser is refused).
2. ``thin`` (m): walls (obstacle runs at most ``MAX_WALL`` across, longer along, free on both
   sides) keep their middle ``thin`` m; wall ends, junctions and doorways stay where they were.
3. ``unknown`` (probability per region): free regions the robot can never reach (no cell of the
   C-space region of any start touches them: shafts, outside the building) are filled.
4. ``broken`` (holes per metre of wall): holes ``MIN_GAP``-``MAX_GAP`` long through a wall, at
   least two cells from its ends; a robot (0.67 m) or a ball (0.5 m) never passes one, and on the
   C-space grid (0.3 m inflation) no hole joins two regions, so no way round a door opens.
5. ``clutter`` (pieces per m² of floor): groups of four ``LEG`` m posts (chairs, tables) and
   solid shelves 0.3-0.45 m deep against walls.
6. ``bumps`` (probability per cell of wall surface): one-cell bumps on obstacle faces.
7. ``speckle`` (specks per m² of free floor): isolated occupied cells.
8. ``unknown`` again: obstacle cells deeper than ``SURFACE`` m inside an obstacle.

**Unknown cells are obstacles.** curlnav's occupancy is boolean and reads a map_server ``-1`` as
an obstacle (``curlnav.worlds.core.world``), so an unknown cell here is an obstacle cell in
``World.occupancy``, and ``SlamLayers.unknown`` says which: ``SlamLayers.values`` gives the
``OccupancyGrid`` values (0, 100, -1) a SLAM stack would publish. Unknown only ever covers
obstacle interiors (already obstacles) and free cells the robot cannot reach, so the physics has
a wall wherever the building has one, and no cell the robot can drive in turns solid.

**Tasks stay valid.** Additions (clutter, bumps, specks) keep out of the door swings, the balls,
the starts and goals, and the C-space band of each pair's shortest path (``world_paths``, its
0.15 m cells inflated by the C-space radius plus one cell), so each path stays open on the
0.15 m C-space grid and on the world's own; an addition that would fall there is skipped.
Removals (thinning, holes) open nothing a robot fits through. ``degrade`` then checks that every
pair is still connected on both C-space grids with the doors open, and that a pair the source
could not do with its doors closed still cannot (``WorldError`` otherwise: a bug, not bad luck).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from curlnav.worlds.core.world import World, WorldError
from curlnav.worlds.difficulty.metrics import inflate
from curlnav.worlds.difficulty.rank import CSPACE_RADIUS_M, METRIC_RESOLUTION, resample, world_paths
from curlnav.worlds.procedural.namo import closed_door_grid

MAX_WALL = 0.45  # m across: a thicker obstacle is furniture or a block, never thinned or holed
MIN_GAP, MAX_GAP = 0.1, 0.25  # m, a hole's length along its wall (a robot is 0.67 m wide, a ball 0.5 m)
SURFACE = 0.1  # m of an obstacle's surface a laser maps; deeper cells are unknown
LEG = 0.05  # m, a chair or table leg
SHELF_SHARE = 0.3  # of clutter pieces, the share that are shelves (the rest leg groups)
DOOR_KEEP_OUT = 0.15  # m beyond a door's swing, no addition
BALL_KEEP_OUT = 0.15  # m beyond a ball's edge
START_KEEP_OUT = 0.8  # m around a start (the Husky's half-diagonal is 0.6 m)
GOAL_KEEP_OUT = 0.5  # m around a goal
PATH_KEEP_OUT_CELLS = int(round(CSPACE_RADIUS_M / METRIC_RESOLUTION)) + 1  # 0.15 m cells around each pair's path
RNG_STREAM = 37  # the degradations' RNG is np.random.default_rng([seed, RNG_STREAM])
EIGHT = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class SlamLayers:
    """What ``degrade`` did, per cell of the degraded grid (bool arrays of its shape)."""

    source: np.ndarray  # the source's occupancy on the degraded grid
    thinned: np.ndarray  # wall cells removed to thin walls
    gaps: np.ndarray  # wall cells removed as holes
    voids: np.ndarray  # free cells no robot reaches, filled (unknown)
    clutter: np.ndarray  # legs and shelves added
    bumps: np.ndarray  # bumps added on obstacle faces
    speckles: np.ndarray  # isolated specks added
    unknown: np.ndarray  # cells a SLAM map marks unknown: voids and obstacle interiors (all obstacles)
    keep_clear: np.ndarray  # cells no addition may take: door swings, balls, starts, goals, pair paths

    @property
    def added(self) -> np.ndarray:
        return self.voids | self.clutter | self.bumps | self.speckles

    @property
    def removed(self) -> np.ndarray:
        return self.thinned | self.gaps

    def values(self, occupancy: np.ndarray) -> np.ndarray:
        """The ``OccupancyGrid`` values of the degraded map (int8, its shape): 0 free, 100
        occupied, -1 unknown."""
        out = np.where(occupancy, 100, 0).astype(np.int8)
        out[self.unknown] = -1
        return out


def degrade(world: World, seed: int = 0, *, resolution: float | None = None, thin: float = 0.1,
            broken: float = 0.1, speckle: float = 0.1, unknown: float = 1.0, bumps: float = 0.08,
            clutter: float = 0.03) -> World:
    """``world`` as a SLAM map of it (see the module docstring); lengths in m, densities per m or
    m², ``unknown`` and ``bumps`` probabilities. 0 turns a degradation off."""
    return degrade_layers(world, seed, resolution=resolution, thin=thin, broken=broken, speckle=speckle,
                          unknown=unknown, bumps=bumps, clutter=clutter)[0]


def degrade_layers(world: World, seed: int = 0, *, resolution: float | None = None, thin: float = 0.1,
                   broken: float = 0.1, speckle: float = 0.1, unknown: float = 1.0, bumps: float = 0.08,
                   clutter: float = 0.03) -> tuple[World, SlamLayers]:
    """``degrade``, and the layers of what it changed."""
    for name, value in (("thin", thin), ("broken", broken), ("speckle", speckle), ("clutter", clutter)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"degrade: {name} must be a number >= 0, got {value}")
    for name, value in (("unknown", unknown), ("bumps", bumps)):
        if not 0 <= value <= 1:
            raise ValueError(f"degrade: {name} is a probability in [0, 1], got {value}")
    res = world.resolution if resolution is None else float(resolution)
    if not (math.isfinite(res) and 0 < res <= world.resolution + 1e-12):
        raise ValueError(f"degrade: resolution must be positive and at most the world's {world.resolution:g} m, "
                         f"got {resolution}")
    rng = np.random.default_rng([seed, RNG_STREAM])
    source = resample(world.occupancy, world.resolution, res)
    fine = world.with_changes(occupancy=source, resolution=res)
    keep = keep_clear(world, fine)
    grid = source.copy()
    thinned = _thin(grid, max(1, int(round(thin / res))), _cells(MAX_WALL, res)) if thin > 0 else _none(grid)
    grid &= ~thinned
    voids = _voids(fine.with_changes(occupancy=grid), rng, unknown)
    grid |= voids
    gaps = _gaps(grid, keep_clear(world, fine, objects=False), rng, broken, res)
    grid &= ~gaps
    added = _clutter(grid, keep, rng, clutter, res)
    grid |= added
    rim = ndimage.binary_dilation(grid) & ~grid & ~keep & ~ndimage.binary_dilation(gaps, EIGHT)
    bump = rim & (rng.random(grid.shape) < bumps)
    grid |= bump
    specks = _speckles(grid, keep, rng, speckle, res)
    grid |= specks
    interiors = _regions(grid & (ndimage.distance_transform_edt(grid) > _cells(SURFACE, res)), rng, unknown)
    out = world.with_changes(occupancy=grid, resolution=res, source=f"{world.source} degraded seed={seed}")
    check_pairs_kept(world, out)
    return out, SlamLayers(source, thinned, gaps, voids, added, bump, specks, voids | interiors, keep)


def _cells(metres: float, res: float) -> int:
    return max(1, int(round(metres / res)))


def _none(grid: np.ndarray) -> np.ndarray:
    return np.zeros_like(grid, dtype=bool)


# -- where nothing may be added -------------------------------------------------------------
def keep_clear(world: World, fine: World, objects: bool = True) -> np.ndarray:
    """Cells of ``fine`` (``world`` resampled) no addition may take: door swings and, with
    ``objects``, balls, starts, goals and the band of each fixed pair's shortest path (see the
    module docstring)."""
    rows, cols = fine.occupancy.shape
    res = fine.resolution
    u = (np.arange(cols) + 0.5) * res
    v = (np.arange(rows) + 0.5) * res
    keep = np.zeros((rows, cols), dtype=bool)

    def disc(x: float, y: float, radius: float) -> None:
        cu, cv = fine.grid_from_map(x, y)
        reach = radius + res
        c0, c1 = max(int((cu - reach) / res), 0), min(int((cu + reach) / res) + 1, cols)
        r0, r1 = max(int((cv - reach) / res), 0), min(int((cv + reach) / res) + 1, rows)
        if r0 < r1 and c0 < c1:
            keep[r0:r1, c0:c1] |= np.hypot(u[None, c0:c1] - cu, v[r0:r1, None] - cv) <= radius + res * math.sqrt(0.5)

    for door in world.doors:
        disc(door.hinge_x, door.hinge_y, door.width + DOOR_KEEP_OUT)
    if not objects:
        return keep
    for ball in world.balls:
        disc(ball.x, ball.y, ball.radius + BALL_KEEP_OUT)
    for pair in world.pairs:
        disc(pair.x, pair.y, START_KEEP_OUT)
        disc(pair.gx, pair.gy, GOAL_KEEP_OUT)
    if world.pairs:
        # an added cell lands in one 0.15 m cell of the metric grid (resample's rule); kept out of
        # the C-space reach of every path cell, it cannot block that path
        coarse = resample(world.occupancy, world.resolution, METRIC_RESOLUTION)
        on_path = np.zeros_like(coarse)
        for path in world_paths(world)[1]:
            on_path[path[:, 0], path[:, 1]] = True
        band = inflate(on_path, PATH_KEEP_OUT_CELLS)
        r = np.minimum((np.arange(rows) * res / METRIC_RESOLUTION).astype(int), band.shape[0] - 1)
        c = np.minimum((np.arange(cols) * res / METRIC_RESOLUTION).astype(int), band.shape[1] - 1)
        keep |= band[np.ix_(r, c)]
    return keep


# -- runs of obstacle cells -----------------------------------------------------------------
def obstacle_runs(occupancy: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell, for the run of obstacle cells along ``axis`` (0: rows, i.e. along y; 1: along x)
    that holds it: its length (cells), the cell's index in it, and whether free cells bound it at
    both ends (not the map's edge). Zeros and False on free cells."""
    a = np.asarray(occupancy, dtype=bool)
    if axis == 0:
        return tuple(x.T for x in obstacle_runs(a.T, 1))
    cols = a.shape[1]
    idx = np.broadcast_to(np.arange(cols), a.shape)
    before = np.zeros_like(a)
    before[:, 1:] = a[:, :-1]
    after = np.zeros_like(a)
    after[:, :-1] = a[:, 1:]
    start = np.maximum.accumulate(np.where(a & ~before, idx, 0), axis=1)
    end = np.minimum.accumulate(np.where(a & ~after, idx, cols)[:, ::-1], axis=1)[:, ::-1]
    length = np.where(a, end - start + 1, 0)
    index = np.where(a, idx - start, 0)
    bounded = a & (start > 0) & (end < cols - 1)
    return length, index, bounded


def wall_cells(occupancy: np.ndarray, max_cells: int) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """Cells of walls along x (``across`` runs along y at most ``max_cells`` long and bounded by
    free cells, the run along x longer) and along y (the same turned), with the runs of both
    axes: ``(along_x, along_y, runs_y, runs_x)``."""
    runs_y, runs_x = obstacle_runs(occupancy, 0), obstacle_runs(occupancy, 1)
    along_x = runs_y[2] & (runs_y[0] <= max_cells) & (runs_x[0] > max_cells)
    along_y = runs_x[2] & (runs_x[0] <= max_cells) & (runs_y[0] > max_cells)
    return along_x, along_y, runs_y, runs_x


def wall_thickness(occupancy: np.ndarray, resolution: float) -> np.ndarray:
    """The thickness (m) of every wall cross-section of ``occupancy`` (one value per cell along
    each wall; walls as in ``wall_cells``, up to ``MAX_WALL``): what a histogram of wall
    thickness is made of."""
    along_x, along_y, runs_y, runs_x = wall_cells(occupancy, _cells(MAX_WALL, resolution))
    return np.concatenate([runs_y[0][along_x & (runs_y[1] == 0)], runs_x[0][along_y & (runs_x[1] == 0)]]) * resolution


def _thin(grid: np.ndarray, keep_cells: int, max_cells: int) -> np.ndarray:
    """Wall cells outside each wall's middle ``keep_cells``: those to remove."""
    along_x, along_y, runs_y, runs_x = wall_cells(grid, max_cells)
    remove = np.zeros_like(grid)
    for wall, (length, index, _) in ((along_x, runs_y), (along_y, runs_x)):
        low = (length - keep_cells) // 2
        remove |= wall & (length > keep_cells) & ((index < low) | (index >= low + keep_cells))
    return remove


# -- the degradations ----------------------------------------------------------------------
def _regions(mask: np.ndarray, rng: np.random.Generator, probability: float) -> np.ndarray:
    """The 8-connected regions of ``mask``, each kept with ``probability``."""
    if probability <= 0 or not mask.any():
        return _none(mask)
    labels, count = ndimage.label(mask, structure=EIGHT)
    chosen = np.concatenate([[False], rng.random(count) < probability])
    return chosen[labels]


def _voids(world: World, rng: np.random.Generator, probability: float) -> np.ndarray:
    """Free regions no robot reaches: 8-connected free regions with no cell of the C-space region
    of a start (of any C-space region for a world that draws random pairs), no ball and no
    hinge; each filled with ``probability``."""
    grid = world.occupancy
    free_labels, _ = ndimage.label(~grid, structure=EIGHT)
    cs_free = ~inflate(grid, int(round(CSPACE_RADIUS_M / world.resolution)))
    if world.pairs and world.random_pairs is None:
        cs_labels, _ = ndimage.label(cs_free, structure=EIGHT)
        starts = [cs_labels[world.cell_of(p.x, p.y)] for p in world.pairs]
        reach = np.isin(cs_labels, [s for s in starts if s])
    else:
        reach = cs_free
    seen = set(np.unique(free_labels[reach]).tolist())
    rows, cols = grid.shape
    for x, y in [(b.x, b.y) for b in world.balls] + [(d.hinge_x, d.hinge_y) for d in world.doors]:
        iy, ix = world.cell_of(x, y)
        if 0 <= iy < rows and 0 <= ix < cols:
            seen.add(int(free_labels[iy, ix]))
    void = ~grid & ~np.isin(free_labels, sorted(seen))
    return _regions(void, rng, probability)


def _gaps(grid: np.ndarray, keep: np.ndarray, rng: np.random.Generator, per_metre: float, res: float) -> np.ndarray:
    """Holes through walls, ``per_metre`` of wall on average (see the module docstring); none in a
    door swing."""
    along_x, along_y, runs_y, runs_x = wall_cells(grid, _cells(MAX_WALL, res))
    sections = [(along_x & (runs_y[1] == 0)), (along_y & (runs_x[1] == 0))]  # a wall's first cell across
    length_m = (sections[0].sum() + sections[1].sum()) * res
    count = int(rng.poisson(per_metre * length_m)) if per_metre > 0 else 0
    gaps = _none(grid)
    if not count:
        return gaps
    starts = np.argwhere(sections[0] | sections[1])
    lo, hi = _cells(MIN_GAP, res), max(_cells(MIN_GAP, res), int(math.floor(MAX_GAP / res + 1e-9)))
    margin = 2
    rows, cols = grid.shape
    for k in rng.permutation(len(starts))[:count]:
        r, c = (int(v) for v in starts[k])
        horizontal = bool(sections[0][r, c])  # a wall along x: the hole runs along x
        span = int(rng.integers(lo, hi + 1))
        wall, (length, index, _) = (along_x, runs_y) if horizontal else (along_y, runs_x)
        cells = []
        for t in range(-margin, span + margin):
            rr, cc = (r, c + t) if horizontal else (r + t, c)
            if not (0 <= rr < rows and 0 <= cc < cols) or not wall[rr, cc] or gaps[rr, cc]:
                break
            first = (rr - index[rr, cc], cc) if horizontal else (rr, cc - index[rr, cc])
            across = [(first[0] + i, cc) if horizontal else (rr, first[1] + i) for i in range(length[rr, cc])]
            if any(keep[p] or gaps[p] for p in across):
                break
            if 0 <= t < span:
                cells += across
        else:
            for p in cells:
                gaps[p] = True
    return gaps


def _clutter(grid: np.ndarray, keep: np.ndarray, rng: np.random.Generator, per_m2: float, res: float) -> np.ndarray:
    """Leg groups (chairs 0.4-0.5 m, tables 0.7-1.6 x 0.6-0.9 m) on free floor and shelves
    (0.3-0.45 x 0.8-2.0 m) against walls, ``per_m2`` pieces per m² of free floor on average, each
    with a free cell all round it (but for a shelf's back) and none in ``keep``; a piece with no
    room after 20 tries is left out."""
    count = int(rng.poisson(per_m2 * (~grid).sum() * res * res)) if per_m2 > 0 else 0
    added = _none(grid)
    spots = np.argwhere(~grid & ~keep)
    for _ in range(count if len(spots) else 0):
        shelf = rng.random() < SHELF_SHARE
        for _ in range(20):
            r, c = (int(v) for v in spots[rng.integers(len(spots))])
            piece = _shelf(grid, r, c, rng, res) if shelf else _leg_group(r, c, rng, res)
            if piece is None:
                continue
            (r0, c0, r1, c1), back, cells = piece
            if _room(grid | added, keep, r0, c0, r1, c1, back):
                for rr0, cc0, rr1, cc1 in cells:
                    added[rr0:rr1, cc0:cc1] = True
                break
    return added


def _room(blocked: np.ndarray, keep: np.ndarray, r0: int, c0: int, r1: int, c1: int, back: tuple | None) -> bool:
    """``[r0, r1) x [c0, c1)`` on the map with a free cell all round it (but for the ``back``
    side of the ring: a shelf stands against a wall), and clear of ``keep``."""
    rows, cols = blocked.shape
    if r0 < 1 or c0 < 1 or r1 > rows - 1 or c1 > cols - 1:
        return False
    ring = blocked[r0 - 1:r1 + 1, c0 - 1:c1 + 1].copy()
    if back is not None:
        ring[back] = False
    return not ring.any() and not keep[r0:r1, c0:c1].any()


def _shelf(grid: np.ndarray, r: int, c: int, rng: np.random.Generator, res: float):
    """A shelf whose back lies along the wall next to free cell ``(r, c)`` (None when there is
    no wall there or it is shorter than the shelf): ``(box, back side of its ring, [box])``."""
    rows, cols = grid.shape
    depth, length = _cells(rng.uniform(0.3, 0.45), res), _cells(rng.uniform(0.8, 2.0), res)
    sides = [(dr, dc) for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))
             if 0 <= r + dr < rows and 0 <= c + dc < cols and grid[r + dr, c + dc]]
    if not sides:
        return None
    dr, dc = sides[int(rng.integers(len(sides)))]
    if dr:
        r0 = r if dr < 0 else r - depth + 1
        box, back, wall = (r0, c, r0 + depth, c + length), (0 if dr < 0 else -1, slice(None)), grid[r + dr, c:c + length]
    else:
        c0 = c if dc < 0 else c - depth + 1
        box, back, wall = (r, c0, r + length, c0 + depth), (slice(None), 0 if dc < 0 else -1), grid[r:r + length, c + dc]
    if len(wall) < length or not wall.all():
        return None
    return box, back, [box]


def _leg_group(r: int, c: int, rng: np.random.Generator, res: float):
    """A chair's or a table's four legs around ``(r, c)``: ``(box, None, [leg boxes])``."""
    chair = rng.random() < 0.5
    a, b = (rng.uniform(0.4, 0.5),) * 2 if chair else (rng.uniform(0.7, 1.6), rng.uniform(0.6, 0.9))
    h, w = (_cells(a, res), _cells(b, res)) if rng.random() < 0.5 else (_cells(b, res), _cells(a, res))
    leg = _cells(LEG, res)
    r0, c0 = r - h // 2, c - w // 2
    legs = [(lr, lc, lr + leg, lc + leg) for lr in (r0, r0 + h - leg) for lc in (c0, c0 + w - leg)]
    return (r0, c0, r0 + h, c0 + w), None, legs


def _speckles(grid: np.ndarray, keep: np.ndarray, rng: np.random.Generator, per_m2: float, res: float) -> np.ndarray:
    """``per_m2`` specks per m² of free floor on average, each one cell with only free cells
    round it, none in ``keep``."""
    specks = _none(grid)
    count = int(rng.poisson(per_m2 * (~grid).sum() * res * res)) if per_m2 > 0 else 0
    if not count:
        return specks
    alone = ~ndimage.binary_dilation(grid, EIGHT) & ~keep
    alone[[0, -1], :] = alone[:, [0, -1]] = False
    spots = np.flatnonzero(alone)
    if len(spots):
        specks.flat[rng.choice(spots, size=min(count, len(spots)), replace=False)] = True
    return specks


# -- the check ------------------------------------------------------------------------------
def _connected(world: World, doors_closed: bool, structure: np.ndarray) -> list[bool]:
    """Per pair of ``world``: start and goal in one region of the C-space grid (``structure``:
    4- or 8-connected)."""
    grid = closed_door_grid(world) if doors_closed else world.occupancy
    cs = inflate(grid, int(round(CSPACE_RADIUS_M / world.resolution)))
    labels, _ = ndimage.label(~cs, structure=structure)
    out = []
    for pair in world.pairs:
        s, g = labels[world.cell_of(pair.x, pair.y)], labels[world.cell_of(pair.gx, pair.gy)]
        out.append(bool(s) and s == g)
    return out


def check_pairs_kept(source: World, degraded: World) -> None:
    """``WorldError`` naming the pair when ``degraded`` lost a pair of ``source``: disconnected
    on its C-space grid (4-connected, doors open) or the 0.15 m one (``world_paths``), or
    connected with the doors closed where the source was not (8-connected: any way round)."""
    if not source.pairs:
        return
    four = ndimage.generate_binary_structure(2, 1)
    for pair, ok in zip(source.pairs, _connected(degraded, False, four)):
        if not ok:
            raise WorldError(f"{degraded.source}: pair {pair.name!r} is disconnected on the C-space grid")
    world_paths(degraded)  # MetricsError names the pair
    if source.doors:
        before, after = _connected(source, True, EIGHT), _connected(degraded, True, EIGHT)
        for pair, was, now in zip(source.pairs, before, after):
            if now and not was:
                raise WorldError(f"{degraded.source}: pair {pair.name!r} found a way round the closed doors")
