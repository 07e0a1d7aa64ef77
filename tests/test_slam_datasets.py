"""SLAM on the real datasets: Intel (GMapping-corrected poses as reference, drifting odometry) and exp2.

The unmarked tests run a prefix of each log; the ``slow`` ones run the whole logs and check the
acceptance figures (relation error, loop closures fixing the drift, map consistency).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import shared_file
from trundle.fusion.evaluation.trajectory_errors import (
    Trajectory,
    absolute_trajectory_error,
    relation_error,
    trajectory_relations,
)
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs.importers import breezyslam, carmen
from trundle.logs.topics import TF_STATIC_TOPIC
from trundle.tools.cli.main import main


def intel_run(scans: int | None, loop_closure: bool = True) -> tuple[Slam, Trajectory]:
    """Our SLAM on the Intel log with odometry = GMapping's poses + 5 %, 2 deg/m drift (seed 1)."""
    log = carmen.read_carmen(shared_file("intel/intel.gfs.log"))
    stamps, reference = carmen.scan_poses(log)
    odometry = drifting_odometry(reference, seed=1)
    slam = Slam(SlamConfig.from_mapping({"loop_closure": {"enabled": loop_closure}}))
    for topic, msg, _ in carmen.messages(log, odometry="laser", laser_odometry=odometry):
        if topic == TF_STATIC_TOPIC:
            continue
        if scans is not None and slam.stats.scans >= scans:
            break
        slam.process(topic, msg)
    slam.finish()
    return slam, Trajectory(stamps, reference)


def test_intel_prefix_relation_error() -> None:
    slam, reference = intel_run(150)
    estimate = Trajectory(*slam.trajectory())
    error = relation_error(estimate, trajectory_relations(Trajectory(reference.stamps_ns[:150], reference.poses[:150])))
    assert error.count == 149 and error.missing == 0
    assert error.translation_abs_m.mean <= 0.05 and error.rotation_abs_deg.mean <= 1.0


def test_exp2_prefix_through_wheel_odometry() -> None:
    lines, _ = breezyslam.read_dat(shared_file("breezyslam/exp2.dat"))
    slam = Slam(SlamConfig(), DiffDriveOdometry(breezyslam.WHEEL_RADIUS_M, breezyslam.TRACK_M))
    for topic, msg, _ in breezyslam.messages(lines[:200]):
        slam.process(topic, msg)
    assert slam.stats.scans == 200 and slam.stats.matched >= 195
    assert np.mean(slam.stats.residuals) < 0.025
    assert slam.map_residuals(slam.build_map()).mean() < 0.02


@pytest.mark.slow
def test_intel_full_relation_error_and_loop_closure() -> None:
    slam, reference = intel_run(None)
    estimate = Trajectory(*slam.trajectory())
    error = relation_error(estimate, trajectory_relations(reference))
    assert error.count == 909
    assert error.translation_abs_m.mean <= 0.05 and error.rotation_abs_deg.mean <= 1.0
    assert slam.stats.loop_closures > 50
    open_loop, _ = intel_run(None, loop_closure=False)
    with_loops = absolute_trajectory_error(estimate, reference)
    without = absolute_trajectory_error(Trajectory(*open_loop.trajectory()), reference)
    assert with_loops.rmse_m < 0.5 * without.rmse_m and with_loops.max_m < 0.3


@pytest.mark.slow
def test_exp2_full_command(tmp_path) -> None:
    mcap = tmp_path / "exp2.mcap"
    assert main(["import", "breezyslam", str(shared_file("breezyslam/exp2.dat")), "-o", str(mcap)]) == 0
    assert main(["slam", str(mcap), "-o", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["scans"] == 641 and report["loop_closures"] >= 1
    assert report["scan_to_map_residual_m"]["mean"] < 0.02
    assert report["path_length_m"] == pytest.approx(44.5, rel=0.1)
