"""SE(2) algebra, scan-to-points (REP 117, mount, de-skew) and the voxel filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.planar_world import ROOM, cast
from trundle.fusion.geometry import (
    compose,
    deskewed,
    inverse,
    no_return_directions,
    relative,
    rotate_covariance,
    scan_returns,
    scan_to_points,
    transform_points,
    voxel_filter,
    wrap_angle,
)
from trundle.logs.messages import LaserScan

poses = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-10, 10)).map(np.array)


@settings(max_examples=100, deadline=None)
@given(poses, poses)
def test_relative_undoes_compose_and_inverse_is_an_inverse(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(relative(a, compose(a, b))[:2], b[:2], atol=1e-9)
    assert abs(wrap_angle(relative(a, compose(a, b))[2] - b[2])) < 1e-9
    np.testing.assert_allclose(compose(a, inverse(a)), [0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(relative(a, b), compose(inverse(a), b), atol=1e-9)
    np.testing.assert_allclose(transform_points(compose(a, b), np.array([[1.0, 2.0]])),
                               transform_points(a, transform_points(b, np.array([[1.0, 2.0]]))), atol=1e-9)


def test_hand_computed_compose_and_wrap() -> None:
    np.testing.assert_allclose(compose(np.array([1.0, 2.0, math.pi / 2]), np.array([1.0, 0.0, math.pi])),
                               [1.0, 3.0, -math.pi / 2], atol=1e-12)
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    np.testing.assert_allclose(wrap_angle(np.array([0.5, -7.0])), [0.5, -7.0 + 2 * math.pi])
    cov = np.diag([4.0, 1.0, 0.1])
    np.testing.assert_allclose(rotate_covariance(cov, math.pi / 2), np.diag([1.0, 4.0, 0.1]), atol=1e-12)


def test_scan_to_points_drops_rep117_readings_and_applies_the_mount() -> None:
    ranges = [1.0, math.inf, -math.inf, math.nan, 0.01, 2.0]
    scan = LaserScan(0, "laser", 0.0, 5 * math.pi / 2 / 5, math.pi / 2 / 5 * 1, 0.0, 0.0, 0.05, 10.0, ranges)
    points = scan_to_points(scan)
    assert len(points) == 2
    np.testing.assert_allclose(points[0], [1.0, 0.0])
    mounted = scan_to_points(scan, np.array([0.2, 0.0, math.pi]))
    np.testing.assert_allclose(mounted[0], [-0.8, 0.0], atol=1e-12)
    directions = no_return_directions(scan)
    assert len(directions) == 1 and np.hypot(*directions[0]) == pytest.approx(1.0)


def test_deskew_puts_a_turning_sweep_back_on_the_walls() -> None:
    """A scan taken while turning at 2 rad/s: each beam cast from where the robot was at its time."""
    beams, step = 361, 1e-4
    angles = -math.pi / 2 + math.pi / 360 * np.arange(beams)
    start, wz, vx = np.array([0.3, -0.2, 0.4]), 2.0, 0.5
    ranges = np.empty(beams)
    for i in range(beams):
        t = i * step
        pose = compose(start, np.array([vx * t, 0.0, wz * t]))  # small-step motion, as the model assumes
        ranges[i] = cast(ROOM, pose, angles[i:i + 1])[0]
    scan = LaserScan(0, "laser", angles[0], angles[-1], math.pi / 360, step, 0.1, 0.05, 30.0, ranges)

    def wall_distance(points: np.ndarray) -> float:
        world = transform_points(start, points)
        a, b = ROOM[:, None, :2], ROOM[:, None, 2:]
        ab = b - a
        t = np.clip(np.einsum("wpk,wpk->wp", world[None] - a, ab) / np.einsum("wpk,wpk->wp", ab, ab), 0, 1)
        nearest = a + t[..., None] * ab
        return float(np.hypot(*(world[None] - nearest).transpose(2, 0, 1)).min(axis=0).mean())

    assert wall_distance(scan_to_points(scan)) > 0.02
    assert wall_distance(scan_to_points(scan, velocity=np.array([vx, 0.0, wz]))) < 1e-3


def test_voxel_filter_keeps_one_mean_point_per_cell_in_order() -> None:
    points = np.array([[0.01, 0.01], [0.03, 0.02], [1.0, 1.0], [0.02, 0.04]])
    thinned = voxel_filter(points, 0.05)
    np.testing.assert_allclose(thinned, [[0.02, 0.7 / 30], [1.0, 1.0]])
    assert voxel_filter(np.zeros((0, 2)), 0.05).shape == (0, 2)


def numpy_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """compose as numpy's array expressions computed it for one pose before its scalar path."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def numpy_inverse(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])], axis=-1)


def numpy_relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def assert_same_bits(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.shape == expected.shape and actual.dtype == expected.dtype == np.float64
    nan = np.isnan(expected)
    assert np.array_equal(np.isnan(actual), nan)
    assert np.array_equal(actual[~nan].view(np.uint64), expected[~nan].view(np.uint64))


coordinates = st.one_of(st.floats(-1e4, 1e4), st.floats(-1e-6, 1e-6), st.sampled_from([0.0, -0.0, math.pi, -math.pi]),
                        st.floats(allow_nan=True, allow_infinity=False, width=64))
wide_poses = st.tuples(coordinates, coordinates, coordinates).map(lambda p: np.array(p, np.float64))


@settings(max_examples=500, deadline=None)
@given(wide_poses, wide_poses)
def test_one_pose_algebra_equals_the_array_expressions_to_the_bit(a: np.ndarray, b: np.ndarray) -> None:
    """compose, relative and inverse of one pose (floats and math) against the numpy expressions they
    replaced for one pose, and against the vectorised path for a batch holding that pose."""
    with np.errstate(all="ignore"):
        assert_same_bits(compose(a, b), numpy_compose(a, b))
        assert_same_bits(relative(a, b), numpy_relative(a, b))
        assert_same_bits(inverse(a), numpy_inverse(a))
        assert_same_bits(compose(a[None], b[None])[0], compose(a, b))
        assert_same_bits(relative(a[None], b[None])[0], relative(a, b))
        assert_same_bits(inverse(a[None])[0], inverse(a))


def test_one_pose_algebra_keeps_numpys_answer_for_an_infinite_heading() -> None:
    a, b = np.array([1.0, 2.0, np.inf]), np.array([0.5, -0.5, 0.1])
    with np.errstate(all="ignore"):
        assert_same_bits(compose(a, b), numpy_compose(a, b))
        assert_same_bits(relative(a, b), numpy_relative(a, b))
        assert_same_bits(inverse(a), numpy_inverse(a))


def scan_to_points_before(scan: LaserScan, sensor_pose: np.ndarray | None, range_min: float | None,
                          range_max: float | None, velocity: np.ndarray | None) -> np.ndarray:
    """scan_to_points as it was before scan_returns and deskewed split it."""
    ranges = scan.ranges.astype(np.float64)
    low = scan.range_min if range_min is None else range_min
    high = scan.range_max if range_max is None else range_max
    keep = np.isfinite(ranges) & (ranges >= low) & (ranges <= high)
    angles = scan.angles()[keep]
    r = ranges[keep]
    points = np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)
    if sensor_pose is not None:
        points = transform_points(sensor_pose, points)
    if velocity is not None and scan.time_increment > 0:
        dt = np.flatnonzero(keep) * float(scan.time_increment)
        vx, vy, wz = (float(v) for v in velocity)
        turn = wz * dt
        c, s = np.cos(turn), np.sin(turn)
        points = np.stack([c * points[:, 0] - s * points[:, 1] + vx * dt,
                           s * points[:, 0] + c * points[:, 1] + vy * dt], axis=1)
    return points


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 400), st.sampled_from([0.0, 1e-5, 2.5e-5]), st.booleans(),
       st.booleans(), st.lists(st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-4, 4)), max_size=3))
def test_scan_returns_deskewed_equal_scan_to_points_to_the_bit(seed: int, beams: int, time_increment: float,
                                                              mounted: bool, limits: bool,
                                                              velocities: list[tuple[float, float, float]]) -> None:
    """One conversion (scan_returns), de-skewed by each velocity (deskewed), gives the points that converting
    the scan again for each velocity gave; so does scan_to_points."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.0, 35.0, beams).astype(np.float32)
    ranges[rng.random(beams) < 0.1] = np.inf
    ranges[rng.random(beams) < 0.05] = np.nan
    ranges[rng.random(beams) < 0.03] = -np.inf
    scan = LaserScan(0, "laser", -2.35, 2.35, 4.7 / max(beams, 1), time_increment, 0.025, 0.1, 30.0, ranges)
    mount = np.array([0.2, -0.1, 0.3]) if mounted else None
    low, high = (0.5, 20.0) if limits else (None, None)
    returns = scan_returns(scan, mount, low, high)
    for velocity in [None, *(np.array(v) for v in velocities)]:
        expected = scan_to_points_before(scan, mount, low, high, velocity)
        for actual in (deskewed(returns, velocity), scan_to_points(scan, mount, low, high, velocity)):
            assert actual.shape == expected.shape
            assert np.array_equal(actual.view(np.uint64), expected.view(np.uint64))
