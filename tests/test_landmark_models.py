"""Observation models (range-bearing, relative position, the inverse model), odometry increment
composition and its covariance, and time-correlated sighting errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.geometry import compose
from trundle.fusion.observation_models import point_from_range_bearing, range_bearing, relative_position
from trundle.fusion.odometry.increments import IncrementAccumulator, MotionNoise, OdometryIncrements, compose_jacobians
from trundle.fusion.optimization.error_correlation import ar1_weights, correlation_time, previous_gaps
from trundle.logs import messages as m

coordinates = st.floats(-20, 20)
angles = st.floats(-math.pi, math.pi)


def _numeric(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    base = f(x)
    return np.stack([(f(x + h * e) - base) / h for e in np.eye(len(x))], axis=-1)


@settings(max_examples=100, deadline=None)
@given(coordinates, coordinates, angles, coordinates, coordinates)
def test_range_bearing_values_and_jacobians(x, y, theta, lx, ly):
    pose, point = np.array([x, y, theta]), np.array([lx, ly])
    if np.hypot(lx - x, ly - y) < 0.1:
        return
    z, d_pose, d_point = range_bearing(pose[None], point[None])
    assert z[0, 0] == pytest.approx(math.hypot(lx - x, ly - y))
    assert math.remainder(z[0, 1] - (math.atan2(ly - y, lx - x) - theta), 2 * math.pi) == pytest.approx(0, abs=1e-9)

    def h_pose(p):
        v = range_bearing(p[None], point[None])[0][0]
        return np.array([v[0], math.remainder(v[1] - z[0, 1], 2 * math.pi)])

    def h_point(q):
        v = range_bearing(pose[None], q[None])[0][0]
        return np.array([v[0], math.remainder(v[1] - z[0, 1], 2 * math.pi)])

    np.testing.assert_allclose(d_pose[0], _numeric(h_pose, pose), atol=1e-4)
    np.testing.assert_allclose(d_point[0], _numeric(h_point, point), atol=1e-4)


@settings(max_examples=100, deadline=None)
@given(coordinates, coordinates, angles, st.floats(0.2, 30), angles)
def test_inverse_model_round_trip_and_jacobians(x, y, theta, r, b):
    pose, z = np.array([x, y, theta]), np.array([r, b])
    point, d_pose, d_z = point_from_range_bearing(pose[None], z[None])
    back = range_bearing(pose[None], point)[0][0]
    assert back[0] == pytest.approx(r, rel=1e-9, abs=1e-9)
    assert math.remainder(back[1] - b, 2 * math.pi) == pytest.approx(0, abs=1e-9)
    np.testing.assert_allclose(d_pose[0], _numeric(lambda p: point_from_range_bearing(p[None], z[None])[0][0], pose),
                               atol=1e-4)
    np.testing.assert_allclose(d_z[0], _numeric(lambda q: point_from_range_bearing(pose[None], q[None])[0][0], z),
                               atol=1e-4)
    local, lp, ll = relative_position(pose[None], point)
    np.testing.assert_allclose(local[0], [r * math.cos(b), r * math.sin(b)], atol=1e-9)
    np.testing.assert_allclose(lp[0], _numeric(lambda p: relative_position(p[None], point)[0][0], pose), atol=1e-4)
    np.testing.assert_allclose(
        ll[0], _numeric(lambda q: relative_position(pose[None], q[None])[0][0], point[0]), atol=1e-4
    )


def test_position_to_range_bearing_covariance():
    """A point 2 m straight ahead with 1 cm along and 4 cm across: range sigma 1 cm, bearing 0.02 rad."""
    o = m.LandmarkObservation.from_position("", [2.0, 0.0], np.diag([0.01 ** 2, 0.04 ** 2]))
    assert (o.range, o.bearing) == (2.0, 0.0)
    np.testing.assert_allclose(o.covariance, np.diag([0.01 ** 2, 0.02 ** 2]), atol=1e-15)
    np.testing.assert_allclose(o.position_covariance(), np.diag([0.01 ** 2, 0.04 ** 2]), atol=1e-15)
    np.testing.assert_allclose(o.translation, [2.0, 0.0, 0.0])


def test_increments_compose_with_covariance_as_matrices_do():
    rng = np.random.default_rng(0)
    noise = MotionNoise()
    acc = IncrementAccumulator(noise)
    delta, cov = np.zeros(3), np.zeros((3, 3))
    for _ in range(60):
        step, dt = rng.normal(size=3) * [0.1, 0.02, 0.2], 0.05
        ja, jb = compose_jacobians(delta, step)
        cov = ja @ cov @ ja.T + jb @ noise.step_covariance(step, dt) @ jb.T
        delta = compose(delta, step)
        acc.add(step, dt)
    np.testing.assert_allclose(acc.delta, delta, atol=1e-12)
    np.testing.assert_allclose(acc.covariance, cov, atol=1e-15)


def test_random_walk_covariance_does_not_depend_on_the_rate():
    """1 m straight at 10 Hz or 1000 Hz: the same heading variance (no per-reading floor)."""
    noise = MotionNoise(xy_per_m=0.1, theta_per_m=0.05, theta_per_rad=0.0, xy_per_s=0.0, theta_per_s=0.0)
    results = []
    for n in (10, 1000):
        acc = IncrementAccumulator(noise)
        for _ in range(n):
            acc.add((1.0 / n, 0.0, 0.0), 1.0 / n)
        results.append(acc.covariance)
    assert results[0][2, 2] == pytest.approx(0.05 ** 2) and results[1][2, 2] == pytest.approx(0.05 ** 2)
    # lateral error builds from the heading error: sum over the path of (1 - s)^2 ds -> 1/3 per m^2
    assert results[1][1, 1] == pytest.approx(0.1 ** 2 + 0.05 ** 2 / 3, rel=0.01)


def test_take_extrapolates_with_the_twist_to_a_sighting_between_readings():
    """Odometry of a robot on a circle at 0.5 m/s, 0.25 rad/s read at 10 Hz; a sighting 40 ms after a
    reading gets the exact pose on the arc (the reading's twist carried on)."""
    v, w = 0.5, 0.25
    def on_arc(t):
        return np.array([v / w * math.sin(w * t), v / w * (1 - math.cos(w * t)), w * t])
    odometry = OdometryIncrements()
    for k in range(11):
        odometry.add(m.Odometry(k * 100_000_000, "odom", "base_link", *on_arc(k * 0.1), vx=v, wz=w))
    first = odometry.take(0)
    np.testing.assert_allclose(first.delta, 0)
    odometry.add(m.Odometry(1_100_000_000, "odom", "base_link", *on_arc(1.1), vx=v, wz=w))
    increment = odometry.take(540_000_000)
    np.testing.assert_allclose(increment.delta, on_arc(0.54), atol=2e-4)   # straight-line extrapolation over 40 ms
    np.testing.assert_array_equal(increment.stamps_ns, np.arange(1, 6) * 100_000_000)
    np.testing.assert_allclose(increment.partial[-1], on_arc(0.5), atol=1e-12)
    rest = odometry.take(1_100_000_000)   # readings after the sighting stayed for the next increment
    np.testing.assert_allclose(compose(on_arc(0.54), rest.delta), on_arc(1.1), atol=2e-4)
    assert odometry.stale == 0
    odometry.take(3_000_000_000)   # 1.9 s after the last reading: stale, no extrapolation
    assert odometry.stale == 1


def test_correlation_time_of_ar1_errors_is_recovered():
    """Sightings of 5 landmarks at 5 Hz with AR(1) errors of correlation time 2 s in one component,
    white in the other: the estimate finds about 2 s and 0."""
    rng = np.random.default_rng(4)
    tau, dt = 2.0, 0.2
    rho = math.exp(-dt / tau)
    groups, stamps, errors = [], [], []
    for landmark in range(5):
        e = rng.normal()
        for k in range(600):
            e = rho * e + math.sqrt(1 - rho ** 2) * rng.normal()
            groups.append(landmark)
            stamps.append(k * dt + 0.01 * landmark)
            errors.append((e, rng.normal()))
    estimate = correlation_time(np.array(errors), np.array(groups), np.array(stamps))
    assert estimate[0] == pytest.approx(tau, rel=0.25)
    assert ar1_weights(np.array([dt]), estimate)[0, 1] > 0.95   # the white component keeps (nearly) full weight
    gaps, previous = previous_gaps(np.array([0, 1, 0, 0]), np.array([0.0, 0.5, 1.0, 3.0]))
    np.testing.assert_array_equal(gaps, [np.inf, np.inf, 1.0, 2.0])
    np.testing.assert_array_equal(previous, [-1, -1, 0, 2])
    w = ar1_weights(np.array([np.inf, 1.0]), np.array([2.0, 0.0]))
    np.testing.assert_allclose(w, [[1.0, 1.0], [(1 - math.exp(-0.5)) / (1 + math.exp(-0.5)), 1.0]])
