"""Static geometry of a world, and the LiDAR's ray cast: the numeric kernels behind ``Scene``.

All are pure functions of arrays (no PyBullet), compiled with numba:

- ``merge_cells_into_rectangles``: cover the obstacle cells of a grid exactly with few
  axis-aligned rectangles (the world's size in boxes, shown by ``curlnav bench env``).
- ``wall_faces`` and ``face_segments``: the cell edges between obstacle and free space, merged
  into straight segments: the scene's wall meshes. Why meshes and not boxes: PyBullet keeps at
  most 16 child shapes in one compound collision shape (``MAX_COMPOUND_COLLISION_SHAPES``) and
  silently drops the rest, so one compound cannot hold a map, and one body per box costs
  broad-phase work for every body at every physics step (about 6 ms per 0.2 s step on a
  92 m x 72 m map of 2,300 compounds, against 0.5 ms for 52 meshes).
- The LiDAR: ``cast_grid`` walks each beam through the occupancy grid cell by cell (an exact
  grid traversal: the first occupied cell a beam enters, or the edge of the map, ends it) and
  ``cast_movable`` intersects each beam analytically with the movable bodies (3-D ray against
  sphere and oriented box, so a ball or box that has left the scan plane a little still reads
  right). The static part never asks PyBullet: on barn-3x3 the 241-ray ``rayTestBatch`` through
  the wall bodies cost more than all the physics. The tests check both parts against PyBullet's
  own ray test on the scene's bodies and the static part against a brute-force march on the grid.

Frames: the kernels work in the *grid frame* (metres along the grid's columns and rows from the
outer corner of cell (0, 0)); ``World.grid_from_map`` converts. The region outside the grid is
solid (the scene puts boundary walls there).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _merge_rectangles(occ: np.ndarray) -> np.ndarray:
    work = occ.copy()
    rows, cols = work.shape
    out = np.empty((16, 4), dtype=np.int64)
    n = 0
    for iy in range(rows):
        ix = 0
        while ix < cols:
            if not work[iy, ix]:
                ix += 1
                continue
            start = ix
            while ix < cols and work[iy, ix]:
                ix += 1
            height = 1
            while iy + height < rows:
                full = True
                for k in range(start, ix):
                    if not work[iy + height, k]:
                        full = False
                        break
                if not full:
                    break
                height += 1
            for r in range(iy, iy + height):
                for k in range(start, ix):
                    work[r, k] = False
            if n == out.shape[0]:
                bigger = np.empty((2 * n, 4), dtype=np.int64)
                bigger[:n] = out
                out = bigger
            out[n, 0] = iy
            out[n, 1] = start
            out[n, 2] = height
            out[n, 3] = ix - start
            n += 1
    return out[:n].copy()


def merge_cells_into_rectangles(occupancy: np.ndarray) -> np.ndarray:
    """Cover the obstacle cells exactly with few axis-aligned rectangles.

    Greedy: runs along each row, then each run grows upward while the rows above hold the same
    cells. Returns an int array of shape ``(n, 4)``: ``(iy, ix, height, width)`` in cells.
    """
    occ = np.ascontiguousarray(occupancy, dtype=np.bool_)
    if occ.ndim != 2:
        raise ValueError(f"occupancy must be 2-D, got shape {occ.shape}")
    return _merge_rectangles(occ)


@numba.njit(cache=True)
def _first_crossing(p, i, d):
    """Along one axis, for a ray at ``p`` (cells) in cell ``i`` going at ``d`` per unit length:
    the cell step (+1, -1 or 0), the ray parameter of the first cell boundary and the parameter
    between boundaries (inf when the ray runs parallel to the axis)."""
    if d > 0.0:
        return 1, (i + 1 - p) / d, 1.0 / d
    if d < 0.0:
        return -1, (p - i) / -d, -1.0 / d
    return 0, np.inf, np.inf


@numba.njit(cache=True)
def _cast_grid(occ, resolution, u, v, angles, max_range, out):
    rows, cols = occ.shape
    px = u / resolution
    py = v / resolution
    t_limit = max_range / resolution
    ix0 = int(math.floor(px))
    iy0 = int(math.floor(py))
    inside = 0 <= ix0 < cols and 0 <= iy0 < rows
    if not inside or occ[iy0, ix0]:
        for k in range(angles.size):
            out[k] = 0.0
        return
    for k in range(angles.size):
        dx = math.cos(angles[k])
        dy = math.sin(angles[k])
        ix = ix0
        iy = iy0
        step_x, t_x, dt_x = _first_crossing(px, ix, dx)
        step_y, t_y, dt_y = _first_crossing(py, iy, dy)
        result = max_range
        while True:
            if t_x < t_y:
                t = t_x
                ix += step_x
                t_x += dt_x
            else:
                t = t_y
                iy += step_y
                t_y += dt_y
            if t >= t_limit:
                break
            if ix < 0 or iy < 0 or ix >= cols or iy >= rows or occ[iy, ix]:
                result = t * resolution
                break
        out[k] = result


def cast_grid(occupancy: np.ndarray, resolution: float, u: float, v: float, angles: np.ndarray,
              max_range: float, out: np.ndarray | None = None) -> np.ndarray:
    """Range (m) from grid-frame point ``(u, v)`` (m) along each of ``angles`` (rad, grid
    frame; shape ``(beams,)``) to the first obstacle cell or the map's edge, ``max_range`` where
    none is nearer. A point inside an obstacle or off the map reads 0 on every beam."""
    out = np.empty(len(angles), dtype=np.float64) if out is None else out
    _cast_grid(occupancy, float(resolution), float(u), float(v), np.asarray(angles, dtype=np.float64),
               float(max_range), out)
    return out


@numba.njit(cache=True)
def _cast_movable(x, y, z, angles, max_range, spheres, boxes, out_range, out_index):
    n_spheres = spheres.shape[0]
    for k in range(angles.size):
        dx = math.cos(angles[k])
        dy = math.sin(angles[k])
        best = max_range
        best_i = -1
        for i in range(n_spheres):
            # |p + t d - c|^2 = r^2 with d in the plane (dz = 0)
            ox = x - spheres[i, 0]
            oy = y - spheres[i, 1]
            oz = z - spheres[i, 2]
            r = spheres[i, 3]
            b = ox * dx + oy * dy
            c = ox * ox + oy * oy + oz * oz - r * r
            disc = b * b - c
            if disc < 0.0:
                continue
            root = math.sqrt(disc)
            t = -b - root
            if t < 0.0:
                if -b + root < 0.0:
                    continue
                t = 0.0  # the beam starts inside the ball
            if t < best:
                best = t
                best_i = i
        for j in range(boxes.shape[0]):
            # boxes[j] = centre (3), rotation matrix rows (9), half extents (3)
            ox = x - boxes[j, 0]
            oy = y - boxes[j, 1]
            oz = z - boxes[j, 2]
            t_near = -np.inf
            t_far = np.inf
            hit = True
            for a in range(3):
                ax = boxes[j, 3 + 3 * a]
                ay = boxes[j, 4 + 3 * a]
                az = boxes[j, 5 + 3 * a]
                o = ox * ax + oy * ay + oz * az  # origin along the box's axis a
                d = dx * ax + dy * ay
                h = boxes[j, 12 + a]
                if abs(d) < 1e-12:
                    if o < -h or o > h:
                        hit = False
                        break
                    continue
                t1 = (-h - o) / d
                t2 = (h - o) / d
                if t1 > t2:
                    t1, t2 = t2, t1
                if t1 > t_near:
                    t_near = t1
                if t2 < t_far:
                    t_far = t2
                if t_near > t_far or t_far < 0.0:
                    hit = False
                    break
            if not hit:
                continue
            t = t_near if t_near > 0.0 else 0.0
            if t < best:
                best = t
                best_i = n_spheres + j
        out_range[k] = best
        out_index[k] = best_i


def cast_movable(x: float, y: float, z: float, angles: np.ndarray, max_range: float, spheres: np.ndarray,
                 boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersect horizontal beams from ``(x, y, z)`` (m, map frame) along ``angles`` (rad) with
    movable bodies.

    ``spheres``: shape ``(n, 4)``: centre x, y, z and radius (m). ``boxes``: shape ``(m, 15)``:
    centre (3), the box's three axes as rows of its rotation matrix (9), half extents (3).
    Returns the range to the first hit (m, ``max_range`` when none) and the index of the body
    hit (spheres first, then boxes; -1 when none), each of shape ``(beams,)``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    ranges = np.empty(len(angles), dtype=np.float64)
    index = np.empty(len(angles), dtype=np.int64)
    _cast_movable(float(x), float(y), float(z), angles, float(max_range),
                  np.ascontiguousarray(spheres, dtype=np.float64).reshape(-1, 4),
                  np.ascontiguousarray(boxes, dtype=np.float64).reshape(-1, 15), ranges, index)
    return ranges, index


@numba.njit(cache=True)
def _face_runs(faces, axis_is_row, r0, r1, c0, c1, out, n):
    # faces: bool (a, b); runs along the second index within [c0, c1) for first index in [r0, r1)
    for r in range(r0, r1):
        c = c0
        while c < c1:
            if not faces[r, c]:
                c += 1
                continue
            start = c
            while c < c1 and faces[r, c]:
                c += 1
            if n == out.shape[0]:
                bigger = np.empty((2 * n + 16, 4), dtype=np.int64)
                bigger[:n] = out[:n]
                out = bigger
            if axis_is_row:  # a horizontal face on row boundary r from column start to c
                out[n, 0] = start
                out[n, 1] = r
                out[n, 2] = c
                out[n, 3] = r
            else:  # faces is transposed: r is a column boundary, start..c rows
                out[n, 0] = r
                out[n, 1] = start
                out[n, 2] = r
                out[n, 3] = c
            n += 1
    return out, n


def wall_faces(occupancy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where obstacle cells border free cells: boolean masks of the grid's cell edges.

    Returns ``(horizontal, vertical)``: ``horizontal[r, c]`` (shape ``(rows + 1, cols)``) is
    True where cell ``(r - 1, c)`` and cell ``(r, c)`` differ; ``vertical[r, c]`` (shape
    ``(rows, cols + 1)``) where ``(r, c - 1)`` and ``(r, c)`` differ. Outside the grid counts as
    an obstacle, so free cells on the map's edge have a face there.
    """
    occ = np.asarray(occupancy, dtype=bool)
    padded = np.pad(occ, 1, constant_values=True)
    horizontal = padded[:-1, 1:-1] != padded[1:, 1:-1]
    vertical = padded[1:-1, :-1] != padded[1:-1, 1:]
    return horizontal, vertical


def face_segments(horizontal: np.ndarray, vertical: np.ndarray, r0: int, c0: int, r1: int, c1: int) -> np.ndarray:
    """Merge the faces of a block of cells ``[r0, r1) x [c0, c1)`` into straight segments.

    A block owns the horizontal faces on row boundaries ``r0..r1-1`` and the vertical faces on
    column boundaries ``c0..c1-1``; the last block of the grid also owns the far boundary (pass
    ``r1 = rows + 1`` or ``c1 = cols + 1`` for it). Returns an int array ``(n, 4)``:
    ``(x0, y0, x1, y1)`` in cell units of the grid frame.
    """
    out = np.empty((64, 4), dtype=np.int64)
    rows_h, cols_h = horizontal.shape
    out, n = _face_runs(horizontal, True, r0, min(r1, rows_h), c0, min(c1, cols_h), out, 0)
    vt = np.ascontiguousarray(vertical.T)
    rows_v, cols_v = vt.shape
    out, n = _face_runs(vt, False, c0, min(c1, rows_v), r0, min(r1, cols_v), out, n)
    return out[:n].copy()


def warm_up() -> None:
    """Compile every kernel now (numba caches the machine code beside this file, or in
    ``NUMBA_CACHE_DIR``), so the first environment step does not pay for it; the container
    image calls this when it is built."""
    grid = np.zeros((4, 4), dtype=bool)
    grid[0] = True
    merge_cells_into_rectangles(grid)
    horizontal, vertical = wall_faces(grid)
    face_segments(horizontal, vertical, 0, 0, 5, 5)
    angles = np.linspace(-1.0, 1.0, 3)
    cast_grid(grid, 0.1, 0.2, 0.2, angles, 1.0)
    cast_movable(0.0, 0.0, 0.0, angles, 1.0, np.array([[0.5, 0.0, 0.0, 0.1]]), np.zeros((1, 15)))
