"""`trundle inject-faults` end to end: odometry poses and wheel angles get the faults, every other
record is copied untouched, the faults are in the metadata, and user mistakes end in one line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.cli_run import trundle
from tests.planar_world import ROOM, scan
from trundle.fusion.geometry import wrap_angle
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.logs import messages as m
from trundle.logs.importers import write_log
from trundle.logs.reader import LogReader


@pytest.fixture(scope="module")
def odometry_log(tmp_path_factory):
    """20 s along x at 0.5 m/s: odometry at 10 Hz, scans at 2 Hz, a static transform."""
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(0, "base_link", "laser", 0.1, 0.0, 0.0),)), 0)]
    for k in range(201):
        stamp = 10**9 + k * 100_000_000
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", -4.0 + 0.05 * k, 0.0, 0.0), stamp))
        if k % 5 == 0:
            items.append(("/scan", scan(ROOM, np.array([-4.0 + 0.05 * k, 0.0, 0.0]), beams=90, stamp_ns=stamp), stamp))
    path = tmp_path_factory.mktemp("faults") / "odom.mcap"
    write_log(items, path, metadata={"command": "test"})
    return path


@pytest.fixture(scope="module")
def wheel_log(tmp_path_factory):
    """Wheel angles (JointState, 20 Hz) of 10 s straight at 1 m/s; the wheel model in the robot metadata."""
    items = []
    for k in range(201):
        stamp = k * 50_000_000
        angle = k * 0.05 / 0.1
        items.append(("/wheels", m.JointState(stamp, "base_link", ("left", "right"), np.array([angle, angle])), stamp))
    path = tmp_path_factory.mktemp("faults") / "wheels.mcap"
    write_log(items, path, metadata={"command": "test", "robot": {"wheel_radius_m": 0.1, "track_m": 0.5}})
    return path


def raw(path, topic: str) -> list[bytes]:
    return [r.data for r in LogReader(path).raw_messages(topics=[topic])]


def test_heading_glitch_on_odometry_poses(odometry_log, tmp_path, capsys) -> None:
    out = tmp_path / "glitch.mcap"
    code, stdout, stderr = trundle(capsys, "inject-faults", str(odometry_log), "-o", str(out),
                                   "--heading-glitch", "5:20:0.6")
    assert code == 0, stderr
    assert "heading_glitch at 5.00 s for 0.60 s +20.0 deg" in stdout
    assert raw(out, "/scan") == raw(odometry_log, "/scan") and raw(out, "/tf_static") == raw(odometry_log, "/tf_static")
    before = [msg.msg for msg in LogReader(odometry_log).messages(topics=["/odom"])]
    after = [msg.msg for msg in LogReader(out).messages(topics=["/odom"])]
    assert len(before) == len(after) == 201
    t = np.array([(o.stamp_ns - before[0].stamp_ns) * 1e-9 for o in before])
    turn = np.array([wrap_angle(a.theta - b.theta) for a, b in zip(after, before, strict=True)])
    assert np.all(turn[t <= 5.0] == 0.0) and np.allclose(turn[t >= 5.6 - 1e-9], math.radians(20.0), atol=1e-9)
    # from the glitch on, the path runs off at 20 degrees: 0.5 m/s for the 14.4 s after the window
    last = after[-1]
    assert math.hypot(last.x - after[56].x, last.y - after[56].y) == pytest.approx(7.2, abs=1e-6)
    assert math.atan2(last.y - after[56].y, last.x - after[56].x) == pytest.approx(math.radians(20.0), abs=1e-9)
    faults = json.loads(LogReader(out).info().metadata["faults"]["faults"])
    assert faults == [{"kind": "heading_glitch", "start_s": 5.0, "duration_s": 0.6, "value": math.radians(20.0)}]


def test_dropout_removes_odometry_and_nothing_else(odometry_log, tmp_path, capsys) -> None:
    out = tmp_path / "dropout.mcap"
    code, stdout, _ = trundle(capsys, "inject-faults", str(odometry_log), "-o", str(out), "--dropout", "4:1.95")
    assert code == 0 and "/odom 181 of 201 kept (20 dropped)" in stdout
    info = LogReader(out).info()
    assert info.topics["/odom"].count == 181 and info.topics["/scan"].count == 41


def test_wheel_angles_get_the_glitch_the_slip_and_the_scale(wheel_log, tmp_path, capsys) -> None:
    out = tmp_path / "wheels.mcap"
    code, _, stderr = trundle(capsys, "inject-faults", str(wheel_log), "-o", str(out), "--heading-glitch", "2:-30",
                              "--slip", "6:2:0.5", "--scale", "0.02", "--json")
    assert code == 0, stderr
    odometry = DiffDriveOdometry(0.1, 0.5)
    for item in LogReader(out).messages(topics=["/wheels"]):
        odometry.update(item.msg)
    assert math.degrees(odometry.pose[2]) == pytest.approx(-30.0, abs=1e-6)
    # 10 m, 2 m of it slipping by 50 %, all 2 % long
    assert odometry.distance_m == pytest.approx((10.0 + 0.5 * 2.0) * 1.02, rel=1e-6)


def test_random_glitches_from_the_command_line(odometry_log, tmp_path, capsys) -> None:
    out = tmp_path / "random.mcap"
    code, stdout, _ = trundle(capsys, "inject-faults", str(odometry_log), "-o", str(out), "--glitches", "3",
                              "--seed", "4", "--json")
    assert code == 0
    report = json.loads(stdout)
    assert len(report["faults"]) == 3 and all(f["kind"] == "heading_glitch" for f in report["faults"])


@pytest.mark.parametrize("argv, message", [
    (["--heading-glitch", "soon:20"], "--heading-glitch 'soon:20': expected T:DEG or T:DEG:S"),
    (["--slip", "1:2"], "--slip '1:2': expected T:S:FRACTION"),
    (["--slip", "1:2:-1.5"], "would reverse the wheels"),
    ([], "no fault asked for"),
    (["--heading-glitch", "100:30"], "heading_glitch at 100 s is outside the log's odometry (0 to 20.00 s"),
    (["--dropout=-1:2"], "dropout at -1 s is outside the log's odometry"),
])
def test_user_mistakes_end_in_one_line(odometry_log, tmp_path, capsys, argv, message) -> None:
    code, _, stderr = trundle(capsys, "inject-faults", str(odometry_log), "-o", str(tmp_path / "x.mcap"), *argv)
    assert code == 2 and message in stderr and len(stderr.strip().splitlines()) == 1


def test_a_log_without_odometry_or_the_same_file_is_refused(odometry_log, tmp_path, capsys) -> None:
    scans_only = tmp_path / "scans.mcap"
    write_log([("/scan", scan(ROOM, np.zeros(3), beams=30, stamp_ns=1), 1)], scans_only, metadata={})
    code, _, stderr = trundle(capsys, "inject-faults", str(scans_only), "-o", str(tmp_path / "y.mcap"),
                              "--scale", "0.1")
    assert code == 2 and "has no odometry" in stderr
    code, _, stderr = trundle(capsys, "inject-faults", str(odometry_log), "-o", str(odometry_log), "--scale", "0.1")
    assert code == 2 and "exists" in stderr and "never overwritten" in stderr
