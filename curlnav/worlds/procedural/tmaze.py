"""``t-maze-doors``: T-Mazes that vary, where the doors must be pushed open, not driven round.

A bar of ``rooms`` rooms in a row (3 to 5, drawn from the seed when 0), each 2.7-4.0 m wide and
2.6-3.6 m deep, and a stem room below one of the inner bar rooms. Neighbouring rooms are joined
by one opening each, at a random place along their wall: a hinged door (1.05-1.35 m gap) with
probability ``door_share``, else a narrow gate (0.9-1.05 m, no door); at least two openings are
doors. The rooms form a tree, so the only way between two rooms is through the openings between
them, and a closed door blocks it (``curlnav.worlds.procedural.namo.reachable(..., doors_closed=True)``).

A door turns one way only, so every door opens away from a root room drawn from the seed, with
its hinge at either end of its gap. A pair goes from one room to another crossing at least one
door, every door on its way the way it opens, gates either way; so no pair can be done without
pushing a door, and none asks for a pull. ``pairs`` (4) pairs p1..pN, sorted by the rooms they
cross then by start-goal distance (curriculum sub-steps 1..N, as the T-Maze's), start facing along
their shortest path. Each room holds a ball with probability ``ball_share``, re-placed inside its
room on every reset. Same parameters and seed: the same world, bit for bit.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from curlnav.worlds.core.pairs import HUSKY_FOOTPRINT, footprint_free
from curlnav.worlds.core.world import Ball, Door, Region, StartGoal, World
from curlnav.worlds.difficulty.metrics import GridGraph, inflate
from curlnav.worlds.difficulty.rank import CSPACE_RADIUS_M
from curlnav.worlds.procedural.namo import closed_door_grid, door_crossings

RESOLUTION = 0.15  # m per cell
WALL = 0.15  # m, nominal wall thickness
ROOM_WIDTH = (2.7, 4.0)  # m, along the bar
ROOM_DEPTH = (2.6, 3.6)  # m, across the bar (and the stem's depth)
DOOR_GAP = (1.05, 1.35)  # m; the panel is 4 cm shorter
GATE_GAP = (0.9, 1.05)  # m; the Husky is 0.67 m wide
BALL_RADIUS = 0.3  # m
ROOM_MARGIN = 0.7  # m from a room's walls to a start or goal
START_CLEAR_OF_DOOR = 0.45  # m beyond a door's swing for a start (the robot's half-length is 0.5 m)
GOAL_CLEAR_OF_DOOR = 0.3  # m beyond a door's swing for a goal


def _snap(metres: float) -> float:
    return round(metres / RESOLUTION) * RESOLUTION


def _fill(grid: np.ndarray, x0: float, y0: float, x1: float, y1: float, value: bool = True) -> None:
    """Every cell that overlaps ``[x0, x1] x [y0, y1]`` (m)."""
    r0, r1 = max(int(math.floor(y0 / RESOLUTION + 1e-9)), 0), int(math.ceil(y1 / RESOLUTION - 1e-9))
    c0, c1 = max(int(math.floor(x0 / RESOLUTION + 1e-9)), 0), int(math.ceil(x1 / RESOLUTION - 1e-9))
    grid[r0:r1, c0:c1] = value


def _swing(closed_angle: float, opens_toward: np.ndarray) -> str:
    """The swing (``left``: counter-clockwise) that moves the panel's tip toward ``opens_toward``."""
    left = np.array([-math.sin(closed_angle), math.cos(closed_angle)])
    return "left" if float(left @ opens_toward) > 0 else "right"


def t_maze_doors(seed: int = 0, rooms: int = 0, door_share: float = 0.6, ball_share: float = 0.8,
                 pairs: int = 4) -> World:
    """A varying T-Maze with doors to push; see the module docstring."""
    if rooms not in (0, 3, 4, 5):
        raise ValueError(f"rooms must be 3, 4 or 5 (0: drawn from the seed), got {rooms}")
    if not (0 <= door_share <= 1 and 0 <= ball_share <= 1) or pairs < 1:
        raise ValueError("door_share and ball_share are shares in [0, 1]; pairs >= 1")
    rng = np.random.default_rng([seed, 2])
    n = rooms or int(rng.integers(3, 6))
    widths = [_snap(rng.uniform(*ROOM_WIDTH)) for _ in range(n)]
    depth, stem_depth = _snap(rng.uniform(*ROOM_DEPTH)), _snap(rng.uniform(*ROOM_DEPTH))
    xs = np.concatenate([[0.0], np.cumsum(widths)])
    width, height = float(xs[-1]), stem_depth + depth
    k = int(rng.integers(1, n - 1))  # the bar room above the stem: an inner one, so the maze is a T
    grid = np.zeros((int(round(height / RESOLUTION)), int(round(width / RESOLUTION))), dtype=bool)
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = True
    _fill(grid, 0, 0, xs[k], stem_depth)  # solid below the bar, but for the stem
    _fill(grid, xs[k + 1], 0, width, stem_depth)
    _fill(grid, 0, stem_depth - WALL / 2, width, stem_depth + WALL / 2)
    for x in (xs[k], xs[k + 1]):
        _fill(grid, x - WALL / 2, 0, x + WALL / 2, stem_depth)
    for x in xs[1:-1]:
        _fill(grid, x - WALL / 2, stem_depth, x + WALL / 2, height)

    # rooms 0..n-1: the bar, west to east; room n: the stem. Openings: (room a, room b), a tree.
    boxes = [(xs[i], stem_depth, xs[i + 1], height) for i in range(n)] + [(xs[k], 0.0, xs[k + 1], stem_depth)]
    edges = [(i, i + 1) for i in range(n - 1)] + [(k, n)]
    is_door = [bool(rng.random() < door_share) for _ in edges]
    while sum(is_door) < 2:
        is_door[int(rng.integers(len(edges)))] = True
    root = int(rng.integers(n + 1))
    parent = _tree_parents(n + 1, edges, root)
    doors: list[Door] = []
    door_of_edge: dict[int, int] = {}
    for e, (a, b) in enumerate(edges):
        gap = _snap(rng.uniform(*(DOOR_GAP if is_door[e] else GATE_GAP)))
        child = b if parent[b] == a else a
        if e < n - 1:  # a wall along x = xs[b] between bar rooms a (west) and b (east)
            x = xs[b]
            y0 = _snap(rng.uniform(stem_depth + WALL + 0.1, height - WALL - 0.1 - gap))
            _fill(grid, x - WALL, y0, x + WALL, y0 + gap, value=False)
            ends, along = ((x, y0), (x, y0 + gap)), math.pi / 2
            toward = np.array([1.0 if child == b else -1.0, 0.0])
        else:  # the wall along y = stem_depth between bar room k (north) and the stem (south)
            x0 = _snap(rng.uniform(xs[k] + WALL + 0.1, xs[k + 1] - WALL - 0.1 - gap))
            _fill(grid, x0, stem_depth - WALL, x0 + gap, stem_depth + WALL, value=False)
            ends, along = ((x0, stem_depth), (x0 + gap, stem_depth)), 0.0
            toward = np.array([0.0, 1.0 if child == k else -1.0])
        if is_door[e]:
            hinge_at_low_end = bool(rng.random() < 0.5)
            hx, hy = ends[0] if hinge_at_low_end else ends[1]
            closed = along if hinge_at_low_end else along + math.pi
            closed = math.atan2(math.sin(closed), math.cos(closed))
            door_of_edge[e] = len(doors)
            doors.append(Door(hinge_x=round(float(hx), 6), hinge_y=round(float(hy), 6), width=round(gap - 0.04, 6),
                              closed_angle=round(closed, 9), swing=_swing(closed, toward), mass=0.5,
                              hinge_friction=0.2))
    margin = WALL / 2 + BALL_RADIUS + 0.2
    regions = tuple(Region(x0 + margin, y0 + margin, x1 - margin, y1 - margin) for x0, y0, x1, y1 in boxes)
    balls = tuple(Ball((r.x_min + r.x_max) / 2, (r.y_min + r.y_max) / 2, BALL_RADIUS, 0.1, region=i)
                  for i, r in enumerate(regions) if rng.random() < ball_share)
    world = World(name=f"t-maze-doors-{seed}", occupancy=grid, resolution=RESOLUTION, balls=balls,
                  doors=tuple(doors), ball_regions=regions,
                  source=f"generated:t-maze-doors seed={seed} rooms={n} door_share={door_share} ball_share={ball_share}")
    routes = _routes(n + 1, edges, parent, door_of_edge)
    return world.with_changes(pairs=_pairs(world, boxes, routes, pairs, rng))


def _tree_parents(count: int, edges: list[tuple[int, int]], root: int) -> list[int]:
    """Each room's neighbour toward ``root`` (``root``'s own: -1)."""
    links: dict[int, list[int]] = {i: [] for i in range(count)}
    for a, b in edges:
        links[a].append(b)
        links[b].append(a)
    parent = [-2] * count
    parent[root] = -1
    queue = deque([root])
    while queue:
        a = queue.popleft()
        for b in links[a]:
            if parent[b] == -2:
                parent[b] = a
                queue.append(b)
    return parent


def _routes(count: int, edges: list[tuple[int, int]], parent: list[int],
            door_of_edge: dict[int, int]) -> list[tuple[int, int, int]]:
    """``(start room, goal room, openings crossed)`` of every route that crosses at least one door
    and every door the way it opens (from the root's side)."""
    edge_index = {frozenset(e): i for i, e in enumerate(edges)}

    def up(a: int) -> list[int]:
        path = [a]
        while parent[path[-1]] >= 0:
            path.append(parent[path[-1]])
        return path

    out = []
    for a in range(count):
        for b in range(count):
            if a == b:
                continue
            pa, pb = up(a), up(b)
            meet = next(r for r in pa if r in pb)
            climb = pa[:pa.index(meet) + 1]  # a .. meet, crossed child -> parent: against the doors
            descend = pb[:pb.index(meet) + 1][::-1]  # meet .. b, crossed parent -> child: with them
            against = [edge_index[frozenset(p)] for p in zip(climb, climb[1:])]
            along = [edge_index[frozenset(p)] for p in zip(descend, descend[1:])]
            if any(e in door_of_edge for e in against) or not any(e in door_of_edge for e in along):
                continue
            out.append((a, b, len(against) + len(along)))
    return out


def _pairs(world: World, boxes: list[tuple[float, float, float, float]], routes: list[tuple[int, int, int]],
           count: int, rng: np.random.Generator) -> tuple[StartGoal, ...]:
    """``count`` pairs over ``routes``, spread from the shortest to the longest, each checked on
    the grid: reachable with the doors open, blocked with them closed, every door on its
    shortest path crossed the way it opens."""
    radius = int(round(CSPACE_RADIUS_M / RESOLUTION))
    open_cs = inflate(world.occupancy, radius)
    closed_cs = inflate(closed_door_grid(world), radius)
    open_graph, closed_graph = GridGraph(open_cs), GridGraph(closed_cs)
    routes = sorted(routes, key=lambda r: (r[2], r[0], r[1]))
    picks = [routes[int(round(i))] for i in np.linspace(0, len(routes) - 1, count)] if len(routes) > 1 else routes * count
    closed_world = world.with_changes(occupancy=closed_door_grid(world))
    found: list[tuple[int, float, float, float, float, float, float]] = []
    spare = [r for r in routes if r not in picks]
    refilled = False
    while picks and len(found) < count:
        a, b, crossed = picks.pop(0)
        pair = _pair_for_route(world, closed_world, boxes[a], boxes[b], (open_cs, closed_cs), (open_graph, closed_graph),
                               rng)
        if pair is not None:
            found.append((crossed, math.hypot(pair[3] - pair[0], pair[4] - pair[1]), *pair))
        elif spare:
            picks.append(spare.pop(0))  # a route with no room for a start and goal: another one
        if not picks and found and len(found) < count and not refilled:
            picks, refilled = list(routes), True  # more pairs on the routes that had room
    if len(found) < count:
        raise ValueError(f"{world.name}: found {len(found)} of {count} pairs through doors")
    found.sort()
    return tuple(StartGoal(f"p{i + 1}", sx, sy, yaw, gx, gy, step=i + 1)
                 for i, (_, _, sx, sy, yaw, gx, gy) in enumerate(found))


def _pair_for_route(world: World, closed_world: World, start_box, goal_box, grids, graphs,
                    rng: np.random.Generator) -> tuple[float, float, float, float, float] | None:
    """``(x, y, yaw, gx, gy)`` of a start in ``start_box`` and a goal in ``goal_box``, or None.
    Starts and goals keep clear of the door swings where the rooms leave room, else less so
    (a door that swings into the start room is one this pair never pushes)."""
    open_cs, closed_cs = grids
    open_graph, closed_graph = graphs
    for start_clear, goal_clear in ((START_CLEAR_OF_DOOR, GOAL_CLEAR_OF_DOOR), (0.0, 0.0), (-0.6, -0.6)):
        for _ in range(70):
            sx, sy = _point_in(start_box, rng)
            gx, gy = _point_in(goal_box, rng)
            if any(math.hypot(sx - d.hinge_x, sy - d.hinge_y) < d.width + start_clear for d in world.doors):
                continue
            if any(math.hypot(gx - d.hinge_x, gy - d.hinge_y) < d.width + goal_clear for d in world.doors):
                continue
            s, g = world.cell_of(sx, sy), world.cell_of(gx, gy)
            if open_cs[s] or open_cs[g] or closed_cs[s] or closed_cs[g]:
                continue
            path = open_graph.shortest_paths([s], [g], duplicate_start=False)[0]
            if path is None or closed_graph.shortest_paths([s], [g])[0] is not None:
                continue  # must be reachable with the doors open, and only then
            points = np.array([world.cell_centre(int(r), int(c)) for r, c in path])
            crossings = door_crossings(world, points)
            if not crossings or not all(forward for _, forward in crossings):
                continue
            ahead = points[min(len(points) - 1, int(round(1.0 / RESOLUTION)))]
            yaw = round(math.atan2(ahead[1] - sy, ahead[0] - sx), 6)
            if not footprint_free(closed_world, sx, sy, yaw, *HUSKY_FOOTPRINT, margin=0.1):
                continue
            return sx, sy, yaw, gx, gy
    return None


def _point_in(box: tuple[float, float, float, float], rng: np.random.Generator) -> tuple[float, float]:
    x0, y0, x1, y1 = box
    return (round(float(rng.uniform(x0 + ROOM_MARGIN, x1 - ROOM_MARGIN)), 3),
            round(float(rng.uniform(y0 + ROOM_MARGIN, y1 - ROOM_MARGIN)), 3))
