"""Seeded procedural world families, in curlnav's world format.

Every generator returns a ``World`` whose start/goal pairs are connected on the C-space grid
(the static map inflated by ``CSPACE_RADIUS_M`` at the world's resolution; doors count as
open). Same family, parameters and seed: same world, bit for bit.

Families: ``barn`` (the BARN benchmark's cellular automaton), ``barn-3x3`` (3 x 3 BARN blocks
scaled to 36 m, 8 balls re-placed every reset), ``t-maze`` (five rooms in a T joined by hinged
doors and narrow gates, one ball per room, curriculum pairs p1..p4), ``t-maze-doors`` (T-Mazes
that vary, whose pairs must push doors open: ``curlnav.worlds.procedural.tmaze``), and worlds with the
character of the paper's others: ``cave``, ``forest``, ``garage``, ``indoor``, ``office``,
``campus``, ``auditorium``; and ``slam-office``, a large office floor as a SLAM stack maps it
(0.05 m cells, ragged walls, furniture, noise: thousands of rectangles; ``curlnav.worlds.procedural.slam_like``).
The registry of every family's name is ``curlnav.worlds.families.FAMILIES`` (with ``generate``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from curlnav.worlds.core.world import Ball, Door, RandomPairs, Region, StartGoal, World
from curlnav.worlds.difficulty.metrics import GridGraph, inflate
from curlnav.worlds.procedural.namo import reachable

RESOLUTION = 0.15  # m per cell: BARN's, fine enough for doors and gates
CSPACE_RADIUS_M = 0.3  # m; BARN's 2 cells at 0.15 m


def cspace(world: World, radius_m: float = CSPACE_RADIUS_M) -> np.ndarray:
    return inflate(world.occupancy, int(round(radius_m / world.resolution)))


def _walled(rows: int, cols: int) -> np.ndarray:
    grid = np.zeros((rows, cols), dtype=bool)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = True
    return grid


def _cells(metres: float) -> int:
    return int(round(metres / RESOLUTION))


def _box(grid: np.ndarray, x0: float, y0: float, x1: float, y1: float, value: bool = True) -> None:
    grid[max(_cells(y0), 0):max(_cells(y1), 0), max(_cells(x0), 0):max(_cells(x1), 0)] = value


def _disc(grid: np.ndarray, x: float, y: float, r: float) -> None:
    rows, cols = grid.shape
    yy, xx = np.ogrid[:rows, :cols]
    grid[((xx + 0.5) * RESOLUTION - x) ** 2 + ((yy + 0.5) * RESOLUTION - y) ** 2 <= r * r] = True


def keep_largest_region(grid: np.ndarray, radius_m: float = CSPACE_RADIUS_M) -> np.ndarray:
    """Fill every free pocket that is not part of the largest C-space region, so that any two
    free cells the robot can stand on are connected."""
    cs = inflate(grid, int(round(radius_m / RESOLUTION)))
    labels, count = ndimage.label(~cs, structure=np.ones((3, 3)))
    if count <= 1:
        return grid
    sizes = ndimage.sum(np.ones_like(labels), labels, index=np.arange(1, count + 1))
    keep = labels == (1 + int(np.argmax(sizes)))
    # free cells within the robot radius of the kept region stay free
    near = ndimage.maximum_filter(keep.astype(np.uint8), size=2 * int(round(radius_m / RESOLUTION)) + 1) > 0
    out = grid.copy()
    out[~near & ~grid] = True
    return out


def choose_pairs(grid: np.ndarray, count: int, min_distance_m: float, rng: np.random.Generator,
                 prefix: str = "p", yaw_to_goal: bool = True) -> tuple[StartGoal, ...]:
    """``count`` random start/goal pairs on the largest C-space region, at least
    ``min_distance_m`` apart and connected by a shortest path (checked)."""
    cs = inflate(grid, int(round(CSPACE_RADIUS_M / RESOLUTION)))
    labels, n = ndimage.label(~cs, structure=np.ones((3, 3)))
    if n == 0:
        raise ValueError("the map has no free C-space cell")
    sizes = ndimage.sum(np.ones_like(labels), labels, index=np.arange(1, n + 1))
    cells = np.argwhere(labels == 1 + int(np.argmax(sizes)))
    graph = GridGraph(cs)
    pairs: list[StartGoal] = []
    for _ in range(50 * count):
        if len(pairs) == count:
            break
        s = cells[rng.integers(len(cells))]
        g = cells[rng.integers(len(cells))]
        if math.hypot(*(s - g)) * RESOLUTION < min_distance_m:
            continue
        if graph.shortest_paths([tuple(s)], [tuple(g)])[0] is None:
            continue
        sx, sy = (s[1] + 0.5) * RESOLUTION, (s[0] + 0.5) * RESOLUTION
        gx, gy = (g[1] + 0.5) * RESOLUTION, (g[0] + 0.5) * RESOLUTION
        yaw = math.atan2(gy - sy, gx - sx) if yaw_to_goal else float(rng.uniform(-math.pi, math.pi))
        pairs.append(StartGoal(f"{prefix}{len(pairs) + 1}", sx, sy, yaw, gx, gy))
    if len(pairs) < count:
        raise ValueError(f"found only {len(pairs)} of {count} connected pairs {min_distance_m} m apart")
    return tuple(pairs)


# -- BARN ------------------------------------------------------------------------------------
def barn_cellular_automaton(rng: np.random.Generator, fill_pct: float, smooth_iter: int, rows: int = 30,
                            cols: int = 30) -> np.ndarray:
    """BARN's generator: walls on the first and last row, random fill, then synchronous
    smoothing (>= 5 obstacle neighbours -> obstacle, <= 1 -> free). Outside the map counts as
    obstacle above and below the grid, not left or right."""
    grid = rng.random((rows, cols)) < fill_pct
    grid[0, :] = grid[-1, :] = True
    for _ in range(smooth_iter):
        padded = np.zeros((rows + 2, cols + 2), dtype=np.int32)
        padded[1:-1, 1:-1] = grid
        padded[0, :] = padded[-1, :] = 1  # above and below: obstacle; left and right: free
        neighbours = sum(padded[1 + dr:rows + 1 + dr, 1 + dc:cols + 1 + dc]
                         for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc)
        grid = np.where(neighbours >= 5, True, np.where(neighbours <= 1, False, grid))
    return grid


def _flood_4(free: np.ndarray) -> tuple[np.ndarray, int]:
    return ndimage.label(free, structure=np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]]))


def barn(seed: int = 0, fill_pct: float = 0.25, smooth_iter: int = 3, max_tries: int = 50_000) -> World:
    """One BARN world: 30 x 30 cells of 0.15 m; start on column 0, goal on column 29, both in
    the largest C-space region touching both edges; unconnected worlds are rejected and drawn
    again (``seed`` fixes the whole sequence)."""
    rng = np.random.default_rng(seed)
    for _ in range(max_tries):
        grid = barn_cellular_automaton(rng, fill_pct, smooth_iter)
        cs = inflate(grid, 2)
        labels, n = _flood_4(~cs)
        shared = sorted(set(labels[:, 0][labels[:, 0] > 0]) & set(labels[:, -1][labels[:, -1] > 0]),
                        key=lambda label: -int((labels == label).sum()))
        if not shared:
            continue
        region = shared[0]
        start_rows = np.nonzero(labels[:, 0] == region)[0]
        goal_rows = np.nonzero(labels[:, -1] == region)[0]
        start = (int(rng.choice(start_rows)), 0)
        goal = (int(rng.choice(goal_rows)), grid.shape[1] - 1)
        if GridGraph(cs).shortest_paths([start], [goal])[0] is None:
            continue
        pair = StartGoal("p1", (start[1] + 0.5) * RESOLUTION, (start[0] + 0.5) * RESOLUTION, 0.0,
                         (goal[1] + 0.5) * RESOLUTION, (goal[0] + 0.5) * RESOLUTION)
        return World(name=f"barn-{seed}", occupancy=grid, resolution=RESOLUTION, pairs=(pair,),
                     source=f"generated:barn seed={seed} fill_pct={fill_pct} smooth_iter={smooth_iter}")
    raise ValueError(f"no connected BARN world in {max_tries} tries (fill_pct={fill_pct})")


def barn_3x3(seed: int = 0, fill_pct: float = 0.2, smooth_iter: int = 4, size: float = 36.0, balls: int = 8,
             pairs: int = 9) -> World:
    """A 36 m x 36 m world of 3 x 3 BARN blocks, each scaled from 4.5 m to 12 m; inner block
    walls removed, a wall all round; 8 balls re-placed at random on every reset; random
    training pairs at least 8 m apart and 9 fixed pairs."""
    rng = np.random.default_rng(seed)
    n = _cells(size)
    coarse = np.zeros((90, 90), dtype=bool)
    for bi in range(3):
        for bj in range(3):
            block = barn_cellular_automaton(rng, fill_pct, smooth_iter)
            block[0, :] = block[-1, :] = False  # inner walls would cut the world into strips
            coarse[bi * 30:(bi + 1) * 30, bj * 30:(bj + 1) * 30] = block
    index = (np.arange(n) * 90 // n).clip(0, 89)
    grid = coarse[np.ix_(index, index)]
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = True
    grid = keep_largest_region(grid)
    fixed = choose_pairs(grid, pairs, 8.0, rng)
    region = Region(0.5, 0.5, size - 0.5, size - 0.5)
    ball_list = tuple(Ball(size / 2, size / 2, 0.3, 0.5, region=0) for _ in range(balls))
    return World(name=f"barn-3x3-{seed}", occupancy=grid, resolution=RESOLUTION, balls=ball_list, pairs=fixed,
                 ball_regions=(region,), random_pairs=RandomPairs(min_distance=8.0, clearance=0.6),
                 source=f"generated:barn-3x3 seed={seed}")


# -- T-maze ---------------------------------------------------------------------------------
def t_maze(seed: int = 0, room_width: float = 3.25, room_depth: float = 3.0, wall: float = 0.15,
           door_width: float = 1.1, gate_width: float = 0.9, ball_radius: float = 0.3) -> World:
    """Five rooms in a T, about 13 m x 6 m: four rooms in a row (R0..R3, the bar, on top) and
    one below R1 (the stem S). Neighbouring rooms are joined by a hinged door (very light, as
    the authors') or a narrow gate (0.9 m: 0.23 m wider than the Husky); which is which is
    drawn from ``seed``. One ball per room, re-placed inside its room on every reset.

    Curriculum pairs p1..p4, sorted by start-goal distance (the paper's order): R0->R1 (2 rooms,
    4.5 m), S->R2 (3 rooms with a turn, 5.2 m), R1->R3 (3 rooms, 7.7 m), S->R3 (4 rooms with a
    turn, 7.9 m). Every 4-room route has the turn, as in the authors' T (three rooms in a row, two
    above the middle one): a straight run through the whole bar (R0->R3) would be a 4-room task
    that a policy memorises from scratch in about 70k steps (measured), not the hardest step.
    Doors open away from the start of every pair.
    """
    rng = np.random.default_rng(seed)
    width, height = 4 * room_width, 2 * room_depth
    grid = _walled(_cells(height), _cells(width))
    # every cell below the bar is solid except the stem room
    _box(grid, 0, 0, room_width, room_depth)
    _box(grid, 2 * room_width, 0, width, room_depth)
    _box(grid, room_width - wall / 2, 0, room_width + wall / 2, room_depth)  # stem walls
    _box(grid, 2 * room_width - wall / 2, 0, 2 * room_width + wall / 2, room_depth)
    _box(grid, room_width, room_depth - wall / 2, 2 * room_width, room_depth + wall / 2)  # stem / bar wall
    _box(grid, 0, room_depth - wall / 2, room_width, room_depth + wall / 2)
    _box(grid, 2 * room_width, room_depth - wall / 2, width, room_depth + wall / 2)
    for k in (1, 2, 3):  # walls between bar rooms
        _box(grid, k * room_width - wall / 2, room_depth, k * room_width + wall / 2, height)
    doors = []
    kinds = ["door" if rng.random() < 0.5 else "gate" for _ in range(4)]
    kinds[0], kinds[2] = "door", "gate"  # at least one of each
    y_mid = room_depth + room_depth / 2
    for k, kind in zip((1, 2, 3), kinds[:3]):  # vertical walls of the bar: gap centred on the room
        gap = door_width if kind == "door" else gate_width
        y0 = y_mid - gap / 2
        _box(grid, k * room_width - wall / 2 - 0.01, y0, k * room_width + wall / 2 + 0.01, y0 + gap, value=False)
        if kind == "door":
            doors.append(Door(hinge_x=k * room_width, hinge_y=y0, width=gap - 0.04, closed_angle=math.pi / 2,
                              swing="right", mass=0.5, hinge_friction=0.2))
    # stem -> R1 through the horizontal wall at y = room_depth; travel is upward (+y)
    kind = kinds[3]
    gap = door_width if kind == "door" else gate_width
    x0 = room_width + room_width / 2 - gap / 2
    _box(grid, x0, room_depth - wall / 2 - 0.01, x0 + gap, room_depth + wall / 2 + 0.01, value=False)
    if kind == "door":
        # hinge on the left end, closed along +x; pushed from below it turns counter-clockwise
        doors.append(Door(hinge_x=x0, hinge_y=room_depth, width=gap - 0.04, closed_angle=0.0, swing="left",
                          mass=0.5, hinge_friction=0.2))
    rooms = {
        "R0": (0, room_depth, room_width, height), "R1": (room_width, room_depth, 2 * room_width, height),
        "R2": (2 * room_width, room_depth, 3 * room_width, height), "R3": (3 * room_width, room_depth, width, height),
        "S": (room_width, 0, 2 * room_width, room_depth),
    }
    margin = wall + ball_radius + 0.2
    regions = tuple(Region(x0 + margin, y0 + margin, x1 - margin, y1 - margin) for x0, y0, x1, y1 in rooms.values())
    balls = tuple(Ball((r.x_min + r.x_max) / 2, (r.y_min + r.y_max) / 2, ball_radius, 0.1, region=i)
                  for i, r in enumerate(regions))

    def centre(name: str, dx: float = 0.0) -> tuple[float, float]:
        x0, y0, x1, y1 = rooms[name]
        return (x0 + x1) / 2 + dx, (y0 + y1) / 2

    routes = [("R0", "R1", 0.0), ("S", "R2", math.pi / 2), ("R1", "R3", 0.0), ("S", "R3", math.pi / 2)]
    candidates = []
    for a, b, yaw in routes:
        (sx, sy), (gx, gy) = centre(a, -0.6 if a != "S" else 0.0), centre(b, 0.6)
        if a == "S":
            sy -= 0.5
        candidates.append((math.hypot(gx - sx, gy - sy), sx, sy, yaw, gx, gy))
    candidates.sort()
    pairs = tuple(StartGoal(f"p{i + 1}", sx, sy, yaw, gx, gy, step=i + 1)
                  for i, (_, sx, sy, yaw, gx, gy) in enumerate(candidates))
    return World(name=f"t-maze-{seed}", occupancy=grid, resolution=RESOLUTION, balls=balls, doors=tuple(doors),
                 pairs=pairs, ball_regions=regions, source=f"generated:t-maze seed={seed}")


# -- families with the character of the paper's other worlds ------------------------------------
def cave(seed: int = 0, width: float = 60.0, height: float = 48.0, tunnels: int = 6, tunnel_width: float = 3.0,
         pairs: int = 10) -> World:
    """Wide winding tunnels carved by random walkers in solid rock (SubT-like)."""
    rng = np.random.default_rng(seed)
    grid = np.ones((_cells(height), _cells(width)), dtype=bool)
    x, y = width / 2, height / 2
    for _ in range(tunnels):
        heading = rng.uniform(-math.pi, math.pi)
        for _ in range(int(2 * (width + height) / tunnel_width)):
            r = tunnel_width / 2 * rng.uniform(0.8, 1.4)
            free = np.zeros_like(grid)
            _disc(free, x, y, r)
            grid &= ~free
            heading += rng.normal(0, 0.35)
            x = float(np.clip(x + math.cos(heading) * tunnel_width * 0.6, 3, width - 3))
            y = float(np.clip(y + math.sin(heading) * tunnel_width * 0.6, 3, height - 3))
        x, y = rng.uniform(5, width - 5), rng.uniform(5, height - 5)  # the next tunnel starts elsewhere
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = True
    grid = keep_largest_region(grid)
    return _finish("cave", seed, grid, pairs, min_distance=12.0)


def forest(seed: int = 0, size: float = 40.0, trees_per_100m2: float = 2.5, pairs: int = 10) -> World:
    """An open field of trees (trunks 0.2-0.5 m in radius) at a given density."""
    rng = np.random.default_rng(seed)
    grid = _walled(_cells(size), _cells(size))
    count = int(trees_per_100m2 * size * size / 100)
    for _ in range(count):
        _disc(grid, rng.uniform(1.5, size - 1.5), rng.uniform(1.5, size - 1.5), rng.uniform(0.2, 0.5))
    return _finish("forest", seed, keep_largest_region(grid), pairs, min_distance=12.0)


def garage(seed: int = 0, width: float = 40.0, height: float = 60.0, pillar_spacing: float = 7.0,
           pairs: int = 10) -> World:
    """A pillared parking hall: square pillars on a regular grid, a few partition walls."""
    rng = np.random.default_rng(seed)
    grid = _walled(_cells(height), _cells(width))
    for x in np.arange(pillar_spacing, width - 1, pillar_spacing):
        for y in np.arange(pillar_spacing, height - 1, pillar_spacing):
            _box(grid, x - 0.35, y - 0.35, x + 0.35, y + 0.35)
    for _ in range(3):
        y = float(rng.choice(np.arange(pillar_spacing, height - 1, pillar_spacing)))
        x0 = rng.uniform(0, width / 2)
        _box(grid, x0, y - 0.1, x0 + rng.uniform(6, width / 2), y + 0.1)
    return _finish("garage", seed, keep_largest_region(grid), pairs, min_distance=15.0)


def indoor(seed: int = 0, width: float = 48.0, height: float = 40.0, corridor: float = 2.2, room: float = 6.0,
           pairs: int = 10, name: str = "indoor") -> World:
    """Long corridors joining lobbies, rooms on both sides of each corridor, doorways."""
    rng = np.random.default_rng(seed)
    grid = np.ones((_cells(height), _cells(width)), dtype=bool)
    rows_y = np.arange(room + corridor / 2 + 1, height - room, 2 * room + corridor)
    for cy in rows_y:  # horizontal corridors with rooms above and below
        _box(grid, 1, cy - corridor / 2, width - 1, cy + corridor / 2, value=False)
        for x in np.arange(1, width - room, room):
            for side in (-1, 1):
                y0 = cy + corridor / 2 + 0.15 if side > 0 else cy - corridor / 2 - room + 0.15
                _box(grid, x + 0.15, y0, x + room - 0.15, y0 + room - 0.3, value=False)
                if rng.random() < 0.8:  # a doorway into the corridor
                    dx = rng.uniform(0.8, room - 2.0)
                    dy0 = cy + corridor / 2 - 0.05 if side > 0 else cy - corridor / 2 - 0.25
                    _box(grid, x + dx, dy0, x + dx + 1.2, dy0 + 0.3, value=False)
    _box(grid, 1, 1, corridor + 1, height - 1, value=False)  # a spine corridor joins them
    for cy in rows_y[::2]:  # lobbies where the spine meets a corridor
        _box(grid, 1, cy - 3, 8, cy + 3, value=False)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = True
    return _finish(name, seed, keep_largest_region(grid), pairs, min_distance=10.0)


def office(seed: int = 0, pairs: int = 6) -> World:
    """A smaller, tighter ``indoor``: 30 m x 18 m, narrower corridors, smaller rooms."""
    return indoor(seed, width=30.0, height=18.0, corridor=1.6, room=4.0, pairs=pairs, name="office")


def campus(seed: int = 0, width: float = 90.0, height: float = 80.0, block: float = 16.0, street: float = 8.0,
           pairs: int = 10) -> World:
    """Building blocks on a street grid, with courtyards and plazas."""
    rng = np.random.default_rng(seed)
    grid = _walled(_cells(height), _cells(width))
    for x in np.arange(street, width - block, block + street):
        for y in np.arange(street, height - block, block + street):
            if rng.random() < 0.15:
                continue  # a plaza
            w, h = rng.uniform(0.6, 1.0) * block, rng.uniform(0.6, 1.0) * block
            _box(grid, x, y, x + w, y + h)
            if rng.random() < 0.4:  # courtyard with an entrance
                _box(grid, x + 2, y + 2, x + w - 2, y + h - 2, value=False)
                _box(grid, x + w / 2 - 1, y, x + w / 2 + 1, y + 2, value=False)
    return _finish("campus", seed, keep_largest_region(grid), pairs, min_distance=25.0)


def auditorium(seed: int = 0, width: float = 40.0, height: float = 25.0, tiers: int = 7, pairs: int = 6) -> World:
    """A tiered hall: arcs of seating around a stage, broken by aisles, entered through a
    corridor with bends."""
    rng = np.random.default_rng(seed)
    grid = _walled(_cells(height), _cells(width))
    rows, cols = grid.shape
    yy, xx = np.mgrid[:rows, :cols]
    px, py = (xx + 0.5) * RESOLUTION, (yy + 0.5) * RESOLUTION
    stage = (width * 0.45, 2.0)
    radius = np.hypot(px - stage[0], py - stage[1])
    angle = np.degrees(np.arctan2(py - stage[1], px - stage[0]))
    aisles = [float(a) for a in rng.uniform(35, 145, 3)]
    for k in range(tiers):
        r0 = 5.0 + 2.0 * k
        seat = (radius >= r0) & (radius < r0 + 0.6) & (px < width * 0.8)
        for a in aisles:
            seat &= np.abs(angle - a) > 4.0
        grid |= seat
    # the entrance corridor with two bends, on the right
    _box(grid, width * 0.8, 0, width * 0.8 + 0.3, height * 0.7)
    _box(grid, width * 0.8 + 3.0, height * 0.3, width, height * 0.3 + 0.3)
    _box(grid, width * 0.8 + 0.3, height * 0.6, width - 3.0, height * 0.6 + 0.3)
    _box(grid, width * 0.8, height * 0.15, width * 0.8 + 0.3, height * 0.15 + 1.4, value=False)
    return _finish("auditorium", seed, keep_largest_region(grid), pairs, min_distance=10.0)


def dead_end(seed: int = 0, width: float = 22.0, height: float = 16.0, pairs: int = 4, clutter: int = 6) -> World:
    """A U-shaped wall between start and goal, its mouth towards the start: the straight line to
    the goal leads into the U, whose back wall (0.3 m thick) stands between the robot and the goal,
    and the way round is out of the mouth again. Mouth 2.4-4.0 m wide, U 2.5-5.0 m deep; ``clutter``
    trees (radius 0.2-0.4 m) stand clear of the U and of the pairs. Each pair starts 1.5-4 m before
    the mouth, facing the goal, and ends 2-4 m behind the back wall (so a policy that only follows
    the goal's bearing drives into the U, and a policy that remembers no wall turns back into it)."""
    rng = np.random.default_rng(seed)
    grid = _walled(_cells(height), _cells(width))
    mouth, depth, wall = rng.uniform(2.4, 4.0), rng.uniform(2.5, 5.0), 0.3
    y_mid = height / 2 + rng.uniform(-1.5, 1.5)
    x_back = width / 2 + rng.uniform(-1.0, 2.0)  # the back wall's inner face
    x_mouth = x_back - depth
    _box(grid, x_back, y_mid - mouth / 2 - wall, x_back + wall, y_mid + mouth / 2 + wall)  # back wall
    for side in (-1, 1):  # the two arms, from the mouth to the back wall
        y_in = y_mid + side * mouth / 2
        _box(grid, x_mouth, min(y_in, y_in + side * wall), x_back, max(y_in, y_in + side * wall))
    chosen: list[StartGoal] = []
    for _ in range(100 * pairs):
        if len(chosen) == pairs:
            break
        sx, sy = x_mouth - rng.uniform(1.5, 4.0), y_mid + rng.uniform(-0.25, 0.25) * mouth
        gx, gy = x_back + wall + rng.uniform(2.0, 4.0), y_mid + rng.uniform(-0.25, 0.25) * mouth
        if min(sx, gx) < 1.0 or max(sx, gx) > width - 1.0:
            continue
        chosen.append(StartGoal(f"p{len(chosen) + 1}", sx, sy, math.atan2(gy - sy, gx - sx), gx, gy))
    trees = 0
    for _ in range(50 * clutter):  # clear of the U (1.5 m round it) and of every start and goal (2 m)
        if trees == clutter:
            break
        x, y, r = rng.uniform(1.5, width - 1.5), rng.uniform(1.5, height - 1.5), rng.uniform(0.2, 0.4)
        if (x_mouth - 1.5 < x < x_back + wall + 1.5 and abs(y - y_mid) < mouth / 2 + wall + 1.5) or any(
                math.hypot(x - px, y - py) < 2.0 for p in chosen for px, py in ((p.x, p.y), (p.gx, p.gy))):
            continue
        _disc(grid, x, y, r)
        trees += 1
    world = World(name=f"dead-end-{seed}", occupancy=grid, resolution=RESOLUTION, pairs=tuple(chosen),
                  source=f"generated:dead-end seed={seed}")
    for p in chosen:
        if not reachable(world, p):
            raise ValueError(f"dead-end seed {seed}: pair {p.name} is blocked (width {width} m, height {height} m)")
    return world


def _finish(family: str, seed: int, grid: np.ndarray, pairs: int, min_distance: float) -> World:
    rng = np.random.default_rng([seed, 1])
    chosen = choose_pairs(grid, pairs, min_distance, rng)
    return World(name=f"{family}-{seed}", occupancy=grid, resolution=RESOLUTION, pairs=chosen,
                 source=f"generated:{family} seed={seed}")
