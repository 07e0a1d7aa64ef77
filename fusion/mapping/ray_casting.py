"""Ray casting into a log-odds grid, compiled: the cells each ray crosses and the once-per-scan update
of those cells and of the returns' cells (numba, cached on disk).

numpy needed an array per sample for each step of the DDA and a grid-sized hit mask per scan; these
loops visit each sample once and touch only the cells the rays reach. The arithmetic is numpy's, step
for step (float32 log-odds updated in float32), so the grids are equal to the bit.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
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


@numba.njit(cache=True, nogil=True)
def update_cells(log_odds: np.ndarray, observed: np.ndarray, hit_flat: np.ndarray, crossed_flat: np.ndarray,
                 l_hit: float, l_miss: float, l_min: float, l_max: float) -> None:
    """One scan's update of ``log_odds`` (float32) and ``observed`` (flat indices): ``l_miss`` once on every
    crossed cell that holds no return, ``l_hit`` once on every return's cell, clamped to [l_min, l_max].

    A cell crossed by many rays or hit by many returns changes once: every new value is computed from
    the values before the scan, then written.
    """
    flat, seen = log_odds.ravel(), observed.ravel()
    miss, hit = np.float32(l_miss), np.float32(l_hit)
    low, high = np.float32(l_min), np.float32(l_max)
    before_hits = np.empty(hit_flat.shape[0], np.float32)
    for j in range(hit_flat.shape[0]):
        before_hits[j] = flat[hit_flat[j]]
    freed = np.empty(crossed_flat.shape[0], np.float32)
    for j in range(crossed_flat.shape[0]):
        freed[j] = max(flat[crossed_flat[j]] + miss, low)
    for j in range(crossed_flat.shape[0]):
        flat[crossed_flat[j]] = freed[j]
        seen[crossed_flat[j]] = True
    for j in range(hit_flat.shape[0]):   # a return's cell is not free, whatever crossed it
        flat[hit_flat[j]] = min(before_hits[j] + hit, high)
        seen[hit_flat[j]] = True


@numba.njit(cache=True, nogil=True)
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
