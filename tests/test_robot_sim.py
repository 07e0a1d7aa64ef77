"""Simulated robot: route following, exact ground truth, wheels, slip, sensors sampled at any time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.tools.sim.robot import Mount, RobotModel, RobotSim
from trundle.tools.sim.world import cast_rays, load_world, parse_world, simulate_scan


@pytest.fixture(scope="module")
def office():
    return load_world()


@pytest.fixture(scope="module")
def perfect(office):
    return RobotSim(office, noise=False)


@pytest.fixture(scope="module")
def noisy(office):
    return RobotSim(office, seed=3)


def test_office_loop_returns_near_its_start_without_touching_walls(noisy, office):
    assert noisy.path_length_m() >= 50.0
    end = noisy.pose_at(noisy.duration_s)
    assert np.hypot(*(end[:2] - np.array(office.start[:2]))) < 0.15
    assert abs(math.remainder(end[2] - office.start[2], 2 * math.pi)) < 0.35
    beams = np.linspace(-math.pi, math.pi, 180, endpoint=False)
    clearance = [cast_rays(office.segments, p[:2], beams).distance.min()
                 for p in noisy.poses_at(np.arange(0.0, noisy.duration_s, 0.25))]
    assert min(clearance) > 0.45  # the robot is 0.5 m wide: 0.2 m to spare
    speeds = np.hypot(*np.diff(noisy.poses_at(np.arange(0, noisy.duration_s, 0.1))[:, :2], axis=0).T) / 0.1
    assert speeds.max() <= noisy.model.max_speed_m_s * 1.05


def test_odometry_of_perfect_wheels_reproduces_ground_truth_between_control_ticks(perfect, office):
    """trundle.fusion.odometry.diff_drive (the CAN helper's code) fed with wheel angles at every control tick and at
    times in between gives the ground truth exactly: wheels and poses are one consistent motion,
    and poses inside a control step lie on that step's arc."""
    model = perfect.model
    odometry = DiffDriveOdometry(model.wheel_radius_m, model.track_m)
    odometry.reset(office.start)
    ticks = np.arange(0.0, perfect.duration_s, model.control_period_s)
    times = np.unique(np.concatenate([ticks, np.arange(0.0037, perfect.duration_s, 0.0113)]))
    angles = np.array([perfect.wheel_angles_at(t) for t in times])
    out = odometry.update_many((times * 1e9).astype(np.int64), angles[:, 0], angles[:, 1])
    t = times[-1]
    truth = perfect.poses_at([t])[0]
    assert out.x == pytest.approx(truth[0], abs=1e-9) and out.y == pytest.approx(truth[1], abs=1e-9)
    assert math.remainder(out.theta - truth[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_straight_route_hand_computed():
    world = parse_world({"walls": [{"points": [[-1, -2], [8, -2], [8, 2], [-1, 2]], "closed": True}],
                         "route": [[0, 0], [5, 0]], "start": [0, 0, 0]})
    sim = RobotSim(world, RobotModel(wheel_radius_m=0.1), noise=False)
    end = sim.pose_at(sim.duration_s)
    assert end[0] == pytest.approx(5.0, abs=0.05) and end[1] == 0.0 and end[2] == 0.0
    left, right = sim.wheel_angles_at(sim.duration_s)
    assert left == right == pytest.approx(end[0] / 0.1, abs=1e-9)  # rolled distance / radius
    np.testing.assert_array_equal(sim.wheel_speeds_at(sim.duration_s + 1.0), [0.0, 0.0])
    # the laser 0.2 m ahead of base_link sees the east wall at 8 - x - 0.2 straight ahead
    t = sim.duration_s / 2
    ahead = sim.ranges_at(t)[sim.model.laser_model.beams // 2]
    assert ahead == pytest.approx(8.0 - sim.pose_at(t)[0] - 0.2, abs=1e-9)


def test_slip_and_encoder_noise_make_odometry_drift_by_a_bounded_amount(noisy, office):
    model = noisy.model
    count = 2 * math.pi / model.encoder_cpr
    times = np.arange(0.0, noisy.duration_s, 0.01)
    angles = np.array([noisy.encoder_angles_at(t) for t in times])
    np.testing.assert_allclose(angles / count, np.round(angles / count), atol=1e-6)  # whole counts
    odometry = DiffDriveOdometry(model.wheel_radius_m, model.track_m)
    odometry.reset(office.start)
    out = odometry.update_many((times * 1e9).astype(np.int64), angles[:, 0], angles[:, 1])
    error = np.hypot(out.x - noisy.pose_at(times[-1])[0], out.y - noisy.pose_at(times[-1])[1])
    assert 0.02 < error < 0.1 * noisy.path_length_m()


def test_sensors_are_deterministic_in_time_and_seed(office):
    a, b = RobotSim(office, seed=1, laps=1), RobotSim(office, seed=2)
    t = 12.345
    np.testing.assert_array_equal(a.ranges_at(t), a.ranges_at(t))
    assert not np.array_equal(a.ranges_at(t), b.ranges_at(t))
    np.testing.assert_array_equal(a.frame_at(t), a.frame_at(t))
    assert a.frame_at(t).shape == (480, 640, 3)


def test_laser_scan_is_taken_from_the_mounted_pose(perfect, office):
    t = 20.0
    base = perfect.pose_at(t)
    mount = perfect.model.laser
    laser = (base[0] + mount.x * math.cos(base[2]), base[1] + mount.x * math.sin(base[2]), base[2])
    np.testing.assert_allclose(perfect.ranges_at(t), simulate_scan(office, laser, perfect.model.laser_model),
                               rtol=0, atol=1e-9)
    camera = perfect.camera_pose_at(t)
    assert camera.z == perfect.model.camera.z and camera.yaw == pytest.approx(math.remainder(base[2], 2 * math.pi))
    assert Mount().x == 0.0
