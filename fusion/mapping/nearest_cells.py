"""The match fields' distance transform, compiled (numba, cached on disk): for each cell of a window, the
distance to the nearest occupied cell within a radius, as the fields read it.

A match reads the fields only up to a few cells beyond its cap (half a metre), so each occupied cell
stamps a disc of that radius into the window: exact Euclidean distances (OpenCV's precise transform
of the whole padded window gives the same to float32 rounding), and each field's value looked up per
squared distance instead of computed per cell (the likelihood's exp over the window cost as much as
the transform). It costs the occupied cells times the disc, not passes over the whole padded window.
"""

from __future__ import annotations

import math

import numba
import numpy as np


def squared_distances(radius: int) -> np.ndarray:
    """The distances (cells, float32) a disc of ``radius`` cells can hold, indexed by their square, and inf
    after them (no occupied cell within the radius): what :func:`stamped_fields`'s tables are made from."""
    values = np.sqrt(np.arange(radius * radius + 2, dtype=np.float64)).astype(np.float32)
    values[-1] = np.inf
    return values


@numba.njit(cache=True, nogil=True)
def stamped_fields(rows: np.ndarray, cols: np.ndarray, row0: int, col0: int, height: int, width: int, radius: int,
                   tables: np.ndarray) -> np.ndarray:
    """Fields (T, height, width) of the distance to the nearest of the occupied cells ``(rows, cols)`` over
    the window ``[row0, row0 + height) x [col0, col0 + width)`` (same coordinates).

    ``tables`` (T, radius^2 + 2) holds each field's value per squared distance in cells, the last
    column for none within ``radius`` (see :func:`squared_distances`).
    """
    none = radius * radius + 1
    best = np.full((height, width), none, np.int32)
    for k in range(rows.shape[0]):
        r, c = rows[k] - row0, cols[k] - col0
        for dr in range(max(-radius, -r), min(radius, height - 1 - r) + 1):
            reach = int(math.sqrt(radius * radius - dr * dr))
            row = best[r + dr]
            for dc in range(max(-reach, -c), min(reach, width - 1 - c) + 1):
                row[c + dc] = min(row[c + dc], dr * dr + dc * dc)
    fields = np.empty((tables.shape[0], height, width), np.float32)
    for t in range(tables.shape[0]):
        for i in range(height):
            for j in range(width):
                fields[t, i, j] = tables[t, best[i, j]]
    return fields


@numba.njit(cache=True, nogil=True)
def occupied_cells(log_odds: np.ndarray, r0: int, r1: int, c0: int, c1: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The occupied cells (log-odds above 0) of ``log_odds[r0:r1, c0:c1]``: their rows and columns in that
    window, in ``np.nonzero``'s (row-major) order, and the window as OpenCV's distance transforms take it
    (uint8: 0 on an occupied cell, 255 elsewhere). One pass where numpy made a mask, its nonzero and the image."""
    height, width = r1 - r0, c1 - c0
    image = np.empty((height, width), np.uint8)
    count = 0
    for i in range(height):
        for j in range(width):
            if log_odds[r0 + i, c0 + j] > 0.0:
                image[i, j] = 0
                count += 1
            else:
                image[i, j] = 255
    rows = np.empty(count, np.int64)
    cols = np.empty(count, np.int64)
    k = 0
    for i in range(height):
        for j in range(width):
            if image[i, j] == 0:
                rows[k], cols[k] = i, j
                k += 1
    return rows, cols, image
