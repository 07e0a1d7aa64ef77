"""The wall lines' neighbourhood moments, compiled (numba, cached on disk): for each occupied cell, the
mean of its returns and the moments of the returns of its occupied 3 x 3 neighbourhood about it, and from
them the terms of the line through those returns.

numpy needed nine masked gathers of six planes per window, and a dozen calls more for the lines' terms
(70 us a window of 300 cells); these loops read each neighbour once. The arithmetic is numpy's, term for term.
"""

from __future__ import annotations

import numpy as np

from trundle.fusion.compiled import kernel


@kernel
def neighbourhood_moments(slots: np.ndarray, moments: np.ndarray, log_odds: np.ndarray, rows: np.ndarray,
                          cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For cells ``(rows, cols)`` of a grid whose cells' return moments are ``moments[slots[row, col]]``
    (count, sums of u, v, u^2, uv, v^2 in cell units; row 0 zero: no return): the mean of each cell's
    returns (N, 2, absolute cell units, x then y) and the count and moments (N, 6) of the returns of its
    occupied (log-odds > 0) 3 x 3 neighbourhood about that mean (sums of 1, x, y, x^2, xy, y^2)."""
    height, width = log_odds.shape
    n = rows.shape[0]
    mean = np.empty((n, 2))
    sums = np.zeros((n, 6))
    for i in range(n):
        r, c = rows[i], cols[i]
        own = moments[slots[r, c]]
        count = np.float64(own[0])
        mean[i, 0] = c + np.float64(own[1]) / count
        mean[i, 1] = r + np.float64(own[2]) / count
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if rr < 0 or cc < 0 or rr >= height or cc >= width or not log_odds[rr, cc] > 0.0:
                    continue
                m = moments[slots[rr, cc]]
                n0, n1, n2 = np.float64(m[0]), np.float64(m[1]), np.float64(m[2])
                n3, n4, n5 = np.float64(m[3]), np.float64(m[4]), np.float64(m[5])
                ox, oy = cc - mean[i, 0], rr - mean[i, 1]
                sums[i, 0] += n0
                sums[i, 1] += n1 + ox * n0
                sums[i, 2] += n2 + oy * n0
                sums[i, 3] += n3 + 2 * ox * n1 + ox * ox * n0
                sums[i, 4] += n4 + ox * n2 + oy * n1 + ox * oy * n0
                sums[i, 5] += n5 + 2 * oy * n2 + oy * oy * n0
    return mean, sums


@kernel
def line_terms(slots: np.ndarray, moments: np.ndarray, log_odds: np.ndarray, rows: np.ndarray, cols: np.ndarray,
               origin: np.ndarray, resolution: float, min_flatness: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For cells ``(rows, cols)`` (as :func:`neighbourhood_moments` takes them) on a grid whose cell (0, 0) starts
    at ``origin`` (m) with cells of ``resolution`` m: the mean of each cell's returns (N, 2, m); twice the
    covariance ``sxy`` and the difference ``sxx - syy`` of its neighbourhood's returns about their centroid
    (cell units^2), whose ``atan2`` is twice the direction of the line through them; and whether they lie
    on one (flatness ``1 - smaller / larger`` spread at least ``min_flatness``, and at least three returns).
    numpy's expressions element by element; the ``atan2`` is left to the caller, as numpy computes it
    (its vector code differs from the C library's in the last bit)."""
    mean, sums = neighbourhood_moments(slots, moments, log_odds, rows, cols)
    n = rows.shape[0]
    world = np.empty((n, 2))
    twice_sxy, difference = np.empty(n), np.empty(n)
    is_line = np.empty(n, np.bool_)
    for i in range(n):
        world[i, 0] = origin[0] + mean[i, 0] * resolution
        world[i, 1] = origin[1] + mean[i, 1] * resolution
        count = sums[i, 0]
        mx, my = sums[i, 1] / count, sums[i, 2] / count
        sxx, sxy, syy = sums[i, 3] / count - mx * mx, sums[i, 4] / count - mx * my, sums[i, 5] / count - my * my
        twice_sxy[i], difference[i] = 2.0 * sxy, sxx - syy
        half = difference[i] / 2.0
        spread = np.sqrt(half * half + sxy * sxy)
        centre = (sxx + syy) / 2.0
        larger = centre + spread
        flat = 1.0 - (centre - spread) / (larger if not larger < 1e-12 else 1e-12)   # np.maximum's: NaN stays
        is_line[i] = flat >= min_flatness and count >= 3
    return world, twice_sxy, difference, is_line
