"""Log-odds occupancy grid: ray tracing, updates, growth, fields and the nav_msgs export."""

from __future__ import annotations

import gc
import math
import weakref

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.mapping.nearest_cells import chamfer_nearest
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid, log_odds, trace_rays
from trundle.fusion.mapping.ray_casting import ray_cells
from trundle.fusion.matching.scan_matching import match_scan
from trundle.logs import ros2


@settings(max_examples=150, deadline=None)
@given(st.integers(-40, 40), st.integers(-40, 40), st.integers(-40, 40), st.integers(-40, 40))
def test_ray_cells_have_bresenham_properties(x0: int, y0: int, x1: int, y1: int) -> None:
    """Between cell centres: max(|dx|,|dy|) cells, 8-connected, each within half a cell of the segment."""
    start, end = np.array([x0 + 0.5, y0 + 0.5]), np.array([[x1 + 0.5, y1 + 0.5]])
    cells = ray_cells(start, end)
    assert len(cells) == max(abs(x1 - x0), abs(y1 - y0))
    if len(cells) == 0:
        return
    assert tuple(cells[0]) == (y0, x0)
    path = np.vstack([cells, [[y1, x1]]])
    assert np.abs(np.diff(path, axis=0)).max() == 1
    centres = path[:, ::-1] + 0.5
    direction = (end[0] - start) / np.linalg.norm(end[0] - start)
    offsets = centres - start
    perpendicular = np.abs(offsets[:, 0] * direction[1] - offsets[:, 1] * direction[0])
    # Distance along the minor axis from the true line is at most half a cell.
    major = max(abs(direction[0]), abs(direction[1]))
    assert np.all(perpendicular / major <= 0.5 + 1e-9)


def test_ray_cells_hand_computed_diagonal() -> None:
    cells = ray_cells(np.array([0.5, 0.5]), np.array([[3.5, 2.5]]))
    # DDA samples at t = 0, 1/3, 2/3: x 0.5, 1.5, 2.5; y 0.5, 1.17, 1.83 -> rows 0, 1, 1.
    assert cells.tolist() == [[0, 0], [1, 1], [1, 2]]


def test_single_ray_updates_exact_log_odds() -> None:
    grid = LogOddsGrid(0.05, p_hit=0.7, p_miss=0.4)
    grid.insert_rays(np.array([0.025, 0.025]), np.array([[1.025, 0.025]]))
    rows, cols = np.nonzero(grid.observed)
    assert len(set(rows.tolist())) == 1
    x = grid.cell_centers(rows, cols)[:, 0]
    values = grid.log_odds[rows, cols]
    order = np.argsort(x)
    np.testing.assert_allclose(x[order], 0.025 + 0.05 * np.arange(21))
    np.testing.assert_allclose(values[order][:20], math.log(0.4 / 0.6), rtol=1e-6)
    assert values[order][20] == pytest.approx(math.log(0.7 / 0.3), rel=1e-6)


def test_cells_crossed_by_many_rays_update_once_per_scan_and_clamp() -> None:
    grid = LogOddsGrid(0.1, l_min=-1.0, l_max=2.0)
    ends = np.array([[2.0, 0.05], [2.0, 0.06], [2.0, 0.04]])
    grid.insert_rays(np.array([0.05, 0.05]), ends)
    cell = np.floor(grid.world_to_cell(np.array([0.05, 0.05]))).astype(int)
    assert grid.log_odds[cell[1], cell[0]] == pytest.approx(log_odds(0.4), rel=1e-6)
    for _ in range(20):
        grid.insert_rays(np.array([0.05, 0.05]), ends)
    assert grid.log_odds.min() == pytest.approx(-1.0)
    assert grid.log_odds.max() == pytest.approx(2.0)


def test_growth_keeps_content_in_place() -> None:
    grid = LogOddsGrid(0.05, grow_cells=8)
    grid.insert_rays(np.array([0.0, 0.0]), np.array([[1.0, 0.5]]))
    before = {tuple(np.round(p, 6)) for p in grid.occupied_points()}
    old_shape = grid.shape
    grid.insert_rays(np.array([-20.0, 15.0]), np.array([[-21.0, 14.0]]))
    assert grid.shape[0] > old_shape[0] and grid.shape[1] > old_shape[1]
    after = {tuple(np.round(p, 6)) for p in grid.occupied_points()}
    assert before < after
    # The lattice is kept: the origin moved by whole cells.
    assert np.allclose(np.mod(grid.origin / 0.05 + 1e-9, 1.0), 0.0, atol=1e-6)


def test_free_ends_clear_without_marking_a_hit() -> None:
    grid = LogOddsGrid(0.05)
    grid.insert_rays(np.array([0.0, 0.0]), np.zeros((0, 2)), free_ends_xy=np.array([[0.0, 1.0]]))
    assert grid.observed.sum() == 20
    assert np.all(grid.log_odds[grid.observed] < 0)


def numpy_growth(grid: LogOddsGrid, xy_min: np.ndarray, xy_max: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """ensure_contains' new origin and shape as numpy computed them before it computed them on floats."""
    height, width = grid.shape
    lo = np.floor(grid.world_to_cell(xy_min)).astype(np.int64)
    hi = np.floor(grid.world_to_cell(xy_max)).astype(np.int64)
    if not height:
        pad_lo = -lo + grid.grow_cells
        new_w, new_h = hi - lo + 1 + 2 * grid.grow_cells
    else:
        pad_lo = np.maximum(-lo, 0) + np.where(lo < 0, grid.grow_cells, 0)
        pad_hi = np.maximum(hi - (width - 1, height - 1), 0) + np.where(hi >= (width, height), grid.grow_cells, 0)
        new_w, new_h = width + pad_lo[0] + pad_hi[0], height + pad_lo[1] + pad_hi[1]
    return grid.origin - pad_lo * grid.resolution, (int(new_h), int(new_w))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-40.0, 40.0), st.floats(-40.0, 40.0), st.floats(0.0, 30.0), st.floats(0.0, 30.0)),
                min_size=1, max_size=4), st.sampled_from([0.05, 0.1, 0.03]), st.integers(0, 70))
def test_growth_equals_numpy(boxes: list[tuple[float, float, float, float]], resolution: float, grow: int) -> None:
    """The origin and shape a grid grows to, box after box, bit for bit as numpy's arithmetic had them, and the
    cells it held kept where they were (their centres, to rounding: the origin moved)."""
    grid = LogOddsGrid(resolution, grow_cells=grow, origin_xy=(0.013, -0.021), mark_returns=True, subcell=True)
    for x, y, w, h in boxes:
        xy_min, xy_max = np.array([x, y]), np.array([x + w, y + h])
        inside = grid.shape[0] and np.all(grid.world_to_cell(xy_min) >= 0) \
            and np.all(grid.world_to_cell(xy_max) < grid.shape[::-1])
        origin, shape = (grid.origin, grid.shape) if inside else numpy_growth(grid, xy_min, xy_max)
        marked = grid.cell_centers(*np.nonzero(grid.observed))
        grid.ensure_contains(xy_min, xy_max)
        np.testing.assert_array_equal(grid.origin, origin)
        assert grid.shape == shape
        np.testing.assert_allclose(grid.cell_centers(*np.nonzero(grid.observed)), marked, rtol=0, atol=1e-9)
        grid.observed[grid.shape[0] // 2, grid.shape[1] // 3] = True


def test_a_box_that_is_not_finite_is_refused() -> None:
    grid = LogOddsGrid(0.05)
    with pytest.raises(ValueError, match="not finite"):
        grid.ensure_contains(np.array([math.nan, 0.0]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match="not finite"):
        grid.ensure_contains(np.array([0.0, 0.0]), np.array([1.0, math.inf]))
    assert grid.shape == (0, 0)


def test_distance_and_likelihood_fields_are_exact_for_one_occupied_cell() -> None:
    grid = LogOddsGrid(0.05)
    grid.insert_rays(np.array([0.0, 0.0]), np.array([[0.5, 0.5]]))
    grid.ensure_contains(np.array([-1.0, -1.0]), np.array([2.0, 2.0]))
    hit = np.floor(grid.world_to_cell(np.array([0.5, 0.5]))).astype(int)
    field = grid.distance_field(1.0)
    assert field[hit[1], hit[0]] == 0.0
    assert field[hit[1], hit[0] + 3] == pytest.approx(0.15, abs=1e-6)
    assert field[hit[1] + 4, hit[0] + 3] == pytest.approx(0.25, abs=1e-6)  # 3-4-5 triangle
    assert field[hit[1] + 30, hit[0]] == pytest.approx(1.0)  # capped
    likelihood = grid.likelihood_field(0.05)
    assert likelihood[hit[1], hit[0] + 1] == pytest.approx(math.exp(-0.5), rel=1e-5)


def test_message_export_percent_and_unknown_round_trips_through_cdr() -> None:
    grid = LogOddsGrid(0.05, p_hit=0.7, p_miss=0.4)
    grid.insert_rays(np.array([0.0, 0.0]), np.array([[0.5, 0.0]]))
    msg = grid.to_message(123, "map")
    values = set(np.unique(msg.data).tolist())
    assert values == {-1, 40, 70}
    assert msg.origin_x == pytest.approx(grid.origin[0]) and msg.resolution == pytest.approx(0.05)
    decoded = ros2.decode(*ros2.encode(msg))
    assert decoded == msg


def test_large_and_small_grids_update_identically() -> None:
    """A grid grown far beyond the rays (its lattice shifted by whole cells) gets the same map."""
    rng = np.random.default_rng(0)
    ends = rng.uniform(-3, 3, (200, 2))
    small, large = LogOddsGrid(0.05, grow_cells=4), LogOddsGrid(0.05, grow_cells=4)
    large.ensure_contains(np.array([-60.0, -60.0]), np.array([60.0, 60.0]))  # far more cells than rays touch
    for grid in (small, large):
        grid.insert_rays(np.array([0.01, 0.02]), ends)
        grid.insert_rays(np.array([0.5, -0.3]), ends[:100])
    for grid in (small, large):
        assert grid.observed.sum() == small.observed.sum()
    np.testing.assert_allclose(
        np.sort(small.occupied_points(), axis=0), np.sort(large.occupied_points(), axis=0), atol=1e-9
    )
    np.testing.assert_array_equal(np.sort(small.log_odds[small.observed]), np.sort(large.log_odds[large.observed]))


def test_rays_traced_once_update_every_grid_on_the_lattice() -> None:
    """One trace serves two grids whose arrays start at different cells (as the two active submaps'),
    exactly as tracing for each; a grid on another lattice refuses it."""
    rng = np.random.default_rng(1)
    ends = rng.uniform(-4, 4, (150, 2))
    free = rng.uniform(-6, 6, (20, 2))
    sensor = np.array([0.013, -0.021])
    shared, first, second = (
        LogOddsGrid(0.05, subcell=True),
        LogOddsGrid(0.05, subcell=True),
        LogOddsGrid(0.05, subcell=True),
    )
    second.ensure_contains(np.array([-9.0, -2.0]), np.array([1.0, 8.0]))
    shared_second = LogOddsGrid(0.05, subcell=True)
    shared_second.ensure_contains(np.array([-9.0, -2.0]), np.array([1.0, 8.0]))
    rays = trace_rays(shared.origin, 0.05, sensor, ends, free)
    for grid in (shared, shared_second):
        grid.insert_traced(rays)
    first.insert_rays(sensor, ends, free)
    second.insert_rays(sensor, ends, free)
    for traced, own in ((shared, first), (shared_second, second)):
        np.testing.assert_array_equal(traced.origin, own.origin)
        np.testing.assert_array_equal(traced.log_odds, own.log_odds)
        assert traced.moments is not None and own.moments is not None
        np.testing.assert_allclose(traced.moments.rows[traced.moments.slots], own.moments.rows[own.moments.slots],
                                   atol=1e-5)
    with pytest.raises(ValueError, match="lattice"):
        LogOddsGrid(0.05, origin_xy=(0.02, 0.0)).insert_traced(rays)


def test_a_dropped_grid_is_freed_at_once_with_the_fields_and_pyramids_it_cached() -> None:
    """A grid caches its match fields and pyramids, and they must not hold it: a reference cycle would keep
    a dropped grid's arrays (megabytes per reference) until Python's cyclic collector ran."""
    grid = LogOddsGrid(0.05, subcell=True)
    angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    walls = 3.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    grid.insert_rays(np.zeros(2), walls)
    result = match_scan(grid, walls[::2], np.array([0.05, -0.05, 0.02]))
    assert result is not None
    fields = grid.match_fields(0.5, 0.05, lines=True)
    assert fields.window is not None and fields.grid is grid
    alive = weakref.ref(grid)
    # a kernel's first compile (an empty numba cache) leaves garbage cycles that hold its callers' frames, the
    # match's among them: collected here, while the grid is still ours, they say nothing of the grid's own
    gc.collect()
    collecting = gc.isenabled()
    gc.disable()
    try:
        del grid
        assert alive() is None
    finally:
        if collecting:
            gc.enable()
    with pytest.raises(ReferenceError, match="gone"):
        _ = fields.grid


@pytest.mark.parametrize(("max_distance_m", "kind"), [(0.5, np.int8), (3.0, np.int16), (10.0, np.int32)])
def test_a_windows_squared_distances_take_the_narrowest_integer(max_distance_m: float, kind: type) -> None:
    """A window keeps its cells' squared distances (up to radius^2 + 1 = 101, 3,601 and 40,001 cells^2 here) in
    int8, int16 or int32, and its distances are the whole grid's in each."""
    grid = LogOddsGrid(0.05, subcell=True)
    angles = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    grid.insert_rays(np.zeros(2), np.column_stack([4.0 * np.cos(angles), 2.5 * np.sin(angles)]))
    fields = grid.match_fields(max_distance_m, 0.05)
    corner = grid.world_to_cell(np.array([[-3.0, -2.0], [3.0, 2.0]]))
    window = fields.around(corner[:, 0], corner[:, 1])
    assert window.squared.dtype == kind
    h, w = window.squared.shape
    rows, cols = np.mgrid[window.row0:window.row0 + h, window.col0:window.col0 + w]
    np.testing.assert_allclose(window.distance(), grid.distance_field(max_distance_m)[rows, cols], atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(0.1, 4.0))
def test_match_field_windows_equal_the_whole_grid_fields(seed: int, x: float, y: float, size: float) -> None:
    """Over the window a match asks for, the distance (capped), the likelihood and the nearest wall are
    what the whole grid's fields give; off the fields' extent (the rays' box and a margin, not the grid's
    margin for growth) they are the values far from any wall; asking outside the window grows it."""
    rng = np.random.default_rng(seed)
    grid = LogOddsGrid(0.05, subcell=True)
    for _ in range(3):
        sensor = rng.uniform(-1, 1, 2)
        angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
        walls = sensor + rng.uniform(1.0, 5.0, (90, 1)) * np.column_stack([np.cos(angles), np.sin(angles)])
        grid.insert_rays(sensor, walls)
    fields = grid.match_fields(0.5, 0.05, lines=True)
    corner = grid.world_to_cell(np.array([[x, y], [x + size, y + size]]))
    window = fields.around(corner[:, 0], corner[:, 1])
    h, w = window.squared.shape
    rows, cols = np.mgrid[window.row0:window.row0 + h, window.col0:window.col0 + w]
    top, bottom, left, right = fields.extent
    assert rows.min() <= max(math.floor(corner[:, 1].min()) - 1, top) and cols.max() >= min(
        math.floor(corner[:, 0].max()) + 1, right - 1)
    outside = np.ones(grid.shape, bool)
    outside[top:bottom, left:right] = False
    assert outside.any()
    assert np.all(grid.distance_field(0.5)[outside] == np.float32(0.5))
    assert not grid.likelihood_field(0.05)[outside].any()
    np.testing.assert_allclose(window.distance(), grid.distance_field(0.5)[rows, cols], atol=1e-6)
    np.testing.assert_allclose(window.likelihood, grid.likelihood_field(0.05)[rows, cols], atol=1e-6)
    exact_cells = grid.distance_field(10.0)[rows, cols] / 0.05
    near = exact_cells < 0.5 / 0.05
    lines = window.lines
    assert lines is not None
    k = np.array([chamfer_nearest(window.occupied, r - window.occupied_row0, c - window.occupied_col0)
                  for r, c in zip(rows[near], cols[near], strict=True)], np.int64)
    assert np.all(k >= 0)
    nearest_cells = np.floor(grid.world_to_cell(lines.mean[k])).astype(np.int64)
    assert np.all(grid.log_odds[nearest_cells[:, 1], nearest_cells[:, 0]] > 0)
    reach = np.hypot(nearest_cells[:, 0] - cols[near], nearest_cells[:, 1] - rows[near])
    assert np.all(reach <= exact_cells[near] + 1.0)
    mean, normal, is_line = grid.line_data(nearest_cells[:, 1], nearest_cells[:, 0])
    np.testing.assert_allclose(lines.mean[k], mean)
    np.testing.assert_allclose(lines.normal[k], normal)
    np.testing.assert_array_equal(lines.is_line[k], is_line)
    if (h, w) != (bottom - top, right - left):   # a cell of the extent outside the window grows it
        first = (window.row0, window.col0) != (top, left)
        far = np.array([left, top]) + 0.5 if first else np.array([right, bottom]) - 0.5
        grown = fields.around(far[:1], far[1:])
        assert grown.squared.size > window.squared.size


def test_the_swept_extent_is_the_rays_box_and_a_margin_through_growth_and_copies() -> None:
    """The cells every inserted ray lies in, grown by a margin and clipped to the grid, on whichever path the rays
    went in (one call, or traced for the submaps) and after the grid grows; a copy keeps it; arrays set otherwise
    than by inserts (a loaded map) have the whole grid."""
    grid = LogOddsGrid(0.1)
    assert grid.swept_extent(3) == (0, 0, 0, 0)
    grid.insert_rays(np.array([0.05, 0.05]), np.array([[1.05, 0.55], [-0.45, -0.95]]))
    assert grid.shape == (16 + 128, 16 + 128)   # y -1.0..0.5 m, x -0.5..1.0 m, and the margin for growth
    # the box's cells from the origin (-0.5 - 6.4, -1.0 - 6.4) m, and 3 more each side
    assert grid.swept_extent(3) == (64 - 3, 64 + 15 + 1 + 3, 64 - 3, 64 + 15 + 1 + 3)
    assert grid.swept_extent(100) == (0, grid.shape[0], 0, grid.shape[1])
    grid.insert_traced(trace_rays(grid.origin, grid.resolution, np.array([0.05, 0.05]), np.array([[20.05, 0.05]])))
    row0 = int(round((-1.0 - grid.origin[1]) / 0.1))
    col0 = int(round((-0.5 - grid.origin[0]) / 0.1))
    assert grid.swept_extent(0) == (row0, row0 + 16, col0, col0 + 206)
    assert grid.copy().swept_extent(2) == grid.swept_extent(2)
    loaded = grid.copy()
    loaded.log_odds = loaded.log_odds.copy()
    assert loaded.swept_extent(2) == (0, grid.shape[0], 0, grid.shape[1])
