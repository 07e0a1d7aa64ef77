"""Replay regression on a log recorded by `trundle demo` (tests/data/demo_short, see its README):
odometry, SLAM and marker detection on recorded data, scored against the simulator's ground truth.

Bounds come from the ground truth; values pinned from the first replay (odometry is arithmetic on
the logged wheel angles, so it is pinned exactly) catch a change in behaviour."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from trundle.fusion.evaluation.trajectory_errors import Trajectory, absolute_trajectory_error
from trundle.fusion.mapping.map_io import read_trajectory_csv
from trundle.logs.reader import LogReader
from trundle.logs.topics import IMAGE_TOPIC, SCAN_TOPIC, WHEELS_TOPIC
from trundle.tools.demo.scoring import map_wall_distances, path_length, score_markers, sensor_mount
from trundle.tools.demo.slam import run_slam, wheel_odometry
from trundle.tools.sim.world import load_world

DATA = Path(__file__).parent / "data" / "demo_short"
LOG = DATA / "demo.mcap"
SCANS, FRAMES = 880, 67


@pytest.fixture(scope="module")
def truth():
    return (Trajectory(*read_trajectory_csv(DATA / "ground_truth.csv")),
            Trajectory(*read_trajectory_csv(DATA / "frames_ground_truth.csv")))


@pytest.fixture(scope="module")
def slam_run():
    return run_slam(LOG)  # with the demo's SLAM options, no progress display


def test_ground_truth_files_belong_to_the_log(truth):
    scans, frames = truth
    with LogReader(LOG) as reader:
        scan_stamps = [m.msg.stamp_ns for m in reader.messages(topics=[SCAN_TOPIC])]
        frame_stamps = [m.msg.stamp_ns for m in reader.messages(topics=[IMAGE_TOPIC])]
    assert np.array_equal(scans.stamps_ns, scan_stamps) and len(scans) == SCANS
    assert np.array_equal(frames.stamps_ns, frame_stamps) and len(frames) == FRAMES
    # the route: from the start (6, 5.25) east along the corridor, turning north at its end
    assert np.allclose(scans.poses[0], [6.0, 5.25, 0.0])
    assert scans.poses[-1, 0] == pytest.approx(24.79, abs=0.01) and scans.poses[-1, 2] > 1.0


def test_wheel_odometry_replays_exactly_what_the_daemon_computed_live(truth):
    scans, _ = truth
    with LogReader(LOG) as reader:
        odometry = wheel_odometry(reader.info())
        replayed = [odometry.update(m.msg) for m in reader.messages(topics=[WHEELS_TOPIC])]
        live = [m.msg for m in reader.messages(topics=["/odom"])]
    replayed = [o for o in replayed if o is not None]
    assert len(replayed) == len(live) == 2187
    # the log was recorded when a live step ran numpy's vectorised arithmetic; it now runs in scalars (the same
    # formulas, another rounding): equal to a few ulps (2.2e-16 m measured)
    assert all(a.stamp_ns == b.stamp_ns and a.x == pytest.approx(b.x, abs=1e-12)
               and a.y == pytest.approx(b.y, abs=1e-12) and a.theta == pytest.approx(b.theta, abs=1e-12)
               for a, b in zip(replayed, live, strict=True))
    # pinned: the pose and distance the logged wheel angles integrate to
    pinned = [18.789902179956684, 0.09772442249100963, 1.2303213214683295]
    assert odometry.pose.tolist() == pytest.approx(pinned, abs=1e-9)
    assert odometry.distance_m == pytest.approx(19.03211177450195, abs=1e-9) and odometry.gaps == 0
    # against the ground truth: the distance to 0.1 %, the turn to 1 degree
    assert odometry.distance_m == pytest.approx(path_length(scans.poses), rel=1e-3)
    assert odometry.pose[2] == pytest.approx(scans.poses[-1, 2] - scans.poses[0, 2], abs=np.radians(1.0))


def test_slam_trajectory_and_map_against_the_ground_truth(truth, slam_run):
    scans, _ = truth
    stats = slam_run.slam.stats
    assert stats.scans == SCANS and stats.matched >= SCANS - 2
    ate = absolute_trajectory_error(slam_run.trajectory, scans)
    assert ate.count == SCANS
    assert ate.rmse_m <= min(0.05, 0.0385 + 0.01)          # acceptance bound; recorded 3.85 cm
    assert ate.rotation_rmse_deg <= 0.3                      # recorded 0.08 deg
    odometry = absolute_trajectory_error(slam_run.odometry, scans)
    assert odometry.rmse_m == pytest.approx(0.016551515495821987, abs=1e-6)
    walls = map_wall_distances(slam_run.grid, load_world(), np.array(ate.alignment_xyt))
    assert walls.size > 2000 and np.mean(walls <= 0.1) >= 0.97    # recorded 100 %


def test_markers_in_view_are_detected_with_their_ids_and_poses(truth):
    _, frames = truth
    world = load_world()
    score = score_markers(LOG, frames, world, sensor_mount(LOG, "camera"))
    assert score.frames == FRAMES and score.unmatched == 0
    # which markers the simulator had in view, from the true camera pose of each frame
    assert dict(score.in_view) == {96: 7, 3: 8, 150: 2}
    assert score.detected_ids() == [3, 96, 150]
    assert len(score.missed) <= 1                            # recorded: one frame of 96 at 4.4 m
    assert not [s for s in score.sightings if not s.in_image or not s.known]
    in_view = [s for s in score.sightings if s.in_view]
    assert len(in_view) == 16
    for s in in_view:                                        # recorded at most 1.6 % of the distance
        assert s.position_error_m <= 0.025 * s.distance_m, (s.id, s.distance_m, s.position_error_m)
        assert s.angle_error_deg <= 15.0
