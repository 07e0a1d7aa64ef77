"""Scan-to-map matching on a known polygon world and on real Intel scans with GMapping's poses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tests.planar_world import CORRIDOR, ROOM, scan
from trundle.fusion.geometry import scan_to_points, transform_points, wrap_angle
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.matching.scan_matching import (
    angular_step,
    correlative_search,
    match_covariance,
    match_scan,
    median_step,
    refine_pose,
    samples_walls_densely,
    score_pyramid,
)


def build_map(walls: np.ndarray, poses: list[tuple[float, float, float]], resolution: float = 0.05,
              max_range: float = 30.0) -> LogOddsGrid:
    grid = LogOddsGrid(resolution)
    for pose in poses:
        pose = np.array(pose)
        points = scan_to_points(scan(walls, pose, beams=720, max_range=max_range))
        grid.insert_rays(pose[:2], transform_points(pose, points))
    return grid


@pytest.fixture(scope="module")
def room_map() -> LogOddsGrid:
    return build_map(ROOM, [(0.0, 0.0, 0.0), (-2.0, 0.5, 1.0), (2.5, -1.5, -2.0)])


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, st.tuples(st.integers(1, 20), st.integers(1, 20)), elements=st.floats(0, 1, width=32)),
       st.integers(1, 4))
def test_pyramid_levels_are_block_maxima(field: np.ndarray, levels: int) -> None:
    pyramid = score_pyramid(field, levels)
    pad = 1 << (levels - 1)
    padded = pyramid[0]
    assert padded[pad:pad + field.shape[0], pad:pad + field.shape[1]].tolist() == field.tolist()
    for h, level in enumerate(pyramid):
        size = 1 << h
        for r in range(0, padded.shape[0], 3):
            for c in range(0, padded.shape[1], 3):
                assert level[r, c] == padded[r:r + size, c:c + size].max()


def test_branch_and_bound_finds_the_exhaustive_optimum(room_map: LogOddsGrid) -> None:
    truth = np.array([0.4, -0.3, 0.5])
    points = scan_to_points(scan(ROOM, truth, beams=180, noise_m=0.01, seed=3))
    initial = np.array([0.1, 0.1, 0.35])
    window, window_theta = 0.5, math.radians(12.0)
    step = angular_step(room_map.resolution, float(np.hypot(*points.T).max()))
    found = correlative_search(room_map, points, initial, window_xy_m=window, window_theta_rad=window_theta)
    assert found is not None
    # Exhaustive: every lattice pose, scored with the same likelihood field.
    field = room_map.likelihood_field(room_map.resolution)
    n = int(math.floor(window_theta / step))
    limit = int(math.ceil(window / room_map.resolution))
    best = -1.0
    for theta in initial[2] + step * np.arange(-n, n + 1):
        rotated = points @ np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]]).T
        cells = np.floor((rotated + initial[:2] - room_map.origin) / room_map.resolution).astype(int)
        d = np.arange(-limit, limit + 1)
        cols = cells[:, 0][None, None, :] + d[:, None, None]
        rows = cells[:, 1][None, None, :] + d[None, :, None]
        inside = (cols >= 0) & (rows >= 0) & (cols < field.shape[1]) & (rows < field.shape[0])
        values = np.where(inside, field[rows.clip(0, field.shape[0] - 1), cols.clip(0, field.shape[1] - 1)], 0.0)
        best = max(best, float(values.mean(axis=2).max()))
    assert found[1] == pytest.approx(best, abs=1e-6)
    assert np.hypot(*(found[0][:2] - truth[:2])) < 0.06
    assert abs(wrap_angle(found[0][2] - truth[2])) < math.radians(1.0)


@pytest.mark.parametrize("offset", [(0.25, -0.2, 8.0), (-0.3, 0.3, -10.0), (0.05, 0.0, 2.0)])
def test_match_recovers_true_pose_from_offset_guess(room_map: LogOddsGrid, offset: tuple[float, float, float]) -> None:
    truth = np.array([-0.7, 0.9, 2.2])
    points = scan_to_points(scan(ROOM, truth, beams=360, noise_m=0.01, seed=7))
    guess = truth + np.array([offset[0], offset[1], math.radians(offset[2])])
    result = match_scan(room_map, points, guess, window_xy_m=0.4, window_theta_rad=math.radians(12.0))
    assert result is not None
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.02
    assert abs(wrap_angle(result.pose[2] - truth[2])) < math.radians(0.3)
    assert result.score > 0.6 and result.inlier_fraction > 0.95 and result.residual_m < 0.03
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_refinement_alone_converges_from_a_few_centimetres(room_map: LogOddsGrid) -> None:
    truth = np.array([1.5, 0.5, -0.4])
    points = scan_to_points(scan(ROOM, truth, beams=360, noise_m=0.005, seed=1))
    result = refine_pose(room_map, points, truth + np.array([0.06, -0.05, math.radians(2.0)]))
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.02
    assert abs(wrap_angle(result.pose[2] - truth[2])) < math.radians(0.3)
    assert result.iterations > 1


def test_corridor_is_uncertain_along_its_axis_only() -> None:
    grid = build_map(CORRIDOR, [(x, 0.0, 0.0) for x in range(-10, 11, 2)], max_range=6.0)
    truth = np.array([0.2, 0.1, 0.0])
    points = scan_to_points(scan(CORRIDOR, truth, beams=360, noise_m=0.01, seed=2, max_range=6.0))
    result = match_scan(grid, points, truth, window_xy_m=0.2, window_theta_rad=math.radians(5.0))
    assert result is not None
    std = np.sqrt(np.diag(result.covariance))
    assert std[0] > 10 * std[1]
    assert abs(result.pose[1] - truth[1]) < 0.02


def test_no_match_below_min_score() -> None:
    grid = build_map(ROOM, [(0.0, 0.0, 0.0)])
    points = np.random.default_rng(0).uniform(-20, 20, (200, 2)) + 100.0
    assert match_scan(grid, points, np.zeros(3), min_score=0.3) is None


def test_search_reaching_the_window_corner_stays_in_bounds() -> None:
    """The best pose at the window's far corner and a point far off the map: the greedy dive's
    sub-blocks beyond the window must not index past the pyramid (they did once: IndexError)."""
    grid = build_map(ROOM, [(0.0, 0.0, 0.0)], max_range=1.5)
    truth = np.array([0.1, 0.0, 0.0])
    points = np.vstack([scan_to_points(scan(ROOM, truth, beams=90, max_range=1.5)), [[100.0, 100.0]]])
    for window in (0.3, 0.45, 1.0, 2.0):
        found = correlative_search(grid, points, truth - np.array([window, window, 0.0]), window_xy_m=window,
                                   window_theta_rad=0.05)
        assert found is not None and np.hypot(*(found[0][:2] - truth[:2])) < 0.03


def test_a_good_match_far_out_in_a_wide_prior_is_not_declined(room_map: LogOddsGrid) -> None:
    """min_score applies to the unweighted score: the prior weighting (sigma 0.2 m) pulls the search score
    of the true pose, 0.15 m off the prediction, down to about e^-0.28 of its ~1, below min_score 0.8."""
    truth = np.array([0.3, 0.2, 0.1])
    points = scan_to_points(scan(ROOM, truth, beams=360, max_range=10.0))
    guess = truth - np.array([0.15, 0.0, 0.0])
    found = correlative_search(room_map, points, guess, window_xy_m=0.4, window_theta_rad=math.radians(5.0),
                               min_score=0.8, prior_std_xy_m=0.2)
    assert found is not None and np.hypot(*(found[0][:2] - truth[:2])) < 0.03 and found[1] < 0.8


def test_shaped_covariance_keeps_the_corridor_blind_along_its_axis() -> None:
    grid = build_map(CORRIDOR, [(x, 0.0, 0.0) for x in range(-10, 11, 2)], max_range=6.0)
    truth = np.array([0.2, 0.1, 0.0])
    points = scan_to_points(scan(CORRIDOR, truth, beams=360, noise_m=0.01, seed=2, max_range=6.0))
    result = refine_pose(grid, points, truth, shaped_covariance=True)
    std = np.sqrt(np.linalg.eigvalsh(result.covariance[:2, :2]))
    assert std[0] == pytest.approx(0.01, rel=1e-3)  # the width: the floor (the map's precision), no less
    assert std[1] > 30 * std[0]  # the axis: nothing to hold it
    assert np.sqrt(result.covariance[2, 2]) >= math.radians(0.25) * (1 - 1e-6)


def corner(wall_y: float, step: float = 0.02) -> np.ndarray:
    """Points every ``step`` on a wall at ``wall_y`` (x from -3 to 3 m) and on a wall across it at x = 3.0123."""
    xs = np.arange(-3.0, 3.0, step)
    ys = np.arange(wall_y - 2.0, wall_y, step)
    return np.vstack([np.column_stack([xs, np.full_like(xs, wall_y)]), np.column_stack([np.full_like(ys, 3.0123), ys])])


def wall_grid(wall_y: float, subcell: bool) -> LogOddsGrid:
    """The corner's returns seen from three places."""
    grid = LogOddsGrid(0.05, subcell=subcell)
    for offset in (-0.5, 0.0, 0.5):
        grid.insert_rays(np.array([offset, 0.0]), corner(wall_y))
    return grid


@pytest.mark.parametrize("wall_y", [0.7623, 0.75, 0.7749])
def test_point_to_line_refinement_puts_a_wall_between_cell_centres(wall_y: float) -> None:
    """Against cell centres the wall sits up to half a cell off (at 0.775 for all three walls); against
    the line through its returns it sits where it is."""
    points = corner(wall_y, 0.05)
    guess = np.array([0.003, 0.004, 0.0])
    lattice = refine_pose(wall_grid(wall_y, subcell=False), points, guess)
    lines = refine_pose(wall_grid(wall_y, subcell=True), points, guess)
    assert np.hypot(*lines.pose[:2]) < 0.001
    if abs(wall_y - 0.775) > 0.005:
        assert abs(lattice.pose[1]) > 5 * np.hypot(*lines.pose[:2])


def test_dense_and_sparse_scans() -> None:
    dense = scan_to_points(scan(ROOM, np.zeros(3), beams=1440, max_range=10.0))
    sparse = scan_to_points(scan(ROOM, np.zeros(3), beams=180, max_range=10.0))
    assert samples_walls_densely(dense, 0.05) and not samples_walls_densely(sparse, 0.05)


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(2, 60), st.just(2)),
              elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
       st.integers(0, 2**32 - 1))
def test_the_median_step_is_numpys_to_the_bit(points: np.ndarray, seed: int) -> None:
    """The compiled median of consecutive distances against numpy's, on any values (NaN and infinities
    included) and on scan-like ones (the same decision, and the same value)."""
    like_a_scan = np.cumsum(np.random.default_rng(seed).normal(0.0, 0.03, (len(points), 2)), axis=0)
    for values in (points, like_a_scan):
        # infinity minus infinity is NaN, and the difference of the largest floats infinite, as intended
        with np.errstate(invalid="ignore", over="ignore"):
            expected = np.median(np.hypot(*np.diff(values, axis=0).T))
        assert median_step(values) == expected or (math.isnan(expected) and math.isnan(median_step(values)))


def numpy_covariance(jacobian: np.ndarray, residuals: np.ndarray, weights: np.ndarray, min_std_xy_m: float,
                     min_std_theta_rad: float, max_variance: float = 100.0, shaped: bool = False) -> np.ndarray:
    """The covariance as numpy computed it before it was compiled (the rows given are the inliers)."""
    count = len(residuals)
    jw = jacobian * weights[:, None]
    hessian = jw.T @ jacobian
    variance = max(float(np.sum(weights * residuals ** 2) / max(count - 3, 1)), 1e-10)
    eigenvalues, vectors = np.linalg.eigh(hessian)
    information = np.maximum(eigenvalues, variance / max_variance) / variance
    raw = (vectors / information) @ vectors.T
    floor = np.diag([min_std_xy_m ** 2, min_std_xy_m ** 2, min_std_theta_rad ** 2])
    if not shaped:
        covariance = raw + floor
    else:
        best_xy = float(np.linalg.eigvalsh(raw[:2, :2])[0])
        scale = max(1.0, min_std_xy_m ** 2 / max(best_xy, 1e-300),
                    min_std_theta_rad ** 2 / max(float(raw[2, 2]), 1e-300))
        values, axes = np.linalg.eigh(scale * raw)
        covariance = (axes * np.minimum(values, max_variance)) @ axes.T + 1e-6 * floor
    return 0.5 * (covariance + covariance.T)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 700), st.integers(0, 2**32 - 1), st.booleans(), st.sampled_from([0.0, 0.1, 0.9, 1.0]))
def test_the_compiled_covariance_is_numpys_to_the_bit(count: int, seed: int, shaped: bool, share_out: float) -> None:
    """On rows as a match gives them (a corridor's: one column nearly zero; a few rows; none) and any inlier
    mask, the same matrix as numpy's expression, to the bit."""
    rng = np.random.default_rng(seed)
    jacobian = rng.normal(size=(count, 3)) * 10.0 ** rng.uniform(-8.0, 2.0, 3)
    residuals = rng.normal(0.0, 0.03, count)
    weights = rng.uniform(0.0, 1.0, count)
    inliers = rng.uniform(size=count) >= share_out
    expected = numpy_covariance(jacobian[inliers], residuals[inliers], weights[inliers], 0.01, math.radians(0.25),
                                shaped=shaped)
    got = match_covariance(jacobian, residuals, weights, inliers, 0.01, math.radians(0.25), shaped=shaped)
    assert np.array_equal(got, expected)


def test_a_match_is_the_same_with_its_fields_clipped_to_the_rays_box(monkeypatch: pytest.MonkeyPatch) -> None:
    """The match fields are computed only over the box of the rays inserted and its margin: a scan that reaches
    past that box, into the grid's margin for growth and beyond the grid, is matched exactly as with fields
    over the whole grid (search, refinement, covariance and scores, to the bit)."""
    grid = build_map(ROOM, [(0.0, 0.0, 0.0), (1.0, 0.5, 0.5)], max_range=2.5)
    truth = np.array([0.5, 0.2, 0.1])
    points = scan_to_points(scan(ROOM, truth, beams=360, noise_m=0.01, seed=5))
    start = truth + np.array([0.08, -0.06, 0.03])
    top, bottom, left, right = grid.swept_extent(12)
    reach = grid.world_to_cell(transform_points(truth, points))
    assert (reach[:, 0] >= right).any() and (reach[:, 0] < grid.shape[1]).any()   # past the box, into the margin
    clipped = match_scan(grid.copy(), points, start, shaped_covariance=True)
    monkeypatch.setattr(LogOddsGrid, "swept_extent", lambda self, margin: (0, self.shape[0], 0, self.shape[1]))
    whole = match_scan(grid.copy(), points, start, shaped_covariance=True)
    assert clipped is not None and whole is not None
    for name in ("pose", "covariance", "score", "residual_m", "inlier_fraction", "search_score", "iterations",
                 "overlap", "overlap_score"):
        np.testing.assert_array_equal(getattr(clipped, name), getattr(whole, name), err_msg=name)
