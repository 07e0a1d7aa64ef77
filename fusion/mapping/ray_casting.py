"""Ray casting into a log-odds grid, compiled: the cells each ray crosses and the once-per-scan update
of those cells and of the returns' cells (numba, cached on disk), each a call per scan.

numpy needed an array per sample for each step of the DDA and a grid-sized hit mask per scan; these
loops visit each sample once and touch only the cells the rays reach. The arithmetic is numpy's, step
for step (float32 log-odds updated in float32), so the grids are equal to the bit.
"""

from __future__ import annotations

import numpy as np

from trundle.fusion.compiled import kernel


@kernel
def ray_cells(start: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Cells (row, col) crossed by rays from ``start`` (2,) to each of ``ends`` (N, 2), end cells excluded.

    Coordinates in cells (x = column, y = row; cell k spans [k, k+1)). Each ray is sampled at
    ``ceil(max(|dx|, |dy|))`` equal steps (a DDA line, like Bresenham's).
    """
    n = ends.shape[0]
    steps = np.empty(n, np.int64)
    total = 0
    for r in range(n):
        steps[r] = int(np.ceil(max(abs(ends[r, 0] - start[0]), abs(ends[r, 1] - start[1]))))
        total += steps[r]
    cells = np.empty((total, 2), np.int64)
    k = 0
    for r in range(n):
        dx, dy = ends[r, 0] - start[0], ends[r, 1] - start[1]
        end_x, end_y = int(np.floor(ends[r, 0])), int(np.floor(ends[r, 1]))
        count = steps[r]
        for i in range(count):
            t = i / count
            x, y = int(np.floor(start[0] + t * dx)), int(np.floor(start[1] + t * dy))
            if x != end_x or y != end_y:
                cells[k, 0], cells[k, 1] = y, x
                k += 1
    return cells[:k]


@kernel
def trace(origin: np.ndarray, resolution: float, sensor_xy: np.ndarray, hits_xy: np.ndarray,
          free_ends_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rays from ``sensor_xy`` (2,) to the returns ``hits_xy`` (N, 2) and the free ends ``free_ends_xy``
    (M, 2) (metres) on the lattice of ``resolution`` m cells whose cell (0, 0) starts at ``origin``: the
    cells crossed (:func:`ray_cells`), the returns' cells as (row, col), their offsets in those cells
    (u, v in [0, 1)) and the bounding box (m) of sensor, returns and free ends (NaN if any is).
    numpy's arithmetic, element by element: ``(xy - origin) / resolution``, its floor and the remainder."""
    n, m = hits_xy.shape[0], free_ends_xy.shape[0]
    ends = np.empty((n + m, 2))
    hit_cells = np.empty((n, 2), np.int64)
    offsets = np.empty((n, 2))
    low, high = sensor_xy.copy(), sensor_xy.copy()
    for i in range(n + m):
        for a in range(2):
            value = hits_xy[i, a] if i < n else free_ends_xy[i - n, a]
            if value < low[a] or value != value:   # numpy's min and max: NaN wins
                low[a] = value
            if value > high[a] or value != value:
                high[a] = value
            ends[i, a] = (value - origin[a]) / resolution
            if i < n:
                cell = np.int64(np.floor(ends[i, a]))
                hit_cells[i, 1 - a] = cell
                offsets[i, a] = ends[i, a] - cell
    start = np.empty(2)
    for a in range(2):
        start[a] = (sensor_xy[a] - origin[a]) / resolution
    return ray_cells(start, ends), hit_cells, offsets, low, high


@kernel
def add_moments(slots: np.ndarray, rows: np.ndarray, count: int, hit_flat: np.ndarray, offsets: np.ndarray) -> int:
    """Add each return's moments (1, u, v, u^2, uv, v^2 of its offset (u, v) in its cell) to its cell's row of
    ``rows`` (float32), in the returns' order; ``slots`` (H, W) holds each cell's row (0: none yet: the
    next free row, ``count``, becomes its). ``rows`` must have room for a new row per return. Returns
    the rows in use."""
    flat = slots.ravel()
    for j in range(hit_flat.shape[0]):
        u, v = offsets[j, 0], offsets[j, 1]
        row = flat[hit_flat[j]]
        if row == 0:
            row = count
            flat[hit_flat[j]] = row
            count += 1
        rows[row, 0] += np.float32(1.0)
        rows[row, 1] += np.float32(u)
        rows[row, 2] += np.float32(v)
        rows[row, 3] += np.float32(u * u)
        rows[row, 4] += np.float32(u * v)
        rows[row, 5] += np.float32(v * v)
    return count


@kernel
def insert_scan(log_odds: np.ndarray, observed: np.ndarray, slots: np.ndarray, rows: np.ndarray, count: int,
                hits: np.ndarray, offsets: np.ndarray, crossed: np.ndarray, row_shift: int, col_shift: int,
                l_hit: float, l_miss: float, l_min: float, l_max: float) -> tuple[int, np.ndarray]:
    """One traced scan into a grid: the returns' cells ``hits`` and the ``crossed`` cells are (row, col) on a
    lattice whose cell (0, 0) is the grid's (``row_shift``, ``col_shift``). ``log_odds`` (float32) takes
    ``l_miss`` once on every crossed cell that holds no return and ``l_hit`` once on every return's cell,
    clamped to [l_min, l_max], and ``observed`` is set on both; unless ``slots`` is empty, each return's
    moments go to its cell's row (:func:`add_moments`). Returns the moment rows in use and the returns'
    flat indices.

    A cell crossed by many rays or hit by many returns changes once: every new value is computed from
    the values before the scan, then written.
    """
    width = log_odds.shape[1]
    flat, seen = log_odds.ravel(), observed.ravel()
    miss, hit = np.float32(l_miss), np.float32(l_hit)
    low, high = np.float32(l_min), np.float32(l_max)
    hit_flat = np.empty(hits.shape[0], np.int64)
    before_hits = np.empty(hits.shape[0], np.float32)
    for j in range(hits.shape[0]):
        hit_flat[j] = (hits[j, 0] + row_shift) * width + hits[j, 1] + col_shift
        before_hits[j] = flat[hit_flat[j]]
    freed = np.empty(crossed.shape[0], np.float32)
    for j in range(crossed.shape[0]):
        freed[j] = max(flat[(crossed[j, 0] + row_shift) * width + crossed[j, 1] + col_shift] + miss, low)
    for j in range(crossed.shape[0]):
        cell = (crossed[j, 0] + row_shift) * width + crossed[j, 1] + col_shift
        flat[cell] = freed[j]
        seen[cell] = True
    for j in range(hits.shape[0]):   # a return's cell is not free, whatever crossed it
        flat[hit_flat[j]] = min(before_hits[j] + hit, high)
        seen[hit_flat[j]] = True
    if slots.size:
        count = add_moments(slots, rows, count, hit_flat, offsets)
    return count, hit_flat


@kernel
def trace_and_insert(log_odds: np.ndarray, observed: np.ndarray, slots: np.ndarray, rows: np.ndarray, count: int,
                     origin: np.ndarray, resolution: float, sensor_xy: np.ndarray, hits_xy: np.ndarray,
                     free_ends_xy: np.ndarray, l_hit: float, l_miss: float, l_min: float, l_max: float
                     ) -> tuple[bool, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`trace` on the grid's own lattice (cell (0, 0) at ``origin``), then :func:`insert_scan` when the box
    of sensor, returns and free ends lies inside the grid: one call where a Python insert made two and the
    object between them (a seventh of an insert of 180 beams). Returns whether it was inserted, the moment
    rows in use, the returns' flat indices (empty if not inserted) and the trace (crossed cells, return
    cells, offsets, box), which an insert outside the grid takes after growing it."""
    crossed, hits, offsets, low, high = trace(origin, resolution, sensor_xy, hits_xy, free_ends_xy)
    height, width = log_odds.shape
    # LogOddsGrid.ensure_contains' test, its arithmetic: NaN is never inside
    inside = height > 0 and (low[0] - origin[0]) / resolution >= 0 and (low[1] - origin[1]) / resolution >= 0 \
        and (high[0] - origin[0]) / resolution < width and (high[1] - origin[1]) / resolution < height
    hit_flat = np.empty(0, np.int64)
    if inside:
        count, hit_flat = insert_scan(log_odds, observed, slots, rows, count, hits, offsets, crossed, 0, 0, l_hit,
                                      l_miss, l_min, l_max)
    return inside, count, hit_flat, crossed, hits, offsets, low, high
