"""The five BARN navigation-difficulty metrics (Perille et al. 2020), vectorised.

Behaviour follows the BARN benchmark's own code, quirks included (see
``shared/reference/difficulty-metrics.md``). Units are grid cells. Grids are boolean or 0/1
arrays indexed ``[row, col]`` with True/1 = obstacle; outside the map is never an obstacle.

Per-cell maps are computed for the whole grid at once with shifted-array scans (no per-cell
Python loop), then averaged over a path's cells, duplicates included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

SQRT2 = math.sqrt(2.0)

# Dispersion rays in BARN's circular order, (row, col) steps.
DISPERSION_RAYS = ((0, 1), (1, 2), (1, 1), (2, 1), (1, 0), (2, -1), (1, -1), (1, -2), (0, -1), (-2, -1), (-1, -1),
                   (-1, -2), (-1, 0), (-2, 1), (-1, 1), (-1, 2))
EIGHT_DIRECTIONS = ((0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1))
METRIC_NAMES = ("distance", "visibility", "dispersion", "characteristic_dimension", "tortuosity")


class MetricsError(ValueError):
    """Bad grid or path (a path cell outside the map, a pair inside an obstacle, no path)."""


def inflate(grid: np.ndarray, radius_cells: int) -> np.ndarray:
    """C-space grid: a cell is blocked when any obstacle lies in the (2r+1) x (2r+1) square
    around it; cells outside the map are ignored."""
    grid = np.asarray(grid, dtype=bool)
    if radius_cells <= 0:
        return grid.copy()
    size = 2 * radius_cells + 1
    return ndimage.maximum_filter(grid.astype(np.uint8), size=size, mode="constant", cval=0).astype(bool)


def _shift(a: np.ndarray, dr: int, dc: int, fill) -> np.ndarray:
    """``out[r, c] = a[r + dr, c + dc]`` where inside the map, else ``fill``."""
    out = np.full_like(a, fill)
    rows, cols = a.shape
    r0, r1 = max(0, -dr), min(rows, rows - dr)
    c0, c1 = max(0, -dc), min(cols, cols - dc)
    if r0 < r1 and c0 < c1:
        out[r0:r1, c0:c1] = a[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
    return out


def free_run_lengths(blocked: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """For each cell, how many consecutive free cells a ray from it in direction (dr, dc)
    crosses, the cell itself included (0 on a blocked cell); the map edge ends a ray."""
    free = ~np.asarray(blocked, dtype=bool)
    rows, cols = free.shape
    # Pointer jumping: after the round with span s, length[p] is the free run from p capped at
    # 2s; a run that fills its first s cells continues with the (capped) run s cells ahead.
    length = free.astype(np.int32)
    span = 1
    while span < max(rows, cols):
        ahead = _shift(length, dr * span, dc * span, 0)
        length = np.where(length == span, span + ahead, length)
        span *= 2
    return length


def distance_map(blocked: np.ndarray) -> np.ndarray:
    """Euclidean distance (cells) from each cell to the nearest blocked cell; 0 on obstacles."""
    blocked = np.asarray(blocked, dtype=bool)
    if not blocked.any():
        return np.full(blocked.shape, np.inf)
    return ndimage.distance_transform_edt(~blocked)


def visibility_map(blocked: np.ndarray) -> np.ndarray:
    """Average over 8 rays of the free length seen from each cell (the cell included; axis
    cells count 1, diagonal cells sqrt(2)); a blocked cell sees 0."""
    total = np.zeros(blocked.shape)
    for dr, dc in EIGHT_DIRECTIONS:
        weight = SQRT2 if dr and dc else 1.0
        total += weight * free_run_lengths(blocked, dr, dc)
    return total / 8.0


def dispersion_map(blocked: np.ndarray, radius: int = 3) -> np.ndarray:
    """Number of hit/miss changes around the 16 rays (BARN's step counting); -1 on obstacles."""
    blocked = np.asarray(blocked, dtype=bool)
    rows, cols = blocked.shape
    hits = []
    for dr, dc in DISPERSION_RAYS:
        increment = 2 if (dr == 2 or dc == 2) else 1
        steps = math.ceil(radius / increment)
        hit = np.zeros(blocked.shape, dtype=bool)
        for k in range(1, steps + 1):
            hit |= _shift(blocked, dr * k, dc * k, False)  # outside the map: never a hit
        hits.append(hit)
    changes = np.zeros(blocked.shape, dtype=np.int32)
    for i in range(16):
        changes += hits[i] != hits[(i + 1) % 16]
    return np.where(blocked, -1, changes).astype(float)


def characteristic_dimension_map(blocked: np.ndarray) -> np.ndarray:
    """Smallest, over the 4 axes, of the free length through the cell (both ways, the cell not
    counted; diagonal cells count sqrt(2)); -1 on obstacles."""
    blocked = np.asarray(blocked, dtype=bool)
    best = np.full(blocked.shape, np.inf)
    for dr, dc in ((0, 1), (1, 1), (1, 0), (1, -1)):
        weight = SQRT2 if dr and dc else 1.0
        forward = free_run_lengths(blocked, dr, dc)
        backward = free_run_lengths(blocked, -dr, -dc)
        through = weight * (np.maximum(forward - 1, 0) + np.maximum(backward - 1, 0))
        best = np.minimum(best, through)
    return np.where(blocked, -1.0, best)


def path_length(path: np.ndarray) -> float:
    """Arc length (cells) of a cell path; diagonal steps count sqrt(2)."""
    path = np.asarray(path, dtype=float)
    if len(path) < 2:
        return 0.0
    return float(np.hypot(*np.diff(path, axis=0).T).sum())


def tortuosity(path: np.ndarray) -> float:
    path = np.asarray(path, dtype=float)
    straight = float(np.hypot(*(path[-1] - path[0])))
    if straight == 0:
        return 1.0
    return path_length(path) / straight


@dataclass(frozen=True)
class MetricMaps:
    """Per-cell metric maps of one C-space grid, computed once, averaged along many paths."""

    blocked: np.ndarray
    distance: np.ndarray
    visibility: np.ndarray
    dispersion: np.ndarray
    characteristic_dimension: np.ndarray

    @staticmethod
    def of(blocked: np.ndarray) -> MetricMaps:
        blocked = np.asarray(blocked, dtype=bool)
        return MetricMaps(blocked, distance_map(blocked), visibility_map(blocked), dispersion_map(blocked),
                          characteristic_dimension_map(blocked))

    def along(self, path: np.ndarray) -> np.ndarray:
        """``[distance, visibility, dispersion, characteristic dimension, tortuosity]``: the
        first four averaged over the path's cells as given (duplicates included)."""
        path = np.asarray(path, dtype=np.int64)
        rows, cols = self.blocked.shape
        if path.ndim != 2 or path.shape[1] != 2 or len(path) == 0:
            raise MetricsError(f"a path is a non-empty list of (row, col) cells, got shape {path.shape}")
        if path[:, 0].min() < 0 or path[:, 1].min() < 0 or path[:, 0].max() >= rows or path[:, 1].max() >= cols:
            raise MetricsError(f"path leaves the {rows} x {cols} map")
        r, c = path[:, 0], path[:, 1]
        return np.array([self.distance[r, c].mean(), self.visibility[r, c].mean(), self.dispersion[r, c].mean(),
                         self.characteristic_dimension[r, c].mean(), tortuosity(path)])


def barn_metrics(grid: np.ndarray, path: np.ndarray, radius_cells: int = 2) -> np.ndarray:
    """The benchmark's five numbers for a raw grid (1 = obstacle) and a path (as BARN stores
    it, start listed twice): inflate by ``radius_cells`` and average along the path."""
    return MetricMaps.of(inflate(grid, radius_cells)).along(path)


# -- shortest paths on the C-space grid ---------------------------------------------------------
class GridGraph:
    """8-connected graph of the free cells of a C-space grid (no diagonal step between two
    blocked cells); shortest paths by Dijkstra (scipy), several sources at once."""

    def __init__(self, blocked: np.ndarray) -> None:
        self.blocked = np.asarray(blocked, dtype=bool)
        rows, cols = self.blocked.shape
        free = ~self.blocked
        index = np.arange(rows * cols).reshape(rows, cols)
        src, dst, w = [], [], []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = free & _shift(free, dr, dc, False)
            if dr and dc:
                # no corner cutting between two blocked cells
                a &= ~(_shift(self.blocked, dr, 0, True) & _shift(self.blocked, 0, dc, True))
            r, c = np.nonzero(a)
            src.append(index[r, c])
            dst.append(index[r + dr, c + dc])
            w.append(np.full(len(r), SQRT2 if dr and dc else 1.0))
        src, dst, w = np.concatenate(src), np.concatenate(dst), np.concatenate(w)
        n = rows * cols
        self.graph = sparse.coo_matrix((np.concatenate([w, w]), (np.concatenate([src, dst]), np.concatenate([dst, src]))),
                                       shape=(n, n)).tocsr()
        self.shape = (rows, cols)

    def shortest_paths(self, starts: list[tuple[int, int]], goals: list[tuple[int, int]],
                       duplicate_start: bool = True) -> list[np.ndarray | None]:
        """One cell path per (start, goal), or None where unreachable. ``duplicate_start``
        lists the start twice, as BARN's path files do."""
        rows, cols = self.shape
        unique = sorted(set(starts))
        flat = [r * cols + c for r, c in unique]
        _, predecessors = csgraph.dijkstra(self.graph, directed=False, indices=flat, return_predecessors=True)
        out = []
        for start, goal in zip(starts, goals):
            pred = predecessors[unique.index(start)]
            node = goal[0] * cols + goal[1]
            target = start[0] * cols + start[1]
            if node != target and pred[node] < 0:
                out.append(None)
                continue
            cells = [node]
            while node != target:
                node = pred[node]
                cells.append(node)
            cells.reverse()
            if duplicate_start:
                cells.insert(0, cells[0])
            out.append(np.array([(n // cols, n % cols) for n in cells], dtype=np.int64))
        return out


def barn_astar(blocked: np.ndarray, start: tuple[int, int], goal: tuple[int, int], radius_cells: int = 2,
               penalty: float = 5.0, duplicate_start: bool = True) -> np.ndarray | None:
    """BARN's planner on a C-space grid: A* over (cell, heading) with 8-connected steps (no
    diagonal between two blocked cells), turns of at most 45 degrees after the first step, and
    a wall-proximity term ``penalty / dist`` added to f (not g) on cells at most
    ``radius_cells`` from an obstacle. Returns the cell path (start twice, as BARN stores it)."""
    import heapq

    blocked = np.asarray(blocked, dtype=bool)
    rows, cols = blocked.shape
    if blocked[start] or blocked[goal]:
        return None
    dist = distance_map(blocked)
    moves = EIGHT_DIRECTIONS  # index k; a 45-degree turn is k +- 1 (mod 8)

    def h(cell):
        return math.hypot(cell[0] - goal[0], cell[1] - goal[1])

    def extra(cell):
        d = dist[cell]
        return penalty / d if 0 < d <= radius_cells else 0.0

    start_state = (start, -1)
    g_cost = {start_state: 0.0}
    parent: dict = {start_state: None}
    heap = [(h(start), 0.0, start, -1)]
    closed = set()
    while heap:
        _, g, cell, heading = heapq.heappop(heap)
        state = (cell, heading)
        if state in closed:
            continue
        closed.add(state)
        if cell == goal:
            cells = []
            while state is not None:
                cells.append(state[0])
                state = parent[state]
            cells.reverse()
            if duplicate_start:
                cells.insert(0, cells[0])
            return np.array(cells, dtype=np.int64)
        allowed = range(8) if heading < 0 else ((heading - 1) % 8, heading, (heading + 1) % 8)
        for k in allowed:
            dr, dc = moves[k]
            nr, nc = cell[0] + dr, cell[1] + dc
            if not (0 <= nr < rows and 0 <= nc < cols) or blocked[nr, nc]:
                continue
            if dr and dc and blocked[cell[0] + dr, cell[1]] and blocked[cell[0], cell[1] + dc]:
                continue
            nxt = ((nr, nc), k)
            ng = g + (SQRT2 if dr and dc else 1.0)
            if ng < g_cost.get(nxt, math.inf):
                g_cost[nxt] = ng
                parent[nxt] = state
                heapq.heappush(heap, (ng + h((nr, nc)) + extra((nr, nc)), ng, (nr, nc), k))
    return None
