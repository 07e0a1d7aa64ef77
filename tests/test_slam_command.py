"""`trundle slam` end to end on a small simulated log: every output file, the MCAP topics, user errors."""

from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest

from tests.cli_run import trundle
from tests.planar_world import ROOM, scan
from tests.test_slam import loop_path
from trundle.fusion.mapping.map_io import load_map, read_trajectory_csv
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.logs import messages as m
from trundle.logs.importers import write_log
from trundle.logs.reader import LogReader


@pytest.fixture(scope="module")
def simulated_log(tmp_path_factory):
    """Odometry (drifting) and 270-degree scans of one lap of the polygon room, laser 0.1 m ahead."""
    truth = loop_path(laps=1, step_m=0.3)
    odometry = drifting_odometry(truth, seed=4)
    mount = np.array([0.1, 0.0, 0.0])
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(0, "base_link", "laser", 0.1, 0.0, 0.0),)), 0)]
    for k, (pose, odo) in enumerate(zip(truth, odometry, strict=True)):
        stamp = 10**9 * (k + 1) // 2
        laser = pose + np.array([mount[0] * math.cos(pose[2]), mount[0] * math.sin(pose[2]), 0.0])
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *odo), stamp))
        items.append(("/scan", scan(ROOM, laser, beams=181, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    write_log(items, path, metadata={"command": "test"})
    return path, truth


def test_slam_command_writes_every_output(simulated_log, tmp_path, capsys) -> None:
    path, truth = simulated_log
    out = tmp_path / "out"
    code, stdout, stderr = trundle(capsys, "slam", str(path), "-o", str(out))
    assert code == 0, stderr
    assert "loop closures" in stdout
    for name in ("map.pgm", "map.yaml", "map.png", "trajectory.png", "trajectory.csv", "report.json", "slam.mcap"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert report["scans"] == len(truth)
    assert report["duration_s"] == pytest.approx(len(truth) * 0.5)  # from the /tf_static at t = 0
    assert report["real_time_factor"] == pytest.approx(report["duration_s"] / report["processing_s"])
    assert report["scan_to_map_residual_m"]["mean"] < 0.02 and report["match_score"]["mean"] > 0.6
    stamps, poses = read_trajectory_csv(out / "trajectory.csv")
    assert len(stamps) == len(truth) and stamps[0] == 500_000_000
    with open(out / "trajectory.csv") as f:
        assert next(csv.reader(f)) == ["t_ns", "x", "y", "theta"]
    assert np.hypot(*(poses[:, :2] - truth[:, :2]).T).mean() < 0.05  # laser mount from /tf_static used

    grid = load_map(out / "map.yaml")
    pgm = cv2.imread(str(out / "map.pgm"), cv2.IMREAD_UNCHANGED)
    assert pgm.dtype == np.uint8 and set(np.unique(pgm)) <= {0, 205, 254}
    with LogReader(out / "slam.mcap") as reader:
        items = list(reader.messages())
    topics = {i.topic for i in items}
    assert topics == {"/tf", "/map", "/path"}
    published = next(i.msg for i in items if i.topic == "/map")
    assert published.resolution == pytest.approx(grid.resolution) and published.origin_x == pytest.approx(grid.origin_x)
    assert np.array_equal(published.data >= 65, grid.data == 100)
    path_msg = next(i.msg for i in items if i.topic == "/path")
    np.testing.assert_allclose(path_msg.poses, poses, atol=1e-5)
    tfs = [i.msg.transforms[0] for i in items if i.topic == "/tf"]
    assert len(tfs) == len(truth) and (tfs[0].frame_id, tfs[0].child_frame_id) == ("map", "odom")


def test_slam_command_user_errors(simulated_log, tmp_path, capsys) -> None:
    path, _ = simulated_log
    bad_config = tmp_path / "bad.toml"
    bad_config.write_text("[slam]\nresolutoin = 0.1\n")
    cases = [("slam", str(tmp_path / "none.mcap"), "-o", str(tmp_path / "o")),
             ("slam", str(path), "-o", str(tmp_path / "o"), "--config", str(bad_config)),
             ("slam", str(path), "-o", str(tmp_path / "o"), "--config", str(tmp_path / "missing.toml"))]
    for argv in cases:
        code, _, stderr = trundle(capsys, *argv)
        assert code == 2, stderr
        assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr
    scans_only = tmp_path / "no_scan.mcap"
    write_log([("/odom", m.Odometry(1, "odom", "base_link", 0.0, 0.0, 0.0), 1)], scans_only, metadata={})
    code, _, stderr = trundle(capsys, "slam", str(scans_only), "-o", str(tmp_path / "o"))
    assert code == 2 and "has no topic /scan (sensor_msgs/msg/LaserScan" in stderr


def test_wheel_model_sources_in_order() -> None:
    from pathlib import Path

    from trundle.logs.errors import UserError
    from trundle.logs.reader import LogInfo, TopicInfo
    from trundle.tools.jobs.config import make_odometry

    wheels = {"/wheels": TopicInfo("sensor_msgs/msg/JointState")}
    robot = json.dumps({"wheel_radius_m": 0.077, "track_m": 0.33, "wheels": ["left", "right"]})
    devices = json.dumps({"can0": {"family": "can", "wheel_radius_m": 0.1, "track_m": 0.5, "wheels": ["l", "r"]}})
    info = LogInfo(Path("x.mcap"), 0, topics=dict(wheels), metadata={"trundle": {"robot": robot, "devices": devices}})
    assert make_odometry(info, {"odometry": {"wheel_radius_m": 0.2, "track_m": 0.4}}).track_m == 0.4
    assert make_odometry(info, {}).track_m == 0.33
    del info.metadata["trundle"]["robot"]
    odometry = make_odometry(info, {})
    assert (odometry.track_m, odometry.left, odometry.right) == (0.5, "l", "r")
    bare = LogInfo(Path("x.mcap"), 0, topics=dict(wheels))
    with pytest.raises(UserError, match="no wheel model"):
        make_odometry(bare, {})
    with pytest.raises(UserError, match="unknown"):
        make_odometry(bare, {"odometry": {"radius": 1}})
    bare.topics["/odom"] = TopicInfo("nav_msgs/msg/Odometry")
    assert make_odometry(bare, {}) is None
    assert make_odometry(LogInfo(Path("x.mcap"), 0), {}) is None
