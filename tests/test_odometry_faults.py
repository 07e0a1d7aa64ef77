"""Odometry fault models: hand-computed faulty paths, wheel-angle faults through the drive model,
random glitch placement, and properties that hold for any path."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.geometry import relative, wrap_angle
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.odometry.faults import OdometryFault, dropped, faulty_poses, faulty_wheels, random_glitches

R, B = 0.1, 0.5  # wheel radius, track (m)


def straight(seconds: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """One pose a second, 1 m/s along x."""
    times = np.arange(seconds + 1, dtype=np.float64)
    return times, np.column_stack([times, np.zeros_like(times), np.zeros_like(times)])


def test_heading_glitch_turns_everything_after_it_by_its_share_of_each_increment() -> None:
    # +90 deg over [2.5, 4.5] s: the increments 2->3, 3->4, 4->5 hold 1/4, 1/2, 1/4 of the window
    times, poses = straight()
    out = faulty_poses(times, poses, [OdometryFault("heading_glitch", 2.5, 2.0, math.pi / 2)])
    quarter = math.pi / 8
    expected_heading = [0, 0, 0, quarter, 3 * quarter, 4 * quarter, 4 * quarter, 4 * quarter, 4 * quarter]
    np.testing.assert_allclose(out[:, 2], expected_heading, atol=1e-12)
    # each 1 m step goes out along the heading of the pose before it (compose: the turn comes at its end)
    x = [0, 1, 2, 3, 3 + math.cos(quarter), 3 + math.cos(quarter) + math.cos(3 * quarter)]
    y = [0, 0, 0, 0, math.sin(quarter), math.sin(quarter) + math.sin(3 * quarter)]
    np.testing.assert_allclose(out[:6, 0], x, atol=1e-12)
    np.testing.assert_allclose(out[:6, 1], y, atol=1e-12)
    np.testing.assert_allclose(out[8, :2], [x[5], y[5] + 3.0], atol=1e-12)  # then 3 m straight up (+y)


def test_slip_and_scale_change_only_the_distances_in_their_window() -> None:
    times, poses = straight()
    slip = faulty_poses(times, poses, [OdometryFault("slip", 2.0, 2.0, 0.5)])
    steps = np.hypot(*np.diff(slip[:, :2], axis=0).T)
    np.testing.assert_allclose(steps, [1, 1, 1.5, 1.5, 1, 1, 1, 1], atol=1e-12)
    assert np.all(slip[:, 2] == 0)
    half = faulty_poses(times, poses, [OdometryFault("slip", 2.5, 1.0, 1.0)])  # half of 2->3 and half of 3->4
    np.testing.assert_allclose(np.hypot(*np.diff(half[:, :2], axis=0).T)[2:4], [1.5, 1.5], atol=1e-12)
    scaled = faulty_poses(times, poses, [OdometryFault("scale", 0.0, 8.0, -0.05)])
    assert scaled[-1, 0] == pytest.approx(8 * 0.95, abs=1e-12)


def test_dropout_marks_the_readings_in_its_window() -> None:
    times = np.arange(10.0)
    mask = dropped(times, [OdometryFault("dropout", 3.0, 2.0), OdometryFault("heading_glitch", 0.0, 9.0, 1.0)])
    assert list(np.flatnonzero(mask)) == [3, 4, 5]


def test_wheel_faults_through_the_drive_model() -> None:
    # 1 m/s straight for 8 s, wheel angles every 0.1 s
    times = np.arange(0, 8.001, 0.1)
    angles = times * 1.0 / R
    faults = [OdometryFault("heading_glitch", 2.0, 0.6, math.radians(20.0)), OdometryFault("slip", 5.0, 1.0, 0.3)]
    left, right = faulty_wheels(times, angles, angles, faults, R, B)
    odometry = DiffDriveOdometry(R, B)
    odometry.update_many((times * 1e9).astype(np.int64), left, right)
    assert math.degrees(odometry.pose[2]) == pytest.approx(20.0, abs=1e-9)  # the heading turned, exactly
    assert odometry.distance_m == pytest.approx(8.0 + 0.3, abs=1e-9)  # the glitch adds no distance, the slip 30 %


def test_fault_values_are_checked() -> None:
    for bad in (("wobble", 0, 1, 0), ("slip", 0, -1, 0.1), ("slip", 0, 1, -1.0), ("heading_glitch", math.nan, 1, 0)):
        with pytest.raises(ValueError):
            OdometryFault(*bad)


def test_random_glitches_are_spread_out_reproducible_and_inside_the_run() -> None:
    glitches = random_glitches(4, 400.0, math.radians(20.0), 0.6, seed=7)
    assert glitches == random_glitches(4, 400.0, math.radians(20.0), 0.6, seed=7)
    starts = [g.start_s for g in glitches]
    assert all(40.0 <= t <= 360.0 - 0.6 for t in starts)
    assert np.all(np.diff(starts) >= 400.0 / 8 - 1e-9)
    assert all(abs(g.value) == pytest.approx(math.radians(20.0)) and g.duration_s == 0.6 for g in glitches)
    with pytest.raises(ValueError):
        random_glitches(50, 10.0, 0.3, 0.6, seed=0)


steps = st.lists(st.tuples(st.floats(-0.5, 1.0), st.floats(-0.2, 0.2), st.floats(-0.5, 0.5)), min_size=2, max_size=30)
glitches = st.lists(st.tuples(st.floats(0.0, 30.0), st.floats(0.0, 5.0), st.floats(-1.0, 1.0)), max_size=4)


@settings(max_examples=60, deadline=None)
@given(steps, glitches)
def test_heading_glitches_add_their_turn_and_keep_every_step_length(path_steps, faults) -> None:
    moves = np.array(path_steps)
    poses = [np.zeros(3)]
    for u in moves:
        c, s = math.cos(poses[-1][2]), math.sin(poses[-1][2])
        poses.append(np.array([poses[-1][0] + c * u[0] - s * u[1], poses[-1][1] + s * u[0] + c * u[1],
                               poses[-1][2] + u[2]]))
    poses = np.array(poses)
    times = np.arange(len(poses), dtype=np.float64)
    glitch = [OdometryFault("heading_glitch", t, d, v) for t, d, v in faults]
    out = faulty_poses(times, poses, glitch)
    end = times[-1]  # the share of each window inside the run, by hand: (0, end] for an instant, else the overlap
    added = sum(g.value * (float(0.0 < g.start_s <= end) if g.duration_s == 0
                           else max(0.0, min(g.start_s + g.duration_s, end) - max(g.start_s, 0.0)) / g.duration_s)
                for g in glitch)
    assert wrap_angle(out[-1, 2] - poses[-1, 2] - added) == pytest.approx(0.0, abs=1e-9)
    original, faulty = relative(poses[:-1], poses[1:]), relative(out[:-1], out[1:])
    np.testing.assert_allclose(np.hypot(*faulty[:, :2].T), np.hypot(*original[:, :2].T), atol=1e-9)
