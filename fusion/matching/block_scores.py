"""The correlative search, compiled (numba, cached on disk; see docs/slam.md for the compile times): the
mean of a score grid under a rotated scan at many translations, and the whole
branch and bound over them in one call.

The gather-and-sum replaces gathering an (M, N) index array in numpy per batch of candidates: the loop
reads each cell once into a float64 sum and allocates nothing. Likelihood values are float32 in
[exp(-8), 1] or 0, so every partial sum is exact in float64 and the result equals numpy's to the bit.
The branch and bound is the numpy loop it replaced, step for step (its candidates in the same order,
so of equal best scores the same one wins); in Python it made a few dozen small numpy calls a search.
"""

from __future__ import annotations

import math

import numpy as np

from trundle.fusion.compiled import kernel


@kernel
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
        # four sums at once, not one chain of dependent additions: every partial sum is exact (see the
        # module's docstring), so in any order the total is the same to the bit
        a = b = c = d = 0.0
        n = 0
        while n + 4 <= count:
            a += flat[row[n] + shift]
            b += flat[row[n + 1] + shift]
            c += flat[row[n + 2] + shift]
            d += flat[row[n + 3] + shift]
            n += 4
        while n < count:
            a += flat[row[n] + shift]
            n += 1
        out[m] = ((a + b) + (c + d)) / max(count, 1)
    return out


@kernel
def _scores(pyramid: np.ndarray, level: int, base: np.ndarray, candidates: np.ndarray, limit: int,
            resolution: float, thetas: np.ndarray, theta0: float, prior_std_xy_m: float,
            prior_std_theta_rad: float) -> np.ndarray:
    """Upper bounds of the (prior-weighted; a prior <= 0: none) scores of blocks of ``2^level`` cells."""
    raw = block_scores(pyramid[level], base, candidates)
    if prior_std_xy_m <= 0.0 and prior_std_theta_rad <= 0.0:
        return raw
    top = (1 << level) - 1
    for m in range(candidates.shape[0]):
        cost = 0.0
        if prior_std_xy_m > 0.0:
            # nearest offset to the prediction inside each block: an upper bound of the prior there
            nx = min(max(0, candidates[m, 1] - limit), candidates[m, 1] - limit + top)
            ny = min(max(0, candidates[m, 2] - limit), candidates[m, 2] - limit + top)
            cost += (resolution * resolution) * (nx * nx + ny * ny) / prior_std_xy_m ** 2
        if prior_std_theta_rad > 0.0:
            cost += ((thetas[candidates[m, 0]] - theta0) / prior_std_theta_rad) ** 2
        raw[m] *= np.exp(-0.5 * cost)
    return raw


@kernel
def _children(candidates: np.ndarray, scores: np.ndarray, bound: float, level: int, limit: int) -> np.ndarray:
    """The four sub-blocks at ``level - 1``, in order, of the blocks at ``level`` scoring at least ``bound``
    (offsets beyond ``limit`` dropped)."""
    s = 1 << (level - 1)
    kids = np.empty((4 * candidates.shape[0], 3), np.int64)
    count = 0
    for m in range(candidates.shape[0]):
        if not scores[m] >= bound:
            continue
        for j in range(4):
            dx, dy = s * (j & 1), s * (j >> 1)   # (0, 0), (s, 0), (0, s), (s, s)
            if candidates[m, 1] + dx <= limit and candidates[m, 2] + dy <= limit:
                kids[count, 0] = candidates[m, 0]
                kids[count, 1] = candidates[m, 1] + dx
                kids[count, 2] = candidates[m, 2] + dy
                count += 1
    return kids[:count]


@kernel
def branch_and_bound(pyramid: np.ndarray, base: np.ndarray, thetas: np.ndarray, theta0: float, limit: int,
                     resolution: float, prior_std_xy_m: float, prior_std_theta_rad: float, min_score: float
                     ) -> tuple[bool, int, int, int, float]:
    """The best lattice pose of the search: over angle indices of ``thetas`` and offsets ``[0, 2 limit]``
    cells in x and y, the mean of ``pyramid[0]`` under the points whose flat cells at offset (0, 0) are
    ``base`` (angles, N), weighted by a Gaussian prior around ``theta0`` and offset ``limit`` (a
    standard deviation <= 0: no prior). Returns whether one scores at least ``min_score`` (unweighted),
    its angle index, x and y offsets and its (weighted) score."""
    levels = pyramid.shape[0]
    top = levels - 1
    step = 1 << top
    weighted = prior_std_xy_m > 0.0 or prior_std_theta_rad > 0.0
    span = 2 * limit
    per_axis = span // step + 1
    candidates = np.empty((len(thetas) * per_axis * per_axis, 3), np.int64)
    m = 0
    for a in range(len(thetas)):   # x first within a row of blocks, as :func:`_children` orders a block's four
        for oy in range(per_axis):
            for ox in range(per_axis):
                candidates[m, 0], candidates[m, 1], candidates[m, 2] = a, ox * step, oy * step
                m += 1
    scores = _scores(pyramid, top, base, candidates, limit, resolution, thetas, theta0, prior_std_xy_m,
                     prior_std_theta_rad)
    bound = 0.0 if weighted else min_score

    # Greedy dives from the best top blocks reach leaves at once: a lower bound to prune with.
    dive = np.empty((min(8, len(scores)), 3), np.int64)
    taken = np.zeros(len(scores), np.bool_)
    for i in range(len(dive)):   # the best eight, best first (of equal scores any: only the bound depends on them)
        best = -1
        for m in range(len(scores)):
            if not taken[m] and (best < 0 or scores[m] > scores[best]):
                best = m
        taken[best] = True
        dive[i] = candidates[best]
    for level in range(top, 0, -1):
        s = 1 << (level - 1)
        kids = np.empty((4 * len(dive), 3), np.int64)
        outside = np.zeros(4 * len(dive), np.bool_)
        for i in range(len(dive)):
            for j in range(4):
                x, y = dive[i, 1] + s * (j & 1), dive[i, 2] + s * (j >> 1)
                outside[4 * i + j] = x > span or y > span
                kids[4 * i + j, 0] = dive[i, 0]
                kids[4 * i + j, 1] = min(x, span)   # scored in bounds, then discarded
                kids[4 * i + j, 2] = min(y, span)
        kid_scores = _scores(pyramid, level - 1, base, kids, limit, resolution, thetas, theta0, prior_std_xy_m,
                             prior_std_theta_rad)
        for i in range(len(dive)):
            best = 4 * i
            for j in range(4):
                if outside[4 * i + j]:
                    kid_scores[4 * i + j] = -np.inf
                elif kid_scores[4 * i + j] > kid_scores[best]:
                    best = 4 * i + j
            dive[i] = kids[best]
        if level == 1:
            bound = max(bound, kid_scores.max())

    for level in range(top, 0, -1):
        candidates = _children(candidates, scores, bound, level, span)
        scores = _scores(pyramid, level - 1, base, candidates, limit, resolution, thetas, theta0, prior_std_xy_m,
                         prior_std_theta_rad)
    if len(scores) == 0:
        return False, 0, 0, 0, 0.0
    i = int(np.argmax(scores))
    raw = block_scores(pyramid[0], base, candidates[i:i + 1])[0] if weighted else scores[i]
    if raw < min_score:
        return False, 0, 0, 0, 0.0
    return True, candidates[i, 0], candidates[i, 1], candidates[i, 2], scores[i]


@kernel
def lattice_cells(points: np.ndarray, theta0: float, step: float, half: int, x0: float, y0: float, origin_x: float,
                  origin_y: float, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int, int]:
    """The search's angles ``theta0 + step * k`` for k in ``[-half, half]`` (numpy's ``theta0 + step *
    np.arange(-half, half + 1)``), and the grid cell (column, row) of each point (N, 2, robot frame) with the
    robot at ``(x0, y0)`` turned by each: ``floor((c x - s y + x0 - origin_x) / resolution)`` and
    ``floor((s x + c y + y0 - origin_y) / resolution)`` with the angle's cosine and sine (the C library's,
    which numpy's equal here), as numpy evaluated them, (angles, N) each; and the least and greatest
    column and row. Five numpy calls a search before."""
    count = points.shape[0]
    thetas = np.empty(2 * half + 1)
    cols = np.empty((thetas.shape[0], count), np.int64)
    rows = np.empty((thetas.shape[0], count), np.int64)
    for a in range(thetas.shape[0]):
        thetas[a] = theta0 + step * np.float64(a - half)
        c, s = math.cos(thetas[a]), math.sin(thetas[a])
        for n in range(count):
            px, py = points[n, 0], points[n, 1]
            cols[a, n] = math.floor((c * px - s * py + x0 - origin_x) / resolution)
            rows[a, n] = math.floor((s * px + c * py + y0 - origin_y) / resolution)
    if cols.size == 0:
        return thetas, cols, rows, 0, 0, 0, 0
    return thetas, cols, rows, cols.min(), cols.max(), rows.min(), rows.max()


@kernel
def flat_cells(cols: np.ndarray, rows: np.ndarray, col_shift: int, row_shift: int, max_col: int, max_row: int,
               width: int) -> np.ndarray:
    """Flat indices ``row * width + col`` of cells ``(rows, cols)`` shifted by ``(row_shift, col_shift)`` and
    clipped to ``[0, max_row] x [0, max_col]`` (as ``np.clip``: the upper bound wins). int32, whose half of
    the memory the branch and bound reads for every candidate makes it a tenth faster (a window of 2^31 cells
    would be a grid of 8 GB: refused)."""
    if max_row * width + max_col >= 1 << 31:
        raise ValueError("a search window of 2^31 cells or more")
    flat = np.empty(cols.shape, np.int32)
    for a in range(cols.shape[0]):
        for n in range(cols.shape[1]):
            col = min(max(cols[a, n] + col_shift, 0), max_col)
            row = min(max(rows[a, n] + row_shift, 0), max_row)
            flat[a, n] = row * width + col
    return flat
