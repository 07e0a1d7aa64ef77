"""SLAM over a demo log: the log replayed (as fast as possible) through the grid SLAM (``grid`` of
``trundle.fusion.slam.estimators``)
with wheel odometry from ``/wheels`` (the wheel model of the daemon's config, stored in the log)
and the laser mount from ``/tf_static``, with the default SLAM configuration (the one every log
gets: nothing here is tuned to the simulated robot); with ``markers`` the daemon's marker
sightings on ``/landmarks`` join the pose graph as landmarks
(the ``grid-landmarks`` estimator).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.evaluation.trajectory_errors import Trajectory
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry, odometry_from_config
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.estimators import EstimatorInputs, make_estimator
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.metadata import read_metadata
from trundle.logs.reader import LogInfo, LogReader
from trundle.logs.replay import replay
from trundle.logs.topics import LANDMARK_TOPIC, SCAN_TOPIC, TF_STATIC_TOPIC, WHEELS_TOPIC
from trundle.tools.jobs.progress import NoProgress, ProgressFactory


@dataclass(eq=False)
class SlamRun:
    """SLAM over a log: the optimised trajectory (one pose per scan, map frame), the wheel
    odometry at the same stamps (odom frame), the map, the SLAM object (stats, keyframes) and
    the wall-clock time SLAM took (s)."""

    slam: Slam
    trajectory: Trajectory
    odometry: Trajectory
    grid: m.OccupancyGrid
    processing_s: float


def wheel_odometry(info: LogInfo) -> DiffDriveOdometry:
    """Wheel odometry with the wheel model the log's metadata holds (the daemon's ``[can]`` table)."""
    model = read_metadata(info.metadata).wheel_model()
    odometry = odometry_from_config(model) if model is not None else None
    if odometry is None:
        raise UserError(f"{info.path}: no wheel model (wheel_radius_m, track_m) in the log's device metadata")
    return odometry


def run_slam(log: Path, config: SlamConfig | None = None, progress: ProgressFactory = NoProgress,
             markers: bool = False) -> SlamRun:
    """Replay ``log`` (as fast as possible) through SLAM with wheel odometry from ``/wheels``
    (``config`` default: the defaults), showing the scans done on a ``progress`` display; with
    ``markers`` the log's ``/landmarks`` too (a UserError when it has none)."""
    with LogReader(log) as reader:
        info = reader.info()
    if SCAN_TOPIC not in info.topics:
        raise UserError(f"{log}: no {SCAN_TOPIC} topic")
    if markers and LANDMARK_TOPIC not in info.topics:
        raise UserError(f"{log}: no {LANDMARK_TOPIC} topic (marker sightings of the daemon)")
    odometry = wheel_odometry(info)
    slam = make_estimator("grid-landmarks" if markers else "grid",
                          EstimatorInputs(config or SlamConfig(), odometry, landmark_topic=LANDMARK_TOPIC))
    assert isinstance(slam, Slam)
    odom_stamps: list[int] = []
    odom_poses: list[np.ndarray] = []
    bar = progress("slam", info.topics[SCAN_TOPIC].count)

    def feed(item: Any) -> None:
        result = slam.process(item.topic, item.msg)
        if item.topic == WHEELS_TOPIC and not odometry.stale:
            odom_stamps.append(item.msg.stamp_ns)
            odom_poses.append(odometry.pose.copy())
        elif result is not None:
            bar.update(slam.stats.scans, f"{slam.stats.scans} scans, {slam.stats.loop_closures} loop closures")

    started = time.perf_counter()
    replay(log, feed, rate=0.0,
           topics=[TF_STATIC_TOPIC, WHEELS_TOPIC, SCAN_TOPIC] + ([LANDMARK_TOPIC] if markers else []))
    slam.finish()
    bar.close()
    if slam.stats.scans == 0:
        raise UserError(f"{log}: no scans on {SCAN_TOPIC}")
    stamps, poses = slam.trajectory()
    grid = slam.build_map().to_message(int(stamps[-1]), "map")
    processing_s = time.perf_counter() - started
    odom = Trajectory(np.array(odom_stamps, np.int64), np.array(odom_poses).reshape(-1, 3))
    return SlamRun(slam, Trajectory(stamps, poses), interpolate(odom, stamps), grid, processing_s)


def interpolate(trajectory: Trajectory, stamps_ns: np.ndarray) -> Trajectory:
    """``trajectory`` at ``stamps_ns`` (linear in x, y and unwrapped heading; clamped at the ends)."""
    t = trajectory.stamps_ns - trajectory.stamps_ns[0]
    q = np.asarray(stamps_ns, np.int64) - trajectory.stamps_ns[0]
    poses = np.stack([np.interp(q, t, trajectory.poses[:, 0]), np.interp(q, t, trajectory.poses[:, 1]),
                      np.interp(q, t, np.unwrap(trajectory.poses[:, 2]))], axis=1)
    return Trajectory(stamps_ns, poses)
