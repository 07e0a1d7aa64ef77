"""Differential-drive odometry: hand-computed trajectories, chunking invariance, gaps, covariance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import shared_file
from trundle.fusion.geometry import wrap_angle
from trundle.fusion.odometry.diff_drive import (
    DiffDriveOdometry,
    OdometrySink,
    integrate,
    integrate_path,
    odometry_from_config,
    odometry_transform,
    propagate_covariance,
    step,
)
from trundle.logs import messages as m
from trundle.logs.errors import UserError

R, B = 0.1, 0.5  # wheel radius, track (m)


def angle_close(a: float, b: float) -> bool:
    return abs(wrap_angle(a - b)) < 1e-9


def js(stamp_ns: int, left_rad: float, right_rad: float, names=("left", "right")) -> m.JointState:
    return m.JointState(stamp_ns, "base_link", names, [left_rad, right_rad])


def run(odo: DiffDriveOdometry, left_rad, right_rad) -> m.Odometry:
    out = None
    for k, (a, b) in enumerate(zip(left_rad, right_rad, strict=True)):
        out = odo.update(js(k * 10_000_000, a, b))
    return out


def test_straight_line_is_exact():
    odo = DiffDriveOdometry(R, B)
    out = run(odo, [0.0, 10.0], [0.0, 10.0])  # 10 rad * 0.1 m = 1 m
    assert (out.x, out.y, out.theta) == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    assert out.vx == pytest.approx(1.0 / 0.01) and out.wz == 0.0


def test_quarter_arc_is_exact():
    # Centre of the turn 2 m to the left: wheels at 1.75 m and 2.25 m roll a quarter circle.
    turn, phi = 2.0, math.pi / 2
    d_left, d_right = (turn - B / 2) * phi, (turn + B / 2) * phi
    out = run(DiffDriveOdometry(R, B), [0.0, d_left / R], [0.0, d_right / R])
    assert out.x == pytest.approx(2.0, abs=1e-9) and out.y == pytest.approx(2.0, abs=1e-9)
    assert angle_close(out.theta, math.pi / 2)


def test_spin_in_place_is_exact():
    d = B / 2 * math.pi  # half a turn on the spot
    out = run(DiffDriveOdometry(R, B), [0.0, -d / R], [0.0, d / R])
    assert abs(out.x) < 1e-12 and abs(out.y) < 1e-12 and angle_close(out.theta, math.pi)


def test_square_legs_compose():
    # 1 m forward, spin +90 deg, 1 m forward -> (1, 1, 90 deg)
    q = B / 2 * math.pi / 2 / R
    left = np.array([0.0, 10.0, 10.0 - q, 20.0 - q])
    right = np.array([0.0, 10.0, 10.0 + q, 20.0 + q])
    out = run(DiffDriveOdometry(R, B), left, right)
    assert (out.x, out.y) == pytest.approx((1.0, 1.0), abs=1e-9) and angle_close(out.theta, math.pi / 2)


def test_integrate_is_pure_and_matches_arc_formula():
    pose = (1.0, -2.0, 0.3)
    end = integrate(pose, 0.4, 0.9, 0.5)
    dtheta = (0.9 - 0.4) / 0.5
    radius = 0.65 / dtheta
    expect = (1.0 + radius * (math.sin(0.3 + dtheta) - math.sin(0.3)),
              -2.0 - radius * (math.cos(0.3 + dtheta) - math.cos(0.3)), 0.3 + dtheta)
    assert tuple(end) == pytest.approx(expect, abs=1e-12)
    assert pose == (1.0, -2.0, 0.3)


steps = st.lists(st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)), min_size=1, max_size=40)


@settings(max_examples=100, deadline=None)
@given(steps, st.data())
def test_any_chunking_gives_the_same_pose(ticks, data):
    left = np.concatenate(([0.0], np.cumsum([a for a, _ in ticks])))
    right = np.concatenate(([0.0], np.cumsum([b for _, b in ticks])))
    stamps = np.arange(left.size) * 10_000_000
    one = DiffDriveOdometry(R, B)
    one.update_many(stamps, left, right)
    cuts = sorted(data.draw(st.sets(st.integers(1, left.size - 1), max_size=left.size)))
    chunked = DiffDriveOdometry(R, B)
    for lo, hi in zip([0, *cuts], [*cuts, left.size], strict=True):
        chunked.update_many(stamps[lo:hi], left[lo:hi], right[lo:hi])
    single = DiffDriveOdometry(R, B)
    run(single, left, right)
    for other in (chunked, single):
        assert np.allclose(other.pose, one.pose, rtol=0, atol=1e-9)
        assert np.allclose(other.covariance, one.covariance, rtol=1e-9, atol=1e-15)


finite = st.floats(-1e3, 1e3)


@settings(max_examples=300, deadline=None)
@given(st.tuples(finite, finite, st.floats(-50, 50)), st.lists(st.floats(-10, 10), min_size=6, max_size=6),
       st.floats(-2, 2) | st.floats(-1e-6, 1e-6), st.floats(-2, 2) | st.floats(-1e-6, 1e-6), st.floats(0.05, 3.0),
       st.floats(0.0, 1e-2))
def test_one_step_in_scalars_equals_the_vectorised_step(pose, cov_factors, d_left, d_right, track, variance):
    """The live path (one reading, scalar arithmetic) against integrate_path + propagate_covariance."""
    lower = np.zeros((3, 3))
    lower[np.tril_indices(3)] = cov_factors
    covariance = lower @ lower.T
    path = integrate_path(pose, d_left, d_right, track)
    expected = propagate_covariance(np.array(pose), covariance, path, np.array([d_left]), np.array([d_right]),
                                    track, variance)
    new_pose, new_covariance = step(pose, covariance, d_left, d_right, track, variance)
    assert np.allclose(new_pose, path[-1], rtol=1e-12, atol=1e-12)
    scale = 1.0 + np.abs(expected).max()
    assert np.allclose(new_covariance, expected, rtol=1e-12, atol=1e-12 * scale)


@settings(max_examples=100, deadline=None)
@given(st.floats(-2, 2), st.floats(-2, 2), st.integers(2, 50), st.floats(-3, 3))
def test_splitting_an_arc_leaves_the_pose_unchanged(d_left, d_right, pieces, theta0):
    whole = integrate((0.0, 0.0, theta0), d_left, d_right, B)
    split = integrate((0.0, 0.0, theta0), np.full(pieces, d_left / pieces), np.full(pieces, d_right / pieces), B)
    assert np.allclose(whole, split, rtol=0, atol=1e-9)


def test_covariance_grows_with_distance_not_time():
    odo = DiffDriveOdometry(R, B, wheel_variance_per_m=1e-3)
    run(odo, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert not odo.covariance.any()
    odo.update_many(np.arange(3, 103) * 10_000_000, np.linspace(0.1, 10.0, 100), np.linspace(0.1, 10.0, 100))
    # straight 1 m: var(x) = var((dl + dr) / 2) = 2 * k * 1 / 4, var(theta) = 2 * k * 1 / B^2
    assert odo.covariance[0, 0] == pytest.approx(1e-3 / 2, rel=1e-9)
    assert odo.covariance[2, 2] == pytest.approx(2e-3 / B**2, rel=1e-9)
    before = odo.covariance[1, 1]
    odo.update_many(np.arange(103, 203) * 10_000_000, np.linspace(10.1, 20.0, 100), np.linspace(10.1, 20.0, 100))
    assert odo.covariance[1, 1] > before > 0
    assert np.allclose(odo.covariance, odo.covariance.T) and np.all(np.linalg.eigvalsh(odo.covariance) > -1e-15)


def test_stale_wheel_flags_and_does_not_jump():
    odo = DiffDriveOdometry(R, B)
    run(odo, [0.0, 1.0], [0.0, 1.0])
    x_before = odo.pose[0]
    assert odo.update(js(30_000_000, math.nan, 1.2)) is None and odo.stale
    # the wheel comes back 500 rad further on: that motion is unseen, so it is not integrated
    out = odo.update(js(1_030_000_000, 501.0, 501.2))
    assert out.x == pytest.approx(x_before) and not odo.stale and odo.gaps == 1
    assert out.pose_covariance[0, 0] >= 1.0**2  # one second of gap at up to 1 m/s
    out = odo.update(js(1_040_000_000, 502.0, 502.2))
    assert out.x == pytest.approx(x_before + 0.1)


def test_unknown_joint_names_are_a_user_error():
    odo = DiffDriveOdometry(R, B)
    with pytest.raises(UserError):
        odo.update(js(0, 0.0, 0.0, names=("a", "b")))


def test_transform_matches_odometry():
    out = run(DiffDriveOdometry(R, B), [0.0, 3.0], [0.0, 5.0])
    tf = odometry_transform(out).transforms[0]
    assert (tf.frame_id, tf.child_frame_id) == ("odom", "base_link")
    assert tf.translation[:2] == pytest.approx((out.x, out.y)) and tf.yaw == pytest.approx(out.theta)


def test_breezyslam_ticks_give_the_published_dead_reckoning():
    # ../shared/data/README.md: 2000 ticks/rev, r = 77 mm, track 330 mm -> ~44.5 m and +79 deg.
    path = shared_file("breezyslam/exp2.dat")
    rows = np.array([line.split()[:4] for line in path.read_text().splitlines()], dtype=np.int64)
    odo = DiffDriveOdometry(0.077, 0.33)
    odo.update_many(rows[:, 0] * 1000, rows[:, 2] * 2 * math.pi / 2000, rows[:, 3] * 2 * math.pi / 2000)
    assert odo.distance_m == pytest.approx(44.5, abs=0.05)
    assert math.degrees(odo.pose[2]) == pytest.approx(79.0, abs=0.5)
    path_poses = integrate_path((0, 0, 0), np.diff(rows[:, 2]) * 2 * math.pi / 2000 * 0.077,
                                np.diff(rows[:, 3]) * 2 * math.pi / 2000 * 0.077, 0.33)
    assert np.allclose(path_poses[-1], odo.pose, atol=1e-9)


def test_sink_publishes_odometry_and_flags_gaps():
    out = []
    sink = OdometrySink(lambda topic, msg, t: out.append((topic, msg)), DiffDriveOdometry(R, B))
    for k, (a, b) in enumerate([(0.0, 0.0), (1.0, 1.0), (math.nan, 2.0), (3.0, 3.0), (4.0, 4.0)]):
        sink("/wheels", js(k * 10_000_000, a, b), k)
    sink("/can/rx", m.CanFrame(0, "can0", 1, b""), 9)
    topics = [t for t, _ in out]
    assert topics.count("/wheels") == 5 and topics.count("/odom") == 4 and topics.count("/tf") == 4
    assert topics[-1] == "/can/rx"
    flags = [msg.status[0] for t, msg in out if t == "/diagnostics"]
    assert [f.level for f in flags] == [m.WARN, m.OK] and "1 gap" in flags[1].message
    odoms = [msg for t, msg in out if t == "/odom"]
    assert odoms[-1].x == pytest.approx(0.2)  # 0.1 before the gap + 0.1 after; the gap's 0.1 is not integrated


def test_odometry_from_config():
    assert odometry_from_config({"encoders": "odrive:0,1"}) is None
    odo = odometry_from_config({"wheel_radius_m": 0.08, "track_m": 0.35, "wheels": ["l", "r"]})
    assert (odo.left_radius_m, odo.track_m, odo.left, odo.right) == (0.08, 0.35, "l", "r")
    for bad in ({"wheel_radius_m": 0.1}, {"wheel_radius_m": -1, "track_m": 0.3}, {"wheel_radius_m": "x", "track_m": 1},
                {"wheel_radius_m": 0.1, "track_m": 0.3, "wheels": ["only"]}):
        with pytest.raises(UserError):
            odometry_from_config(bad)
