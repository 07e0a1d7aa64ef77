"""The compiled kernels (numba) against the numpy code they replaced, on random inputs.

Each ``numpy_*`` function below is the numpy implementation as it stood in the tree before the kernel
took its place (scan_matching.py, occupancy_grid.py, geometry.py), kept here as the oracle: the kernel must give
the same numbers on whatever hypothesis draws (bit for bit where the arithmetic is the same, else to
floating-point tolerance). The numpy code kept the return moments dense (6, H, W); the grid keeps them
per cell that holds a return (:class:`trundle.fusion.mapping.occupancy_grid.ReturnMoments`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from trundle.fusion.geometry import inverse, transform_points, voxel_filter
from trundle.fusion.mapping.map_check import _submap_votes
from trundle.fusion.mapping.nearest_cells import (
    chamfer_nearest,
    occupied_cells,
    squared_distances,
    squared_nearest,
    stamped_field,
)
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid, MatchFields, _likelihood, trace_rays
from trundle.fusion.mapping.ray_casting import insert_scan, ray_cells, trace, trace_and_insert
from trundle.fusion.mapping.submaps import Submap
from trundle.fusion.mapping.wall_moments import neighbourhood_moments
from trundle.fusion.matching.block_scores import block_scores, branch_and_bound, flat_cells, lattice_cells
from trundle.fusion.matching.field_residuals import NO_WALLS, bilinear, field_residuals, match_statistics, pairwise_sum
from trundle.fusion.matching.pose_solver import DONE, solve3, solve_pose_in_window
from trundle.fusion.matching.scan_matching import SCHEDULE, STEP_TOLERANCE, score_pyramid, solve_pose
from trundle.fusion.optimization.robust_kernels import robust_loss

EXAMPLES = settings(max_examples=60, deadline=None)
DISTANCE_TRANSFORM = (cv2.DIST_L2, cv2.DIST_MASK_PRECISE)   # the match fields' OpenCV transform before the kernel


def numpy_block_scores(grid: np.ndarray, base: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    flat = grid.reshape(-1)
    index = base[candidates[:, 0]] + (candidates[:, 2] * grid.shape[1] + candidates[:, 1])[:, None]
    return flat[index].sum(axis=1, dtype=np.float64) / max(base.shape[1], 1)


def numpy_bilinear(field: np.ndarray, u: np.ndarray, v: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    height, width = field.shape
    inside = (u >= 0) & (v >= 0) & (u < width - 1) & (v < height - 1)
    u = np.clip(u, 0, width - 1.000001)
    v = np.clip(v, 0, height - 1.000001)
    c0, r0 = u.astype(np.int64), v.astype(np.int64)
    fu, fv = u - c0, v - r0
    flat = field.reshape(-1)
    i00 = r0 * width + c0
    i10 = np.minimum(i00 + width, flat.size - 1)
    f00, f01 = flat[i00], flat[np.minimum(i00 + 1, flat.size - 1)]
    f10, f11 = flat[i10], flat[np.minimum(i10 + 1, flat.size - 1)]
    top, bottom = f01 - f00, f11 - f10
    du = top + fv * (bottom - top)
    left = f00 + fu * top
    dv = f10 + fu * bottom - left
    return left + fv * dv, du, dv, inside


def numpy_field_residuals(distance: np.ndarray, row0: int, col0: int, cx: np.ndarray, cy: np.ndarray,
                          rx: np.ndarray, ry: np.ndarray, res: float, max_distance_m: float, far: float
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Off the field, a point's distance is ``far``, the field's value with no occupied cell near."""
    d, du, dv, inside = numpy_bilinear(distance, cx - 0.5 - col0, cy - 0.5 - row0)
    active = inside & (d < max_distance_m)
    d[~inside] = far
    jac = np.empty((len(d), 3))
    jac[:, 0] = np.where(active, du, 0.0) / res
    jac[:, 1] = np.where(active, dv, 0.0) / res
    jac[:, 2] = ry * -jac[:, 0] + rx * jac[:, 1]
    return d, jac, active


def numpy_line_residuals(distance: np.ndarray, nearest: np.ndarray, mean: np.ndarray, normal: np.ndarray,
                         is_line: np.ndarray, row0: int, col0: int, cx: np.ndarray, cy: np.ndarray, pose_x: float,
                         pose_y: float, rx: np.ndarray, ry: np.ndarray, res: float, max_distance_m: float, far: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    qx, qy = rx + pose_x, ry + pose_y
    d, du, dv, inside = numpy_bilinear(distance, cx - 0.5 - col0, cy - 0.5 - row0)
    col = np.clip(np.floor(cx).astype(np.int64) - col0, 0, distance.shape[1] - 1)
    row = np.clip(np.floor(cy).astype(np.int64) - row0, 0, distance.shape[0] - 1)
    k = nearest[row, col]
    active = inside & (d < max_distance_m)
    line = active & (k >= 0) & is_line[np.maximum(k, 0)]
    k = np.maximum(k, 0)
    nx, ny = normal[k, 0], normal[k, 1]
    d = np.where(line, (qx - mean[k, 0]) * nx + (qy - mean[k, 1]) * ny, d)
    d[~inside] = far
    jac = np.stack([np.where(line, nx, du / res), np.where(line, ny, dv / res), np.zeros(len(d))], axis=1)
    jac[~active] = 0.0
    jac[:, 2] = ry * -jac[:, 0] + rx * jac[:, 1]
    return d, jac, active


def numpy_ray_cells(start: np.ndarray, ends: np.ndarray) -> np.ndarray:
    delta = ends - start
    steps = np.ceil(np.abs(delta).max(axis=1)).astype(np.int64) if len(ends) else np.zeros(0, np.int64)
    total = int(steps.sum())
    if total == 0:
        return np.zeros((0, 2), np.int64)
    ray = np.repeat(np.arange(len(ends)), steps)
    t = (np.arange(total) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[ray]
    x = np.floor(start[0] + t * delta[:, 0][ray]).astype(np.int64)
    y = np.floor(start[1] + t * delta[:, 1][ray]).astype(np.int64)
    keep = (x != np.floor(ends[:, 0]).astype(np.int64)[ray]) | (y != np.floor(ends[:, 1]).astype(np.int64)[ray])
    return np.stack([y[keep], x[keep]], axis=1)


def numpy_update(log_odds: np.ndarray, observed: np.ndarray, moments: np.ndarray, hit_flat: np.ndarray,
                 crossed_flat: np.ndarray, offsets: np.ndarray, l_hit: float, l_miss: float, l_min: float,
                 l_max: float) -> None:
    if len(hit_flat):
        u, v = offsets.T
        for k, values in enumerate((np.ones_like(u), u, v, u * u, u * v, v * v)):
            np.add.at(moments[k].reshape(-1), hit_flat, values.astype(np.float32))
    is_hit = np.zeros(log_odds.size, bool)
    is_hit[hit_flat] = True
    free_flat = crossed_flat[~is_hit[crossed_flat]]
    flat = log_odds.reshape(-1)
    flat[free_flat] = np.maximum(flat[free_flat] + l_miss, l_min)
    flat[hit_flat] = np.minimum(flat[hit_flat] + l_hit, l_max)
    seen = observed.reshape(-1)
    seen[free_flat] = True
    seen[hit_flat] = True


def numpy_neighbourhood_moments(moments: np.ndarray, log_odds: np.ndarray, rows: np.ndarray, cols: np.ndarray
                                ) -> tuple[np.ndarray, np.ndarray]:
    height, width = log_odds.shape
    m = moments[:, rows, cols].astype(np.float64)
    mean = np.stack([cols + m[1] / m[0], rows + m[2] / m[0]], axis=1)
    sums = np.zeros((len(rows), 6))
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = rows + dr, cols + dc
            ok = (r >= 0) & (c >= 0) & (r < height) & (c < width)
            ok[ok] &= log_odds[r[ok], c[ok]] > 0.0
            n = moments[:, r[ok], c[ok]].astype(np.float64)
            ox, oy = c[ok] - mean[ok, 0], r[ok] - mean[ok, 1]
            sums[ok] += np.stack([n[0], n[1] + ox * n[0], n[2] + oy * n[0], n[3] + 2 * ox * n[1] + ox * ox * n[0],
                                  n[4] + ox * n[2] + oy * n[1] + ox * oy * n[0],
                                  n[5] + 2 * oy * n[2] + oy * oy * n[0]], axis=1)
    return mean, sums


def likelihoods(shape: tuple[int, int]) -> st.SearchStrategy[np.ndarray]:
    """Float32 fields as the likelihood field holds them: 0, or exp(-d^2 / 2) for d up to 4."""
    value = st.one_of(st.just(0.0), st.floats(0.0, 4.0).map(lambda d: math.exp(-0.5 * d * d)))
    return hnp.arrays(np.float32, shape, elements=value.map(np.float32))


@st.composite
def search_problems(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grid, the flat cells of rotated points at offset (0, 0), and candidates whose cells stay inside."""
    height, width, limit = draw(st.integers(3, 30)), draw(st.integers(3, 30)), draw(st.integers(0, 2))
    limit = min(limit, (height - 1) // 2, (width - 1) // 2)
    angles, points = draw(st.integers(1, 4)), draw(st.integers(0, 40))
    grid = draw(likelihoods((height, width)))
    rows = draw(hnp.arrays(np.int64, (angles, points), elements=st.integers(0, height - 1 - 2 * limit)))
    cols = draw(hnp.arrays(np.int64, (angles, points), elements=st.integers(0, width - 1 - 2 * limit)))
    count = draw(st.integers(1, 30))
    candidates = np.stack([draw(hnp.arrays(np.int64, count, elements=st.integers(0, angles - 1))),
                           draw(hnp.arrays(np.int64, count, elements=st.integers(0, 2 * limit))),
                           draw(hnp.arrays(np.int64, count, elements=st.integers(0, 2 * limit)))], axis=1)
    return grid, rows * width + cols, candidates


@EXAMPLES
@given(search_problems())
def test_block_scores_equal_numpy_to_the_bit(problem: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    grid, base, candidates = problem
    np.testing.assert_array_equal(block_scores(grid, base, candidates), numpy_block_scores(grid, base, candidates))


coordinates = st.floats(-3.0, 40.0, allow_nan=False)


@st.composite
def field_points(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A float32 distance field (m) and continuous coordinates in and around it."""
    height, width, n = draw(st.integers(1, 25)), draw(st.integers(1, 25)), draw(st.integers(0, 30))
    field = draw(hnp.arrays(np.float32, (height, width), elements=st.floats(0.0, 0.5, width=32)))
    cx, cy = (draw(hnp.arrays(np.float64, n, elements=coordinates)) for _ in range(2))
    return field, cx, cy


def assert_same(actual: tuple[np.ndarray, ...], expected: tuple[np.ndarray, ...]) -> None:
    for a, e in zip(actual, expected, strict=True):
        np.testing.assert_allclose(a, e, rtol=1e-12, atol=1e-12)


@EXAMPLES
@given(field_points())
def test_bilinear_equals_numpy(problem: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    field, u, v = problem
    assert_same(bilinear(field, u, v), numpy_bilinear(field, u, v))


def opencv_nearest(occupied: np.ndarray) -> np.ndarray:
    """Each cell's nearest occupied cell (its index in ``occupied``, -1 where not occupied; -1: none) as
    OpenCV's labelled distance transform names it: the label less one, its zero pixels being labelled
    1, 2, ... in row-major order."""
    if not (occupied >= 0).any():
        return np.full(occupied.shape, -1, np.int32)
    image = np.where(occupied >= 0, 0, 255).astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(image, cv2.DIST_L2, cv2.DIST_MASK_PRECISE,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    return labels - np.int32(1)


def occupied_index(mask: np.ndarray) -> np.ndarray:
    """The index occupied_cells makes of a mask: each true cell's row-major position, -1 elsewhere."""
    index = np.full(mask.shape, -1, np.int32)
    index[mask] = np.arange(int(mask.sum()), dtype=np.int32)
    return index


def occupied_rows(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows' starts and the columns occupied_cells gives of a mask: row i's true columns are
    ``cols[starts[i]:starts[i + 1]]``, by numpy's nonzero and searchsorted."""
    rows, cols = np.nonzero(mask)
    return np.searchsorted(rows, np.arange(mask.shape[0] + 1)), cols


def brute_force_squared(mask: np.ndarray, margin: int, height: int, width: int, radius: int) -> np.ndarray:
    """The squared distance (cells^2) of each cell of the window ``margin`` cells inside ``mask`` to its nearest
    true cell, ``radius^2 + 1`` beyond ``radius``: every pair measured."""
    seeds = np.argwhere(mask)
    rows, cols = np.mgrid[margin:margin + height, margin:margin + width]
    if not len(seeds):
        return np.full((height, width), radius * radius + 1, np.int64)
    squared = ((rows[..., None] - seeds[:, 0]) ** 2 + (cols[..., None] - seeds[:, 1]) ** 2).min(axis=-1)
    return np.minimum(squared, radius * radius + 1)


@st.composite
def occupancy_windows(draw: st.DrawFn) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
    """Occupied cells over a window grown by a margin, a radius, and continuous coordinates in and around
    the window: (mask, margin, radius, cx, cy)."""
    height, width, margin = draw(st.integers(1, 25)), draw(st.integers(1, 25)), draw(st.integers(0, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    mask = rng.random((height + 2 * margin, width + 2 * margin)) < draw(st.floats(0.0, 0.3))
    mask.flat[rng.integers(mask.size)] = True   # a refinement reads walls where there are some
    n = draw(st.integers(0, 30))
    cx, cy = (draw(hnp.arrays(np.float64, n, elements=coordinates)) for _ in range(2))
    return mask, margin, draw(st.integers(1, 12)), cx, cy


def window_fields(mask: np.ndarray, margin: int, radius: int, res: float, max_distance_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arguments field_residuals finds a window's distances with (nothing found yet, their values per
    squared distance, the occupied cells' index) and the distance field every pair measured gives."""
    height, width = mask.shape[0] - 2 * margin, mask.shape[1] - 2 * margin
    distances = np.minimum(squared_distances(radius) * np.float32(res), np.float32(max_distance_m))
    dense = distances[brute_force_squared(mask, margin, height, width, radius)]
    return np.full((height, width), -1, np.int32), distances, dense


@EXAMPLES
@given(occupancy_windows(), st.integers(-3, 3), st.integers(-3, 3), st.floats(0.01, 0.2), st.floats(0.05, 0.7))
def test_field_residuals_equal_numpy(problem: tuple[np.ndarray, int, int, np.ndarray, np.ndarray], row0: int,
                                     col0: int, res: float, max_distance_m: float) -> None:
    """Point to field, each distance found where it is read, against numpy's bilinear lookups in the distance
    field every pair measured gives; the distances kept are those of the field."""
    mask, margin, radius, cx, cy = problem
    squared, distances, dense = window_fields(mask, margin, radius, res, max_distance_m)
    rx, ry = 0.3 * cx - 1.0, 0.2 * cy + 0.5
    assert_same(field_residuals(squared, distances, occupied_index(mask), *occupied_rows(mask), row0 - margin,
                                col0 - margin, radius,
                                *NO_WALLS, row0, col0, cx, cy, 0.3, -0.2, rx, ry, res, max_distance_m),
                numpy_field_residuals(dense, row0, col0, cx, cy, rx, ry, res, max_distance_m, distances[-1]))
    found = squared >= 0
    assert found.any() == bool(len(cx))   # every point reads four cells, each found once and kept
    np.testing.assert_array_equal(distances[squared[found]], dense[found])


@EXAMPLES
@given(occupancy_windows(), st.integers(0, 3), st.integers(0, 3), st.integers(0, 2**32 - 1), st.floats(-2.0, 2.0),
       st.floats(-2.0, 2.0))
def test_line_residuals_equal_numpy(problem: tuple[np.ndarray, int, int, np.ndarray, np.ndarray], row0: int,
                                    col0: int, seed: int, pose_x: float, pose_y: float) -> None:
    """Point to line where a point's cell's nearest occupied cell (OpenCV's label, over the occupied cells of
    the window grown by a margin) lies on a line, to the field elsewhere."""
    mask, margin, radius, cx, cy = problem
    rng = np.random.default_rng(seed)
    squared, distances, dense = window_fields(mask, margin, radius, 0.05, 0.5)
    occupied = occupied_index(mask)
    walls = int(mask.sum())
    mean = rng.uniform(-1.0, 2.0, (walls, 2))
    angle = rng.uniform(-math.pi, math.pi, walls)
    normal = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
    is_line = rng.random(walls) < 0.7
    rx, ry = 0.05 * cx - 0.5, 0.05 * cy + 0.2
    nearest = opencv_nearest(occupied)[margin:margin + dense.shape[0], margin:margin + dense.shape[1]]
    found = np.full(dense.shape, -2, np.int32)
    assert_same(field_residuals(squared, distances, occupied, *occupied_rows(mask), row0 - margin, col0 - margin,
                                radius, found, mean, normal, is_line, row0, col0, cx, cy, pose_x, pose_y, rx, ry, 0.05,
                                0.5),
                numpy_line_residuals(dense, nearest, mean, normal, is_line, row0, col0, cx, cy, pose_x, pose_y, rx,
                                     ry, 0.05, 0.5, distances[-1]))
    np.testing.assert_array_equal(found[found > -2], nearest[found > -2])   # the labels kept are OpenCV's


@EXAMPLES
@given(st.integers(1, 40), st.integers(1, 40), st.floats(0.0, 0.1), st.integers(0, 2**32 - 1), st.integers(1, 12),
       st.integers(0, 6), st.integers(0, 6))
def test_squared_nearest_equals_the_stamp(height: int, width: int, density: float, seed: int, radius: int, top: int,
                                          left: int) -> None:
    """A cell's squared distance found from the rows' occupied cells (what a refinement reads) is what every pair
    measured gives (within the radius; one more beyond), and what a stamp of a field that falls with the distance
    reads."""
    rng = np.random.default_rng(seed)
    mask = rng.random((height, width)) < density
    mask[rng.random(height) < 0.15, rng.integers(0, width):] = True   # walls along rows: many columns to bisect
    rows, cols = np.nonzero(mask)
    top, left = min(top, height - 1), min(left, width - 1)
    starts, occupied_cols = occupied_rows(mask)
    found = np.array([[squared_nearest(starts, occupied_cols, top + i, left + j, radius) for j in range(width - left)]
                      for i in range(height - top)])
    full = brute_force_squared(np.pad(mask, ((0, top), (0, left))), 0, height, width, radius)
    np.testing.assert_array_equal(found, full[top:, left:])
    falling = -np.arange(radius * radius + 2, dtype=np.float32)   # the stamp's squared distance, negated
    stamped = stamped_field(rows, cols, top, left, height - top, width - left, radius, falling)
    np.testing.assert_array_equal(-stamped, found)


ends = st.floats(-60.0, 60.0, allow_nan=False)


@EXAMPLES
@given(st.floats(-20.0, 20.0), st.floats(-20.0, 20.0), hnp.arrays(np.float64, st.tuples(st.integers(0, 20), st.just(2)),
                                                                  elements=ends))
def test_ray_cells_equal_numpy_to_the_bit(x: float, y: float, targets: np.ndarray) -> None:
    """As (row, col), and as flat indices of a grid 1000 cells wide (the rays' cells as insert_flat reads them)."""
    start = np.array([x, y])
    expected = numpy_ray_cells(start, targets)
    np.testing.assert_array_equal(ray_cells(start, targets), expected)
    np.testing.assert_array_equal(ray_cells(start, targets, 1000), expected[:, :1] * 1000 + expected[:, 1:])


def sparse(moments: np.ndarray, holding: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Dense moments (6, H, W) as the grid keeps them: a slot per cell (0: none) into rows; row 0 zero.
    The cells ``holding`` returns get a row in the order of their flat index."""
    slots = np.zeros(holding.shape, np.int32)
    cells = np.flatnonzero(holding)
    slots.reshape(-1)[cells] = np.arange(1, len(cells) + 1)
    rows = np.zeros((1 + holding.size + 100, 6), np.float32)   # room for a row per return
    rows[1:len(cells) + 1] = moments.reshape(6, -1)[:, cells].T
    return slots, rows, len(cells) + 1


def numpy_trace_rays(origin: np.ndarray, resolution: float, sensor_xy: np.ndarray, hits_xy: np.ndarray,
                     free_ends_xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """occupancy_grid.trace_rays as numpy made it before the kernel: crossed, hit cells, offsets, box."""
    everything = np.vstack([sensor_xy[None], hits_xy, free_ends_xy])
    hit_coords = (hits_xy - origin) / resolution
    hit_cells = np.floor(hit_coords).astype(np.int64)
    crossed = numpy_ray_cells((sensor_xy - origin) / resolution,
                              np.vstack([hit_coords, (free_ends_xy - origin) / resolution]))
    return crossed, hit_cells[:, ::-1], hit_coords - hit_cells, everything.min(axis=0), everything.max(axis=0)


@EXAMPLES
@given(hnp.arrays(np.float64, 2, elements=st.floats(-50.0, 50.0)), st.sampled_from([0.05, 0.1, 0.025, 0.3]),
       hnp.arrays(np.float64, 2, elements=st.floats(-20.0, 20.0)),
       hnp.arrays(np.float64, st.tuples(st.integers(0, 30), st.just(2)), elements=st.floats(-20.0, 20.0)),
       hnp.arrays(np.float64, st.tuples(st.integers(0, 5), st.just(2)), elements=st.floats(-20.0, 20.0)))
def test_trace_equals_numpy_to_the_bit(origin: np.ndarray, resolution: float, sensor: np.ndarray, hits: np.ndarray,
                                       free: np.ndarray) -> None:
    """The rays' cells, the returns' cells and offsets and the bounding box (NaN-free inputs: a scan's points)."""
    for actual, expected in zip(trace(origin, resolution, sensor, hits, free),
                                numpy_trace_rays(origin, resolution, sensor, hits, free), strict=True):
        assert actual.dtype == expected.dtype
        np.testing.assert_array_equal(actual, expected)


@EXAMPLES
@given(st.integers(1, 12), st.integers(1, 12), st.integers(0, 2**32 - 1), st.integers(0, 25), st.integers(0, 60),
       st.integers(-3, 3), st.integers(-3, 3), st.booleans())
def test_insert_scan_equals_the_numpy_flat_indices_and_updates(height: int, width: int, seed: int, hits: int,
                                                               crossed: int, row_shift: int, col_shift: int,
                                                               with_moments: bool) -> None:
    """One call per scan against insert_traced's numpy flat indices and the updates it replaced: log-odds
    (clamped, once per scan however many rays cross a cell), observed flags and moments; the swept box grown by
    the rays'."""
    rng = np.random.default_rng(seed)
    log_odds = rng.uniform(-2.0, 3.5, (height, width)).astype(np.float32)
    observed = rng.random((height, width)) < 0.5
    holding = rng.random((height, width)) < 0.3
    moments = np.where(holding, rng.uniform(0.0, 5.0, (6, height, width)), 0.0).astype(np.float32)
    slots, rows, count = sparse(moments, holding)
    def cells(n: int) -> np.ndarray:   # (row, col) on the shifted lattice, inside the grid
        return np.column_stack([rng.integers(0, height, n) - row_shift, rng.integers(0, width, n) - col_shift])
    hit_cells, crossed_cells, offsets = cells(hits), cells(crossed), rng.random((hits, 2))
    hit_flat = (hit_cells[:, 0] + row_shift) * width + hit_cells[:, 1] + col_shift
    crossed_flat = (crossed_cells[:, 0] + row_shift) * width + crossed_cells[:, 1] + col_shift
    expected = (log_odds.copy(), observed.copy(), moments.copy())
    numpy_update(*expected, hit_flat, crossed_flat, offsets, 0.8473, -0.4055, -2.0, 3.5)
    swept, low, high = np.array([0.5, -1.0, 2.0, 0.0]), rng.uniform(-2.0, 2.0, 2), rng.uniform(-2.0, 2.0, 2)
    expected_swept = np.concatenate([np.minimum(swept[:2], low), np.maximum(swept[2:], high)])
    used, flat = insert_scan(log_odds, observed, slots if with_moments else np.zeros((0, 0), np.int32), rows, count,
                             hit_cells, offsets, crossed_cells, row_shift, col_shift, 0.8473, -0.4055, -2.0, 3.5, swept,
                             low, high)
    np.testing.assert_array_equal(swept, expected_swept)
    np.testing.assert_array_equal(flat, hit_flat)
    np.testing.assert_array_equal(log_odds, expected[0])
    np.testing.assert_array_equal(observed, expected[1])
    if with_moments:
        assert used == 1 + int(np.count_nonzero(expected[2][0]))
        np.testing.assert_array_equal(rows[slots].transpose(2, 0, 1), expected[2])
    else:
        assert used == count


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.05, 0.1, 0.3]), st.integers(0, 30), st.integers(0, 4),
       st.floats(0.5, 12.0), st.booleans())
def test_trace_and_insert_equals_trace_then_insert_scan(seed: int, resolution: float, hits: int, free: int,
                                                        reach: float, with_moments: bool) -> None:
    """insert_rays' one call against the two it replaces (trace, then insert_scan when the box is inside a grid
    of 4 x 4 m; the one call traces flat indices): the same cells, flags, moments, rows in use and returns'
    indices and swept box; outside, nothing written."""
    rng = np.random.default_rng(seed)
    origin = np.array([-2.0, -2.0]) + rng.uniform(-0.1, 0.1, 2)
    size = int(round(4.0 / resolution))
    log_odds = rng.uniform(-2.0, 3.5, (size, size)).astype(np.float32)
    observed = rng.random((size, size)) < 0.5
    holding = rng.random((size, size)) < 0.3
    moments = np.where(holding, rng.uniform(0.0, 5.0, (6, size, size)), 0.0).astype(np.float32)
    slots, rows, count = sparse(moments, holding)
    if not with_moments:
        slots = np.zeros((0, 0), np.int32)
    sensor = rng.uniform(-0.5, 0.5, 2)
    hits_xy, free_xy = (sensor + rng.uniform(-reach, reach, (n, 2)) / 2.0 for n in (hits, free))
    expected = [array.copy() for array in (log_odds, observed, slots, rows)]
    traced = trace(origin, resolution, sensor, hits_xy, free_xy)
    inside = bool(np.all((traced[3] - origin) / resolution >= 0) and np.all((traced[4] - origin) / resolution < size))
    expected_count, expected_flat = count, np.empty(0, np.int64)
    swept, expected_swept = np.array([0.1, 0.2, 0.3, 0.4]), np.array([0.1, 0.2, 0.3, 0.4])
    if inside:
        expected_count, expected_flat = insert_scan(*expected, count, traced[1], traced[2], traced[0], 0, 0, 0.8473,
                                                    -0.4055, -2.0, 3.5, expected_swept, traced[3], traced[4])
    done, used, flat = trace_and_insert(log_odds, observed, slots, rows, count, origin, resolution, sensor, hits_xy,
                                        free_xy, 0.8473, -0.4055, -2.0, 3.5, swept)
    assert done == inside and used == expected_count
    np.testing.assert_array_equal(swept, expected_swept)
    np.testing.assert_array_equal(flat, expected_flat)
    for actual, wanted in zip((log_odds, observed, slots, rows), expected, strict=True):
        np.testing.assert_array_equal(actual, wanted)


@EXAMPLES
@given(st.integers(1, 12), st.integers(1, 12), st.integers(0, 2**32 - 1))
def test_neighbourhood_moments_equal_numpy(height: int, width: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    log_odds = rng.uniform(-2.0, 3.5, (height, width)).astype(np.float32)
    counts = rng.integers(1, 6, (height, width)).astype(np.float32)
    u, v = rng.random((2, height, width)), rng.random((2, height, width))
    moments = np.stack([counts, counts * u[0], counts * v[0], counts * u[1] ** 2, counts * u[1] * v[1],
                        counts * v[1] ** 2]).astype(np.float32)
    slots, table, _ = sparse(moments, np.ones((height, width), bool))
    rows, cols = np.nonzero(log_odds > 0.0)
    assert_same(neighbourhood_moments(slots, table, log_odds, rows, cols),
                numpy_neighbourhood_moments(moments, log_odds, rows, cols))


def numpy_line_data(grid: LogOddsGrid, rows: np.ndarray, cols: np.ndarray, min_flatness: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LogOddsGrid.line_data as numpy computed it from the neighbourhood moments before line_terms."""
    assert grid.moments is not None
    mean, sums = neighbourhood_moments(grid.moments.slots, grid.moments.rows, grid.log_odds, rows, cols)
    mx, my = sums[:, 1] / sums[:, 0], sums[:, 2] / sums[:, 0]
    sxx, sxy, syy = (sums[:, 3] / sums[:, 0] - mx * mx, sums[:, 4] / sums[:, 0] - mx * my,
                     sums[:, 5] / sums[:, 0] - my * my)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    spread = np.sqrt(((sxx - syy) / 2.0) ** 2 + sxy ** 2)
    centre = (sxx + syy) / 2.0
    flat = 1.0 - (centre - spread) / np.maximum(centre + spread, 1e-12)
    return (grid.origin + mean * grid.resolution, np.stack([-np.sin(angle), np.cos(angle)], axis=1),
            (flat >= min_flatness) & (sums[:, 0] >= 3))


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.integers(1, 6), st.floats(0.0, 1.0), st.sampled_from([0.05, 0.1, 0.025]))
def test_line_data_equals_numpy_to_the_bit(seed: int, scans: int, min_flatness: float, resolution: float) -> None:
    """The walls' means, normals and line flags (line_terms, then numpy's arctan2) against the numpy lines they
    replaced, on a grid of scans of walls, a corner and clutter: equal to the bit."""
    rng = np.random.default_rng(seed)
    grid = LogOddsGrid(resolution, subcell=True)
    for _ in range(scans):
        sensor = rng.uniform(-1.0, 1.0, 2)
        wall = np.stack([np.linspace(-3.0, 3.0, 120), np.full(120, 2.0) + rng.normal(0.0, 0.01, 120)], axis=1)
        side = np.stack([np.full(60, 3.0) + rng.normal(0.0, 0.01, 60), np.linspace(-2.0, 2.0, 60)], axis=1)
        clutter = rng.uniform(-3.0, 3.0, (30, 2))
        grid.insert_rays(sensor, np.vstack([wall, side, clutter]))
    rows, cols = np.nonzero(grid.log_odds > 0.0)
    actual = grid.line_data(rows, cols, min_flatness)
    expected = numpy_line_data(grid, rows, cols, min_flatness)
    for a, e in zip(actual, expected, strict=True):
        assert a.shape == e.shape and a.dtype == e.dtype
        np.testing.assert_array_equal(a, e)


def numpy_max_pool(prev: np.ndarray, s: int) -> np.ndarray:
    level = prev.copy()
    if s < level.shape[1]:
        np.maximum(level[:, :-s], prev[:, s:], out=level[:, :-s])
    if s < level.shape[0]:
        np.maximum(level[:-s, :], level[s:, :], out=level[:-s, :])
    return level


@EXAMPLES
@given(st.integers(1, 40), st.integers(1, 40), st.integers(1, 8), st.integers(0, 130), st.integers(0, 2**32 - 1))
def test_the_pyramid_equals_numpy_to_the_bit(height: int, width: int, levels: int, pad: int, seed: int) -> None:
    """OpenCV's maxima against numpy's, level by level, shifts past the edge and no border included."""
    rng = np.random.default_rng(seed)
    field = np.where(rng.random((height, width)) < 0.3, rng.random((height, width)), 0.0).astype(np.float32)
    expected = [np.pad(field, pad)]
    for h in range(1, levels):
        expected.append(numpy_max_pool(expected[-1], 1 << (h - 1)))
    np.testing.assert_array_equal(score_pyramid(field, levels, pad), np.stack(expected))


def test_a_pyramid_reuses_memory_only_when_no_array_uses_it() -> None:
    """A pyramid takes the last pyramid's memory once that is dropped, and writes every cell of it (the values
    left there are another field's); a pyramid alive, or a level kept past its pyramid, keeps its own."""
    rng = np.random.default_rng(7)
    big, small = rng.random((60, 70)).astype(np.float32), rng.random((30, 20)).astype(np.float32)

    def address(array: np.ndarray) -> int:
        return int(array.__array_interface__["data"][0])

    first = score_pyramid(big, 4)
    second = score_pyramid(big, 4)
    assert not np.shares_memory(first, second)
    np.testing.assert_array_equal(first, second)
    where = address(second)
    del second
    third = score_pyramid(small, 3)
    assert address(third) == where
    expected = [np.pad(small, 4)]
    for h in range(1, 3):
        expected.append(numpy_max_pool(expected[-1], 1 << (h - 1)))
    np.testing.assert_array_equal(third, np.stack(expected))
    level = third[1]
    del third
    fourth = score_pyramid(big, 4)
    assert not np.shares_memory(fourth, level) and not np.shares_memory(fourth, first)
    np.testing.assert_array_equal(level, expected[1])


@EXAMPLES
@given(st.integers(1, 40), st.integers(1, 40), st.floats(0.0, 0.08), st.integers(0, 2**32 - 1), st.integers(1, 12),
       st.integers(0, 6), st.integers(0, 6))
def test_the_stamped_likelihood_equals_opencvs_transform(height: int, width: int, density: float, seed: int,
                                                        radius: int, top: int, left: int) -> None:
    """The likelihood stamped over a window inside the padded array against the OpenCV transform of that array:
    equal to float32 rounding up to the radius, the value for none beyond."""
    occupied = np.random.default_rng(seed).random((height, width)) < density
    rows, cols = np.nonzero(occupied)
    top, left = min(top, height - 1), min(left, width - 1)
    inner = (slice(top, height), slice(left, width))   # a window inside the padded array
    values = _likelihood(squared_distances(radius), 0.05, 0.05)
    likelihood = stamped_field(rows, cols, top, left, height - top, width - left, radius, values)
    if not occupied.any():
        assert np.all(likelihood == values[-1])
        return
    expected = cv2.distanceTransform(np.where(occupied, 0, 255).astype(np.uint8), *DISTANCE_TRANSFORM)[inner]
    within = expected <= radius - 1e-3
    np.testing.assert_allclose(likelihood[within], _likelihood(expected, 0.05, 0.05)[within], rtol=1e-5, atol=1e-7)
    assert np.all(likelihood[expected > radius + 1e-3] == values[-1])


@EXAMPLES
@given(st.integers(1, 60), st.integers(1, 60), st.floats(0.0, 0.05), st.integers(0, 2**32 - 1),
       st.sampled_from([0.05, 0.1, 0.025]), st.floats(0.1, 1.0), st.floats(0.01, 0.3))
def test_the_match_fields_to_their_radii_equal_those_stamped_to_the_margin(
        height: int, width: int, density: float, seed: int, resolution: float, max_distance: float, sigma: float
) -> None:
    """Beyond 4 sigma the likelihood, and beyond the cap the capped distance, no longer change: the likelihood
    stamped to MatchFields.likelihood_radius and the distances looked up to its radius are, to the bit, the
    fields stamped to the margin (every occupied cell a window gathers)."""
    occupied = np.random.default_rng(seed).random((height, width)) < density
    rows, cols = np.nonzero(occupied)
    fields = MatchFields(LogOddsGrid(resolution), max_distance, sigma, False, 0.8)
    assert fields.margin == fields.radius + 2 and fields.likelihood_radius <= fields.radius

    def stamped(radius: int, values: np.ndarray) -> np.ndarray:
        return stamped_field(rows, cols, 0, 0, height, width, radius, values)

    def likelihood(radius: int) -> np.ndarray:
        return _likelihood(squared_distances(radius), resolution, sigma)

    def distance(radius: int) -> np.ndarray:
        return np.minimum(squared_distances(radius) * np.float32(resolution), np.float32(max_distance))

    np.testing.assert_array_equal(stamped(fields.likelihood_radius, likelihood(fields.likelihood_radius)),
                                  stamped(fields.margin, likelihood(fields.margin)))
    np.testing.assert_array_equal(fields.distances, distance(fields.radius))
    margin = distance(fields.margin)[brute_force_squared(occupied, 0, height, width, fields.margin)]
    np.testing.assert_array_equal(fields.distances[brute_force_squared(occupied, 0, height, width, fields.radius)],
                                  margin)


@st.composite
def matching_problems(draw: st.DrawFn) -> tuple[LogOddsGrid, np.ndarray, np.ndarray]:
    """A grid of a few random rooms' walls seen from random places, a scan's points and a start pose."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    grid = LogOddsGrid(0.05, subcell=True)
    angles = np.linspace(-math.pi, math.pi, 120, endpoint=False)
    rays = np.column_stack([np.cos(angles), np.sin(angles)])
    walls = rng.uniform(1.0, 4.0, (120, 1)) * rays
    for _ in range(draw(st.integers(1, 3))):
        sensor = rng.uniform(-0.3, 0.3, 2)
        grid.insert_rays(sensor, walls + 0.01 * rng.standard_normal(walls.shape))
    points = walls[rng.random(120) < draw(st.floats(0.2, 1.0))] + 0.01 * rng.standard_normal((1, 2))
    start = np.array([draw(st.floats(-0.2, 0.2)), draw(st.floats(-0.2, 0.2)), draw(st.floats(-0.1, 0.1))])
    return grid, points, start


@settings(max_examples=40, deadline=None)
@given(matching_problems(), st.booleans(), st.integers(0, 20))
def test_compiled_refinement_equals_the_python_loop(problem: tuple[LogOddsGrid, np.ndarray, np.ndarray],
                                                    walls: bool, iterations: int) -> None:
    """The whole solve in one kernel against the loop it replaced: the LM core (solve_pose) over numpy
    Huber weights of field_residuals, growing the window where a step leaves it."""
    grid, points, start = problem
    fields = grid.match_fields(0.5, 0.05, lines=True)
    px, py = points[:, 0], points[:, 1]

    def placed(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rx, ry = c * px - s * py, s * px + c * py
        return rx, ry, (rx + (pose[0] - grid.origin[0])) / 0.05, (ry + (pose[1] - grid.origin[1])) / 0.05

    def evaluate(pose: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        rx, ry, cx, cy = placed(pose)
        window = fields.around(cx, cy)
        assert window.lines is not None
        wall_arrays = (window.lines.nearest, window.lines.mean, window.lines.normal, window.lines.is_line)
        d, jac, active = field_residuals(window.squared, window.distances, window.occupied, window.occupied_starts,
                                         window.occupied_cols, window.occupied_row0, window.occupied_col0,
                                         window.radius, *(wall_arrays if walls else NO_WALLS),
                                         window.row0, window.col0, cx, cy, float(pose[0]), float(pose[1]), rx, ry,
                                         0.05, 0.5)
        loss, weight = robust_loss(d * d, "huber", 0.05)
        return float(loss.sum()), d, jac, weight, active

    _, _, cx, cy = placed(start)
    window = fields.around(cx[:1], cy[:1])   # a window about one point: the first evaluation asks to grow it
    grown = 0
    while True:
        assert window.lines is not None
        height, width = window.squared.shape
        wall_arrays = (window.lines.nearest, window.lines.mean, window.lines.normal, window.lines.is_line)
        status, box, pose, count, *state = solve_pose_in_window(
            window.squared, window.distances, window.occupied, window.occupied_starts, window.occupied_cols,
            window.occupied_row0, window.occupied_col0, window.radius, *(wall_arrays if walls else NO_WALLS),
            np.array([window.row0, window.row0 + height, window.col0, window.col0 + width]), np.array(fields.extent),
            px, py, start, grid.origin, 0.05, 0.5, 0.05, iterations, SCHEDULE, STEP_TOLERANCE)
        if status == DONE:
            break
        grown += 1
        window = fields.around(box[:2], box[2:])
    assert grown >= 1
    expected_pose, expected_iterations, expected = solve_pose(evaluate, start, iterations)
    assert count == expected_iterations
    np.testing.assert_allclose(pose, expected_pose, rtol=0.0, atol=1e-9)
    for actual, wanted in zip(state, expected, strict=True):
        np.testing.assert_allclose(actual, wanted, rtol=1e-9, atol=1e-9)


@EXAMPLES
@given(hnp.arrays(np.float64, (3, 3), elements=st.floats(-1e3, 1e3)), hnp.arrays(np.float64, 3,
                                                                                 elements=st.floats(-1e3, 1e3)))
def test_solve3_equals_numpy(matrix: np.ndarray, rhs: np.ndarray) -> None:
    spd = matrix @ matrix.T + 1e-3 * np.eye(3)   # the damped normal equations are symmetric positive definite
    np.testing.assert_allclose(solve3(spd, rhs), np.linalg.solve(spd, rhs), rtol=1e-6,
                               atol=1e-9 * np.abs(np.linalg.solve(spd, rhs)).max())
    singular = np.ones((3, 3))
    assert np.all(np.isnan(solve3(singular, rhs)))


def numpy_branch_and_bound(pyramid: np.ndarray, base: np.ndarray, thetas: np.ndarray, t0: float, limit: int,
                           res: float, prior_std_xy_m: float | None, prior_std_theta_rad: float | None,
                           min_score: float) -> tuple[bool, int, int, int, float]:
    """correlative_search's branch and bound as it stood in numpy (after its pyramid and base)."""
    def shifts(level: int) -> np.ndarray:
        s = 1 << (level - 1)
        return np.array([[0, 0, 0], [0, s, 0], [0, 0, s], [0, s, s]], np.int64)

    def children(candidates: np.ndarray, level: int, bound: int) -> np.ndarray:
        kids = (candidates[:, None, :] + shifts(level)[None]).reshape(-1, 3)
        return kids[(kids[:, 1] <= bound) & (kids[:, 2] <= bound)]

    def scores_of(level: int, candidates: np.ndarray) -> np.ndarray:
        raw = block_scores(pyramid[level], base, candidates)
        if prior_std_xy_m is None and prior_std_theta_rad is None:
            return raw
        cost = np.zeros(len(candidates))
        if prior_std_xy_m is not None:
            near = np.clip(0, candidates[:, 1:] - limit, candidates[:, 1:] - limit + (1 << level) - 1)
            cost += (res * res) * (near ** 2).sum(axis=1) / prior_std_xy_m ** 2
        if prior_std_theta_rad is not None:
            cost += ((thetas[candidates[:, 0]] - t0) / prior_std_theta_rad) ** 2
        return raw * np.exp(-0.5 * cost)

    top = len(pyramid) - 1
    offsets = np.arange(0, 2 * limit + 1, 1 << top)
    a, ox, oy = np.meshgrid(np.arange(len(thetas)), offsets, offsets, indexing="ij")
    candidates = np.stack([a.ravel(), ox.ravel(), oy.ravel()], axis=1)
    scores = scores_of(top, candidates)
    weighted = prior_std_xy_m is not None or prior_std_theta_rad is not None
    bound = 0.0 if weighted else min_score
    dive = candidates[np.argsort(scores)[::-1][:8]]
    for level in range(top, 0, -1):
        kids = dive[:, None, :] + shifts(level)[None]
        outside = (kids[..., 1] > 2 * limit) | (kids[..., 2] > 2 * limit)
        kids[..., 1:] = np.minimum(kids[..., 1:], 2 * limit)
        kid_scores = scores_of(level - 1, kids.reshape(-1, 3)).reshape(len(dive), 4)
        kid_scores[outside] = -np.inf
        dive = kids[np.arange(len(dive)), np.argmax(kid_scores, axis=1)]
        if level == 1:
            bound = max(bound, float(kid_scores.max()))
    for level in range(top, 0, -1):
        keep = scores >= bound
        candidates = children(candidates[keep], level, 2 * limit)
        scores = scores_of(level - 1, candidates)
    if len(scores) == 0:
        return False, 0, 0, 0, 0.0
    i = int(np.argmax(scores))
    raw = float(block_scores(pyramid[0], base, candidates[i:i + 1])[0]) if weighted else float(scores[i])
    if raw < min_score:
        return False, 0, 0, 0, 0.0
    return True, int(candidates[i, 0]), int(candidates[i, 1]), int(candidates[i, 2]), float(scores[i])


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 9), st.integers(1, 4), st.integers(0, 40),
       st.sampled_from([None, 0.05, 0.3]), st.sampled_from([None, 0.02, 0.2]), st.floats(0.0, 0.6))
def test_branch_and_bound_equals_numpy(seed: int, limit: int, angles: int, points: int, prior_xy: float | None,
                                       prior_theta: float | None, min_score: float) -> None:
    """The same pose as the numpy loop, ties included (a field of few distinct values has many), and the
    same score (to the last bits of the prior's exp, which numpy computes with its own vector code)."""
    rng = np.random.default_rng(seed)
    height, width = rng.integers(2 * limit + 1, 2 * limit + 30, 2)
    field = rng.choice(np.array([0.0, 0.5, 1.0], np.float32), (height, width))
    levels = max(1, min(8, int(math.ceil(math.log2(2 * limit + 1))) + 1))
    pyramid = score_pyramid(field, levels)
    rows = rng.integers(0, pyramid.shape[1] - 2 * limit, (angles, points))
    cols = rng.integers(0, pyramid.shape[2] - 2 * limit, (angles, points))
    thetas = rng.uniform(-0.2, 0.2, angles)
    arguments = (pyramid, rows * pyramid.shape[2] + cols, thetas, 0.01, limit, 0.05)
    found = branch_and_bound(*arguments, -1.0 if prior_xy is None else prior_xy,
                             -1.0 if prior_theta is None else prior_theta, min_score)
    expected = numpy_branch_and_bound(*arguments, prior_xy, prior_theta, min_score)
    assert found[:4] == expected[:4]
    assert found[4] == pytest.approx(expected[4], rel=1e-14, abs=0.0)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 40), st.integers(1, 5), st.integers(0, 40),
       st.sampled_from([None, 0.05, 0.3]), st.sampled_from([None, 0.02, 0.2]), st.floats(0.0, 0.6))
def test_the_search_without_its_one_block_level_finds_the_same_pose(
        seed: int, limit: int, angles: int, points: int, prior_xy: float | None, prior_theta: float | None,
        min_score: float) -> None:
    """correlative_search pools one level less than the branch and bound used to: the level whose one block
    per angle held every offset. Starting from its children, in the order it made them, gives the same pose
    and score, ties included (a field of three values has many), with or without a prior."""
    rng = np.random.default_rng(seed)
    span_levels = int(math.ceil(math.log2(2 * limit + 1)))
    old_levels, levels = max(1, min(8, span_levels + 1)), max(1, min(8, span_levels))
    pad = 1 << (old_levels - 1)
    height, width = rng.integers(1, 40, 2)
    field = rng.choice(np.array([0.0, 0.5, 1.0], np.float32), (height, width))
    before, after = score_pyramid(field, old_levels), score_pyramid(field, levels, pad)
    np.testing.assert_array_equal(after, before[:levels])
    rows = rng.integers(0, before.shape[1] - 2 * limit, (angles, points))
    cols = rng.integers(0, before.shape[2] - 2 * limit, (angles, points))
    base, thetas = rows * before.shape[2] + cols, rng.uniform(-0.2, 0.2, angles)
    priors = (-1.0 if prior_xy is None else prior_xy, -1.0 if prior_theta is None else prior_theta, min_score)
    assert (branch_and_bound(after, base, thetas, 0.01, limit, 0.05, *priors)
            == branch_and_bound(before, base, thetas, 0.01, limit, 0.05, *priors))


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 50), st.integers(1, 50), st.floats(0.0, 0.5), st.integers(0, 2**32 - 1), st.integers(0, 8),
       st.integers(0, 8), st.integers(0, 8), st.integers(0, 8))
def test_occupied_cells_equal_numpy(height: int, width: int, density: float, seed: int, top: int, bottom: int,
                                    left: int, right: int) -> None:
    """The occupied cells of a padded window (kernel) against numpy's mask and nonzero, and their index."""
    rng = np.random.default_rng(seed)
    log_odds = np.where(rng.random((height, width)) < density, rng.uniform(0.01, 3.5, (height, width)),
                        rng.uniform(-2.0, 0.0, (height, width))).astype(np.float32)
    log_odds[rng.random((height, width)) < 0.05] = 0.0   # exactly zero: not occupied
    pr0, pc0 = min(top, height), min(left, width)
    pr1, pc1 = max(height - bottom, pr0), max(width - right, pc0)
    rows, cols, occupied, starts = occupied_cells(log_odds, pr0, pr1, pc0, pc1)
    mask = log_odds[pr0:pr1, pc0:pc1] > 0.0
    expected_rows, expected_cols = np.nonzero(mask)
    np.testing.assert_array_equal(rows, expected_rows)
    np.testing.assert_array_equal(cols, expected_cols)
    assert rows.dtype == expected_rows.dtype and occupied.dtype == np.int32
    np.testing.assert_array_equal(occupied, occupied_index(mask))
    np.testing.assert_array_equal(starts, occupied_rows(mask)[0])


@st.composite
def occupancy_images(draw: st.DrawFn) -> np.ndarray:
    """Occupied cells as a match meets them: scattered, or on walls (lines, which make the most equally near
    cells), over a window of any shape."""
    height, width = draw(st.integers(1, 60)), draw(st.integers(1, 60))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if draw(st.booleans()):
        return rng.random((height, width)) < draw(st.floats(0.0, 0.3))
    image = np.full((height, width), 255, np.uint8)
    for _ in range(draw(st.integers(0, 6))):
        ends = rng.integers(0, [width, height], (2, 2))
        cv2.line(image, (int(ends[0, 0]), int(ends[0, 1])), (int(ends[1, 0]), int(ends[1, 1])), 0, 1)
    return image == 0


@settings(max_examples=150, deadline=None)
@given(occupancy_images())
def test_chamfer_nearest_is_opencvs_label_ties_included(mask: np.ndarray) -> None:
    """Every cell's nearest occupied cell found by rings (chamfer_nearest) is the one OpenCV's labelled distance
    transform names, on scattered cells and on walls, where many cells are equally near two or more."""
    occupied = occupied_index(mask)
    expected = opencv_nearest(occupied)
    found = np.array([[chamfer_nearest(occupied, r, c) for c in range(mask.shape[1])] for r in range(mask.shape[0])])
    np.testing.assert_array_equal(found, expected)


def test_match_fields_nearest_cells_equal_opencv() -> None:
    """The wall lines' nearest cells of real match-field windows (a grid of rooms' walls) are those OpenCV's
    labelled transform of the occupied cells around the window names."""
    rng = np.random.default_rng(7)
    grid = LogOddsGrid(0.05, subcell=True)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    walls = rng.uniform(1.0, 4.0, (360, 1)) * np.column_stack([np.cos(angles), np.sin(angles)])
    for _ in range(3):
        grid.insert_rays(rng.uniform(-0.3, 0.3, 2), walls + 0.01 * rng.standard_normal(walls.shape))
    fields = grid.match_fields(0.5, 0.05, lines=True)
    for _ in range(10):
        centre = rng.uniform(0, min(grid.shape), 2)
        window = fields.around(centre[:1] + rng.uniform(-20, 20, 2), centre[1:] + rng.uniform(-20, 20, 2))
        lines = window.lines
        assert lines is not None
        height, width = window.squared.shape
        pr0, pr1 = max(window.row0 - fields.margin, 0), min(window.row0 + height + fields.margin, grid.shape[0])
        pc0, pc1 = max(window.col0 - fields.margin, 0), min(window.col0 + width + fields.margin, grid.shape[1])
        assert (window.occupied_row0, window.occupied_col0) == (pr0, pc0)
        np.testing.assert_array_equal(window.occupied, occupied_index(grid.log_odds[pr0:pr1, pc0:pc1] > 0.0))
        expected = opencv_nearest(window.occupied)
        for r in range(window.row0 - pr0, window.row0 - pr0 + height, 3):
            for c in range(window.col0 - pc0, window.col0 - pc0 + width, 3):
                assert chamfer_nearest(window.occupied, r, c) == expected[r, c]


def numpy_voxel_filter(points: np.ndarray, cell_m: float) -> np.ndarray:
    """geometry.voxel_filter as numpy computed it before the kernel (np.unique, np.add.at, argsort)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0 or cell_m <= 0:
        return points
    cells = np.floor(points / cell_m).astype(np.int64)
    keys = (cells[:, 0] << 32) + cells[:, 1]
    _, first, inverse_index, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    inverse_index = inverse_index.reshape(-1)
    sums = np.zeros((len(counts), 2))
    np.add.at(sums, inverse_index, points)
    means = sums / counts[:, None]
    return means[np.argsort(first, kind="stable")]


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.integers(0, 1500), st.floats(0.001, 20.0),
       st.sampled_from([0.0, 0.025, 0.05, 0.3]))
def test_voxel_filter_equals_numpy_to_the_bit(seed: int, count: int, spread: float, cell_m: float) -> None:
    """The voxel filter's compiled grouping (voxel_means) against np.unique / np.add.at / argsort: the same
    cells in the same order, the same means to the bit (the sums run in point order in both)."""
    rng = np.random.default_rng(seed)
    points = rng.normal(rng.uniform(-50, 50, 2), spread, (count, 2))
    points[rng.random(count) < 0.1] = points[0] if count else 0.0   # repeated points: cells with many
    actual, expected = voxel_filter(points, cell_m), numpy_voxel_filter(points, cell_m)
    assert actual.shape == expected.shape and actual.dtype == expected.dtype
    assert np.array_equal(actual.view(np.uint64), expected.view(np.uint64))


def numpy_match_statistics(likelihood: np.ndarray, row0: int, col0: int, cx: np.ndarray, cy: np.ndarray,
                           observed: np.ndarray, d: np.ndarray, active: np.ndarray, inlier: float
                           ) -> tuple[float, float, float, float, np.ndarray]:
    """refine_pose's final figures as numpy computed them before match_statistics."""
    n = len(cx)
    inliers = active & (np.abs(d) <= inlier)
    n_in = int(inliers.sum())
    lik, _, _, inside = bilinear(likelihood, cx - 0.5 - col0, cy - 0.5 - row0)
    lik = np.where(inside, lik, 0.0)
    score = float(np.mean(lik)) if n else 0.0
    with np.errstate(invalid="ignore"):   # NaN and huge coordinates become INT64_MIN: off the grid
        cells = np.floor(np.stack([cx, cy], axis=1)).astype(np.int64)
    on_grid = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < observed.shape[1]) & (
        cells[:, 1] < observed.shape[0])
    known = np.zeros(n, bool)
    known[on_grid] = observed[cells[on_grid, 1], cells[on_grid, 0]]
    overlap = float(known.mean()) if n else 0.0
    overlap_score = float(lik[known].mean()) if known.any() else 0.0
    residual = float(np.mean(np.abs(d[inliers]))) if n_in else float("nan")
    return score, overlap, overlap_score, residual, inliers


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.integers(0, 3000), st.integers(1, 40), st.integers(1, 40), st.integers(-5, 5),
       st.integers(-5, 5), st.floats(0.01, 0.3), st.floats(-4.0, 4.0), st.sampled_from([0.05, 0.1, 0.025]))
def test_match_statistics_equal_numpy_to_the_bit(seed: int, count: int, height: int, width: int, row0: int, col0: int,
                                                 inlier: float, theta: float, resolution: float) -> None:
    """A match's score, overlap, overlap score, inlier residual and inliers (one kernel, which places the points)
    against the numpy lines they replaced, the points placed as refine_pose placed them: equal to the bit
    (the kernel's sums are numpy's pairwise ones)."""
    rng = np.random.default_rng(seed)
    likelihood = np.where(rng.random((height, width)) < 0.3, 0.0, rng.random((height, width))).astype(np.float32)
    observed = rng.random((height + 6, width + 6)) < 0.7
    origin = rng.uniform(-20.0, 20.0, 2)
    pose = np.array([*(origin + rng.uniform(0.0, 1.0, 2) * (width + 6, height + 6) * resolution), theta])
    px = rng.uniform(-1.0, 1.0, count) * max(height, width) * resolution
    py = rng.uniform(-1.0, 1.0, count) * max(height, width) * resolution
    px[rng.random(count) < 0.02] = np.nan
    px[rng.random(count) < 0.02] = 1e30
    c, s = math.cos(pose[2]), math.sin(pose[2])
    cx = (c * px - s * py + (pose[0] - origin[0])) / resolution
    cy = (s * px + c * py + (pose[1] - origin[1])) / resolution
    d = rng.normal(0.0, 0.2, count)
    active = rng.random(count) < 0.9
    actual = match_statistics(likelihood, row0, col0, px, py, pose, origin, resolution, observed, d, active, inlier)
    expected = numpy_match_statistics(likelihood, row0, col0, cx, cy, observed, d, active, inlier)
    for a, e in zip(actual[:4], expected[:4], strict=True):
        assert np.array_equal(np.float64(a).view(np.uint64), np.float64(e).view(np.uint64)), (a, e)
    np.testing.assert_array_equal(actual[4], expected[4])
    assert actual[5] == int(expected[4].sum())


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.one_of(st.integers(0, 300), st.integers(300, 20000)), st.floats(1e-3, 1e6))
def test_pairwise_sum_equals_numpy_sum(seed: int, count: int, scale: float) -> None:
    values = np.random.default_rng(seed).standard_normal(count + 5) * scale
    assert pairwise_sum(values, 5, count) == np.sum(values[5:])
    zeros = np.full(count, -0.0)   # numpy's reduction starts from 0.0: no sum is -0.0
    assert np.float64(pairwise_sum(zeros, 0, count)).view(np.uint64) == np.sum(zeros).view(np.uint64)


def numpy_lattice_base(points: np.ndarray, thetas: np.ndarray, x0: float, y0: float, origin: np.ndarray, res: float,
                       limit: int, pad: int, row0: int, col0: int, height: int, width: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """correlative_search's cells of the rotated points, their extent and the clipped flat indices the
    branch and bound reads, as numpy computed them before lattice_cells and flat_cells."""
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    cols = np.floor((c * points[:, 0] - s * points[:, 1] + x0 - origin[0]) / res).astype(np.int64)
    rows = np.floor((s * points[:, 0] + c * points[:, 1] + y0 - origin[1]) / res).astype(np.int64)
    extent = np.array([cols.min(), cols.max(), rows.min(), rows.max()])
    ix = np.clip(cols - col0 + pad - limit, 0, width - 1 - 2 * limit)
    iy = np.clip(rows - row0 + pad - limit, 0, height - 1 - 2 * limit)
    return cols, extent, iy * width + ix


@EXAMPLES
@given(st.integers(0, 2**32 - 1), st.integers(1, 800), st.integers(1, 60), st.floats(-50, 50), st.floats(-50, 50),
       st.floats(-4.0, 4.0), st.sampled_from([0.02, 0.05, 0.1]), st.integers(0, 12), st.integers(-40, 40),
       st.integers(-40, 40), st.integers(1, 400), st.integers(1, 400))
def test_lattice_and_flat_cells_equal_numpy_to_the_bit(seed: int, count: int, angles: int, x0: float, y0: float,
                                                        t0: float, res: float, limit: int, row0: int, col0: int,
                                                        height: int, width: int) -> None:
    """The search's angles and per-rotation cells of the scan's points (lattice_cells) and their clipped flat
    indices (flat_cells) against the numpy expressions they replaced: the same angles and integers."""
    rng = np.random.default_rng(seed)
    points = rng.normal(0.0, rng.uniform(0.1, 15.0), (count, 2))
    thetas = t0 + 0.004 * np.arange(-angles, angles + 1)
    origin = rng.uniform(-60, 10, 2)
    pad = 1 << max(1, min(8, int(math.ceil(math.log2(2 * limit + 1))) + 1)) - 1
    height, width = height + 2 * pad, width + 2 * pad
    found, cols, rows, c_lo, c_hi, r_lo, r_hi = lattice_cells(points, t0, 0.004, angles, x0, y0, float(origin[0]),
                                                              float(origin[1]), res)
    np.testing.assert_array_equal(found, thetas)
    expected_cols, extent, expected_base = numpy_lattice_base(points, thetas, x0, y0, origin, res, limit, pad, row0,
                                                              col0, height, width)
    np.testing.assert_array_equal(cols, expected_cols)
    np.testing.assert_array_equal([c_lo, c_hi, r_lo, r_hi], extent)
    base = flat_cells(cols, rows, pad - limit - col0, pad - limit - row0, width - 1 - 2 * limit,
                      height - 1 - 2 * limit, width)
    np.testing.assert_array_equal(base, expected_base)


def test_flat_cells_refuse_a_window_their_int32_cannot_index() -> None:
    """The flat indices are int32: a window whose last cell is 2^31 or more is refused, the last below it taken."""
    cells = np.zeros((1, 1), np.int64)
    assert flat_cells(cells, cells, 0, 0, 2**31 - 2**20 - 1, 1, 2**20)[0, 0] == 0
    with pytest.raises(ValueError, match="2\\^31"):
        flat_cells(cells, cells, 0, 0, 2**31 - 2**20, 1, 2**20)


def numpy_submap_votes(grid: LogOddsGrid, frame: np.ndarray, points_map: np.ndarray, tolerance_m: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """map_check._submap_votes as numpy computed it before submap_votes."""
    local = transform_points(inverse(frame), points_map)
    cells = np.floor(grid.world_to_cell(local)).astype(np.int64)
    height, width = grid.shape
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < width) & (cells[:, 1] < height)
    rows, cols = cells[inside, 1], cells[inside, 0]
    distance = grid.distance_field(0.5)
    agree = np.zeros(len(points_map), bool)
    conflict = np.zeros(len(points_map), bool)
    near = distance[rows, cols] <= tolerance_m[inside] * (1.0 + 1e-6)
    free = grid.observed[rows, cols] & (grid.log_odds[rows, cols] < 0.0)
    agree[inside] = near
    conflict[inside] = free & ~near
    return agree, conflict


@settings(max_examples=30, deadline=None)
@given(matching_problems(), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(-4.0, 4.0), st.integers(0, 3000),
       st.integers(0, 2**32 - 1))
def test_submap_votes_equal_numpy(problem: tuple[LogOddsGrid, np.ndarray, np.ndarray], x: float, y: float,
                                  theta: float, count: int, seed: int) -> None:
    """The map check's agree / conflict votes of map points against a placed submap (one kernel) against the
    numpy lines they replaced: the same masks, points off the grid and tolerances at the distances included."""
    grid = problem[0]
    rng = np.random.default_rng(seed)
    submap = Submap(0, 0, np.zeros(3), grid)
    frame = np.array([x, y, theta])
    points = rng.uniform(-6.0, 6.0, (count, 2))
    tolerance = rng.choice([0.05, 0.1, 0.15 + 0.5 ** 0.5 * 0.05, 0.6], count) * rng.uniform(0.9, 1.1, count)
    actual = _submap_votes(submap, frame, points, tolerance)
    expected = numpy_submap_votes(grid, frame, points, tolerance)
    np.testing.assert_array_equal(actual[0], expected[0])
    np.testing.assert_array_equal(actual[1], expected[1])


@EXAMPLES
@given(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), st.floats(-2e-5, 2e-5), st.floats(-2e-5, 2e-5))
def test_lattice_check_equals_allclose(col: float, row: float, dx: float, dy: float) -> None:
    """insert_traced's test that a trace is on the grid's lattice, on floats, against np.allclose it replaced."""
    grid = LogOddsGrid(0.05)
    grid.insert_rays(np.zeros(2), np.array([[1.0, 0.5]]))
    origin = grid.origin + np.array([round(col) + dx, round(row) + dy]) * grid.resolution
    rays = trace_rays(origin, grid.resolution, np.zeros(2), np.array([[1.0, 0.5]]))
    shift = (rays.origin - grid.origin) / grid.resolution
    expected = np.allclose(shift, np.rint(shift), atol=1e-6)
    try:
        grid.copy().insert_traced(rays)
        accepted = True
    except ValueError:
        accepted = False
    assert accepted == expected
