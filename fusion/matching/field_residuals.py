"""The refinement's residuals, compiled: bilinear lookups in a match field window and the point-to-field
and point-to-line residuals with their Jacobians, one kernel for both (numba, cached on disk).

One pass over the points replaces a dozen numpy temporaries per evaluation (the refinement evaluates
a few hundred points five to ten times a scan). The arithmetic is numpy's, step for step: field
differences in float32 as the window holds them, interpolation in float64.
"""

from __future__ import annotations

import math

import numpy as np

from trundle.fusion.compiled import kernel
from trundle.fusion.mapping.nearest_cells import kept_nearest, kept_squared

# the largest coordinate a lookup may use inside a field of ``size`` cells: ``size - 1 - EDGE``
EDGE = 0.000001
# the wall arguments of :func:`field_residuals` for the point-to-field residual alone
NO_WALLS = (np.zeros((0, 0), np.int32), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.bool_))


@kernel(inline=True)
def _corners(height: int, width: int, u: float, v: float) -> tuple[int, int, int, int, float, float, bool]:
    """The flat indices of the four cells a bilinear lookup at continuous cell-centre coordinates (u, v) reads
    in a ``height`` x ``width`` field (clamped to its edge), the fractions between them, and whether (u, v)
    lies inside."""
    inside = u >= 0 and v >= 0 and u < width - 1 and v < height - 1
    u = min(max(u, 0.0), width - 1 - EDGE)
    v = min(max(v, 0.0), height - 1 - EDGE)
    c0, r0 = int(u), int(v)   # u, v >= 0: truncation is floor
    last = height * width - 1
    i00 = r0 * width + c0
    i10 = min(i00 + width, last)
    return i00, min(i00 + 1, last), i10, min(i10 + 1, last), u - c0, v - r0, inside


@kernel(inline=True)
def _interpolate(f00: float, f01: float, f10: float, f11: float, fu: float, fv: float) -> tuple[float, float, float]:
    """Value, d/du and d/dv between four cell values (field differences in the field's own precision)."""
    top, bottom = f01 - f00, f11 - f10
    du = top + fv * (bottom - top)
    left = f00 + fu * top
    dv = f10 + fu * bottom - left
    return left + fv * dv, du, dv


@kernel(inline=True)
def _sample(flat: np.ndarray, height: int, width: int, u: float, v: float) -> tuple[float, float, float, bool]:
    """Value, d/du, d/dv of a field (flat, ``height`` x ``width``) at continuous cell-centre coordinates
    (u, v), and whether they lie inside."""
    i00, i01, i10, i11, fu, fv, inside = _corners(height, width, u, v)
    value, du, dv = _interpolate(flat[i00], flat[i01], flat[i10], flat[i11], fu, fv)
    return value, du, dv, inside


@kernel
def bilinear(field: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Value, d/du, d/dv of ``field`` (H, W) at continuous cell-centre coordinates (u, v: (N,) each, u the
    column), and an inside mask (within the outermost cell centres)."""
    height, width = field.shape
    flat = field.ravel()
    n = u.shape[0]
    value, du, dv = np.empty(n), np.empty(n), np.empty(n)
    inside = np.empty(n, np.bool_)
    for i in range(n):
        value[i], du[i], dv[i], inside[i] = _sample(flat, height, width, u[i], v[i])
    return value, du, dv, inside


@kernel
def field_residuals(squared: np.ndarray, distances: np.ndarray, occupied: np.ndarray, starts: np.ndarray,
                    cols: np.ndarray, occupied_row0: int, occupied_col0: int, radius: int, nearest: np.ndarray,
                    mean: np.ndarray, normal: np.ndarray, is_line: np.ndarray, row0: int, col0: int, cx: np.ndarray,
                    cy: np.ndarray, pose_x: float, pose_y: float, rx: np.ndarray, ry: np.ndarray, resolution: float,
                    max_distance_m: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals of points against a match field window whose cell (0, 0) is the grid's (``row0``, ``col0``).

    ``occupied`` indexes the occupied cells around the window from the grid's (``occupied_row0``,
    ``occupied_col0``), and ``starts``, ``cols`` hold each row's
    (:func:`~trundle.fusion.mapping.nearest_cells.occupied_cells`). Point to field: the distance (m) to the nearest
    occupied cell, read bilinearly at the points' continuous grid cell coordinates (cx, cy), off the window the
    value far from any wall (``distances``' last); the distance of a cell is ``distances`` at its squared distance
    within ``radius`` cells, found the first time it is read and kept in ``squared`` (the window's, -1: not yet;
    :func:`~trundle.fusion.mapping.nearest_cells.kept_squared`). Point to line, with walls (``is_line`` not empty):
    where the nearest occupied cell of a point's cell has its returns on a line (``is_line``), the signed distance
    (m) of the point (rotated (rx, ry) plus the pose's (``pose_x``, ``pose_y``), grid frame) to that line (``mean``,
    ``normal``); that cell is found the first time a point's cell asks and kept in ``nearest`` (the window's, -2:
    not yet; :func:`~trundle.fusion.mapping.nearest_cells.kept_nearest`). Returns the residuals, their Jacobian
    (N, 3) with respect to the world-frame pose (x, y, theta), 0 where the point is off the window or beyond
    ``max_distance_m``, and that active mask."""
    height, width = squared.shape
    kept = squared.reshape(-1)
    d_row, d_col = row0 - occupied_row0, col0 - occupied_col0
    n = cx.shape[0]
    d = np.full(n, np.float64(distances[distances.shape[0] - 1]))   # off the window: far from any wall
    jac = np.zeros((n, 3))
    active = np.zeros(n, np.bool_)
    if height == 0 or width == 0:
        return d, jac, active
    # The kept values are read here and the helpers called only for a cell not found yet: numba reference-counts
    # the array arguments of every inlined call, found or not, which cost 50 of 60 ns a point.
    for i in range(n):
        i00, i01, i10, i11, fu, fv, inside = _corners(height, width, cx[i] - 0.5 - col0, cy[i] - 0.5 - row0)
        k00, k01, k10, k11 = kept[i00], kept[i01], kept[i10], kept[i11]
        if k00 < 0 or k01 < 0 or k10 < 0 or k11 < 0:
            k00 = kept_squared(kept, width, starts, cols, d_row, d_col, radius, i00)
            k01 = kept_squared(kept, width, starts, cols, d_row, d_col, radius, i01)
            k10 = kept_squared(kept, width, starts, cols, d_row, d_col, radius, i10)
            k11 = kept_squared(kept, width, starts, cols, d_row, d_col, radius, i11)
        value, du, dv = _interpolate(distances[k00], distances[k01], distances[k10], distances[k11], fu, fv)
        active[i] = inside and value < max_distance_m
        k = -1
        if active[i] and is_line.size:   # an active point's cell is in the window (inside)
            row, col = int(math.floor(cy[i])) - row0, int(math.floor(cx[i])) - col0
            k = nearest[row, col]
            if k < -1:
                k = kept_nearest(nearest, occupied, row, col, d_row, d_col)
        on_line = k >= 0 and is_line[k]
        if on_line:
            value = (rx[i] + pose_x - mean[k, 0]) * normal[k, 0] + (ry[i] + pose_y - mean[k, 1]) * normal[k, 1]
        if inside:
            d[i] = value
        if active[i]:
            jac[i, 0] = normal[k, 0] if on_line else du / resolution
            jac[i, 1] = normal[k, 1] if on_line else dv / resolution
            jac[i, 2] = ry[i] * -jac[i, 0] + rx[i] * jac[i, 1]
    return d, jac, active


@kernel
def _block_sum(values: np.ndarray, start: int, count: int) -> float:
    """numpy's sum of a run of at most 128 values: in order below 8, else in eight interleaved partial sums."""
    if count < 8:
        total = 0.0
        for i in range(start, start + count):
            total += values[i]
        return total
    r0, r1, r2, r3 = values[start], values[start + 1], values[start + 2], values[start + 3]
    r4, r5, r6, r7 = values[start + 4], values[start + 5], values[start + 6], values[start + 7]
    i = 8
    while i < count - count % 8:
        j = start + i
        r0 += values[j]
        r1 += values[j + 1]
        r2 += values[j + 2]
        r3 += values[j + 3]
        r4 += values[j + 4]
        r5 += values[j + 5]
        r6 += values[j + 6]
        r7 += values[j + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < count:
        total += values[start + i]
        i += 1
    return total


@kernel
def pairwise_sum(values: np.ndarray, start: int, count: int) -> float:
    """numpy's sum of ``values[start:start + count]`` (float64), step for step: its pairwise summation (runs of
    up to 128 by :func:`_block_sum`, a longer run split in halves at a multiple of eight and their sums
    added, onto the reduction's identity 0.0), so a mean here equals ``np.mean`` to the bit, signed zeros
    included. The halving runs on a stack of its own: numba cannot load a recursive function from its
    cache (it crashes)."""
    if count <= 128:
        return 0.0 + _block_sum(values, start, count)
    frames = np.empty((128, 3), np.int64)   # start, count, halves done; depth is log2(count / 128) < 60
    sums = np.empty(64)
    frames[0, 0], frames[0, 1], frames[0, 2] = start, count, 0
    depth, stacked = 1, 0
    while depth:
        depth -= 1
        s, c, split = frames[depth, 0], frames[depth, 1], frames[depth, 2]
        if c <= 128:
            sums[stacked] = _block_sum(values, s, c)
            stacked += 1
        elif split:   # both halves summed: the left's sum below the right's
            stacked -= 1
            sums[stacked - 1] = sums[stacked - 1] + sums[stacked]
        else:
            half = c // 2
            half -= half % 8
            frames[depth, 2] = 1
            frames[depth + 1, 0], frames[depth + 1, 1], frames[depth + 1, 2] = s + half, c - half, 0
            frames[depth + 2, 0], frames[depth + 2, 1], frames[depth + 2, 2] = s, half, 0
            depth += 3
    return 0.0 + sums[0]


@kernel
def match_statistics(likelihood: np.ndarray, row0: int, col0: int, px: np.ndarray, py: np.ndarray, pose: np.ndarray,
                     origin: np.ndarray, resolution: float, observed: np.ndarray, d: np.ndarray, active: np.ndarray,
                     inlier_m: float) -> tuple[float, float, float, float, np.ndarray, int]:
    """A converged match's figures in one pass: with the points (``px``, ``py``, robot frame) at ``pose`` on the
    grid (cell (0, 0) at ``origin``, ``resolution`` m), the mean likelihood (the window ``likelihood`` from
    ``row0``, ``col0``; 0 outside it), the share of points on cells the grid ``observed`` and their mean
    likelihood (0: none), the mean ``|d|`` of the inliers (``active`` and ``|d| <= inlier_m``; NaN: none),
    the inlier mask and the inliers. The points' cell coordinates are numpy's expression element by
    element, and the means numpy's (:func:`pairwise_sum` over the same values in the same order), so
    equal to the bit."""
    n = px.shape[0]
    height, width = likelihood.shape
    flat = likelihood.ravel()
    rows, cols = observed.shape
    c, s = math.cos(pose[2]), math.sin(pose[2])
    lik = np.empty(n)
    known_lik = np.empty(n)
    known = 0
    for i in range(n):
        x = (c * px[i] - s * py[i] + (pose[0] - origin[0])) / resolution
        y = (s * px[i] + c * py[i] + (pose[1] - origin[1])) / resolution
        value, _, _, inside = _sample(flat, height, width, x - 0.5 - col0, y - 0.5 - row0)
        lik[i] = value if inside else 0.0
        # floor(x) in [0, cols) exactly when x is (NaN: neither)
        if x >= 0.0 and y >= 0.0 and x < cols and y < rows and observed[int(math.floor(y)), int(math.floor(x))]:
            known_lik[known] = lik[i]
            known += 1
    inliers = np.empty(n, np.bool_)
    residuals = np.empty(n)
    count = 0
    for i in range(n):
        inliers[i] = active[i] and abs(d[i]) <= inlier_m
        if inliers[i]:
            residuals[count] = abs(d[i])
            count += 1
    score = pairwise_sum(lik, 0, n) / n if n else 0.0
    overlap = known / n if n else 0.0
    overlap_score = pairwise_sum(known_lik, 0, known) / known if known else 0.0
    residual = pairwise_sum(residuals, 0, count) / count if count else math.nan
    return score, overlap, overlap_score, residual, inliers, count
