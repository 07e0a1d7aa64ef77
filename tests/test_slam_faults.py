"""SLAM with faulty wheel odometry on the simulated office (exact ground truth): heading glitches,
slip, scale error and dropouts are bridged by the laser; with the odometry check off a glitch breaks
the map and the map self-check says so."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.fusion.evaluation.trajectory_errors import Trajectory, absolute_trajectory_error
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.odometry.faults import OdometryFault, dropped, faulty_wheels
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs import messages as m
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import load_world

SECONDS = 20.0


@pytest.fixture(scope="module")
def office():
    """20 s of the office route: wheel angles at 100 Hz, 40 Hz scans of a sweeping laser, the truth at each scan."""
    sim = RobotSim(load_world(), seed=3)
    wheel_t = np.arange(0.0, SECONDS, 0.01)
    angles = np.array([sim.encoder_angles_at(t) for t in wheel_t])
    scan_t = np.arange(0.0, SECONDS, 0.025)
    scans = [sim.laser_scan(t, int(round(t * 1e9))) for t in scan_t]
    return sim, wheel_t, angles, scan_t, scans, np.array([sim.pose_at(t) for t in scan_t])


def run(office, faults: list[OdometryFault], config: SlamConfig | None = None) -> tuple[Slam, float]:
    """SLAM over the office run with ``faults`` in the wheel angles; returns it and its ATE (m)."""
    sim, wheel_t, angles, scan_t, scans, truth = office
    left, right = faulty_wheels(wheel_t, angles[:, 0], angles[:, 1], faults, sim.model.wheel_radius_m,
                                sim.model.track_m)
    keep = ~dropped(wheel_t, faults)
    mount = sim.model.laser
    slam = Slam(config or SlamConfig(), DiffDriveOdometry(sim.model.wheel_radius_m, sim.model.track_m),
                laser_pose=(mount.x, mount.y, mount.yaw))
    events = sorted([(t, 0, k) for k, t in enumerate(wheel_t) if keep[k]] + [(t, 1, k) for k, t in enumerate(scan_t)])
    for t, kind, k in events:
        if kind == 0:
            slam.process("/wheels", m.JointState(int(round(t * 1e9)), "base_link", ("left", "right"),
                                                 np.array([left[k], right[k]])))
        else:
            slam.process("/scan", scans[k])
    slam.finish()
    stamps, poses = slam.trajectory()
    return slam, absolute_trajectory_error(Trajectory(stamps, poses), Trajectory(stamps, truth)).rmse_m


def test_clean_run_is_accurate_and_consistent(office) -> None:
    slam, ate = run(office, [])
    assert ate < 0.02 and slam.check_map().passed and slam.stats.odometry_rejected <= 5


GLITCHES = [OdometryFault("heading_glitch", 5.0, 0.02, math.radians(20.0)),
            OdometryFault("heading_glitch", 12.0, 0.02, math.radians(-20.0))]


def test_sharp_heading_glitches_are_rejected_and_bridged(office) -> None:
    slam, ate = run(office, GLITCHES)
    assert slam.stats.odometry_rejected >= 2
    assert ate < 0.03 and slam.check_map().passed


def test_without_the_odometry_check_a_glitch_breaks_the_map_and_the_check_says_so(office) -> None:
    slam, ate = run(office, GLITCHES, SlamConfig.from_mapping({"odometry": {"check": False}}))
    check = slam.check_map()
    assert ate > 0.3
    assert not check.passed and any(b - a + 1 >= check.min_stretch for a, b in check.stretches)


@pytest.mark.parametrize("fault", [OdometryFault("slip", 6.0, 1.0, 0.2), OdometryFault("scale", 0.0, SECONDS, 0.02),
                                   OdometryFault("dropout", 7.0, 1.5)], ids=["slip", "scale", "dropout"])
def test_slip_scale_and_dropout_are_carried_by_the_laser(office, fault) -> None:
    """A wheel spinning 20 % fast for a second, a 2 % wrong wheel radius, 1.5 s without odometry."""
    slam, ate = run(office, [fault])
    assert ate < 0.03 and slam.check_map().passed
