"""`trundle slam --estimator ekf` on a laser log without markers: anonymous wall corners as the EKF's
landmarks (associated by JCBB), and the command's one-line errors."""

from __future__ import annotations

import json
import math
from itertools import pairwise

import numpy as np
import pytest

from tests.planar_world import ROOM, scan
from tests.test_landmark_perception import _on_segment
from tests.test_slam import loop_path
from trundle.fusion.evaluation.trajectory_errors import Trajectory, absolute_trajectory_error
from trundle.fusion.geometry import compose
from trundle.fusion.mapping.map_io import read_landmarks_csv, read_trajectory_csv
from trundle.logs import messages as m
from trundle.logs.importers import write_log
from trundle.tools.cli.main import main


@pytest.fixture(scope="module")
def room_log(tmp_path_factory):
    """Two laps of the test room at 2 Hz: exact odometry with a small drift, 271-beam scans."""
    truth = loop_path(laps=2)
    rng = np.random.default_rng(3)
    odometry = [truth[0]]
    for a, b in pairwise(truth):
        step = np.array([math.cos(a[2]) * (b[0] - a[0]) + math.sin(a[2]) * (b[1] - a[1]),
                         -math.sin(a[2]) * (b[0] - a[0]) + math.cos(a[2]) * (b[1] - a[1]),
                         math.remainder(b[2] - a[2], 2 * math.pi)])
        odometry.append(compose(odometry[-1], step * [1.02, 1.0, 1.01] + rng.normal(0, [0.005, 0.005, 0.003])))
    items = []
    for k, (pose, odom) in enumerate(zip(truth, odometry, strict=True)):
        stamp = 1_000_000_000 + k * 500_000_000
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *odom), stamp))
        items.append(("/scan", scan(ROOM, pose, beams=271, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
    folder = tmp_path_factory.mktemp("room")
    write_log(items, folder / "room.mcap", metadata={"command": "test"})
    return folder, Trajectory(1_000_000_000 + np.arange(len(truth)) * 500_000_000, truth)


def test_ekf_maps_the_rooms_corners_from_the_laser(room_log):
    folder, truth = room_log
    out = folder / "ekf"
    assert main(["slam", str(folder / "room.mcap"), "-o", str(out), "--estimator", "ekf"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["estimator"] == "ekf" and report["sightings"] == "laser corners"
    estimate = Trajectory(*read_trajectory_csv(out / "trajectory.csv"))
    ate = absolute_trajectory_error(estimate, truth)
    assert ate.rmse_m < 0.1, ate
    ids, positions, sigmas = read_landmarks_csv(out / "landmarks.csv")
    junctions = np.array([end for k, wall in enumerate(ROOM) for end in (wall[:2], wall[2:])
                          if any(_on_segment(end, other) for j, other in enumerate(ROOM) if j != k)])
    placed = compose(np.array(ate.alignment_xyt), np.column_stack([positions, np.zeros(len(ids))]))[:, :2]
    nearest = np.array([np.hypot(*(junctions - p).T).min() for p in placed])
    # the corners seen from many places are where two walls meet; the EKF's 3-sigma bounds hold them
    assert len(ids) >= 6 and np.mean(nearest < 0.1) >= 0.8, nearest
    assert np.all(nearest[sigmas.max(axis=1) < 0.05] < 3 * 0.05 + 0.03)
    assert report["ekf"]["paired"] > 5 * len(ids)   # re-sighted, not re-created
    for name in ("map.pgm", "trajectory.png", "slam.mcap"):
        assert (out / name).is_file()


def test_user_errors_are_one_line(room_log, tmp_path, capsys):
    folder, _ = room_log
    config = tmp_path / "bad.toml"
    config.write_text("[landmarks]\nassociation = 'guess'\n")
    empty = tmp_path / "empty.mcap"
    write_log([("/odom", m.Odometry(1, "odom", "base_link", 0.0, 0.0, 0.0), 1)], empty, metadata={})
    cases = [(["slam", str(folder / "room.mcap"), "-o", str(tmp_path / "a"), "--estimator", "ekf",
               "--config", str(config)], "bad.toml: landmarks.association = 'guess': expected one of jcbb or nn"),
             (["slam", str(empty), "-o", str(tmp_path / "b")], "has no topic /scan (sensor_msgs/msg/LaserScan"),
             (["slam", str(empty), "-o", str(tmp_path / "c"), "--estimator", "ekf"], "neither landmark sightings")]
    for argv, message in cases:
        assert main(argv) == 2
        stderr = capsys.readouterr().err
        assert message in stderr and len(stderr.strip().splitlines()) == 1, stderr
