"""The correlative search's inner loop, compiled: the mean of a score grid under a rotated scan at
many translations (numba, cached on disk; see docs/slam.md for the compile times).

It replaces gathering an (M, N) index array in numpy per batch of candidates: the loop reads each
cell once into a float64 sum and allocates nothing. Likelihood values are float32 in [exp(-8), 1]
or 0, so every partial sum is exact in float64 and the result equals numpy's to the bit.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def block_scores(grid: np.ndarray, base: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Mean of ``grid`` (H, W) under each candidate's points.

    ``base`` (angles, N) holds the flat index of each rotated point for offset (0, 0);
    ``candidates`` (M, 3) = angle index, dx, dy in cells (every index in the grid, as the search clips).
    """
    flat = grid.ravel()
    width = grid.shape[1]
    count = base.shape[1]
    out = np.empty(candidates.shape[0], np.float64)
    for m in range(candidates.shape[0]):
        row = base[candidates[m, 0]]
        shift = candidates[m, 2] * width + candidates[m, 1]
        total = 0.0
        for n in range(count):
            total += flat[row[n] + shift]
        out[m] = total / max(count, 1)
    return out
