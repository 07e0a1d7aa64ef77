"""CARMEN importer: hand-made lines of every type, fuzzing, the real Intel log, drifting odometry."""

from __future__ import annotations

import contextlib
import math
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import shared_file
from trundle.fusion.geometry import relative
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.logs import messages as m
from trundle.logs.importers.carmen import (
    CarmenLaser,
    CarmenOdom,
    import_carmen,
    messages,
    parse_line,
    read_carmen,
    scan_poses,
)
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main


def test_odom_line() -> None:
    record = parse_line("ODOM 1.5 -2.25 0.5 0.3 -0.1 0 12.75 pippo 12.8")
    assert record == CarmenOdom(12.75, 12.8, 1.5, -2.25, 0.5, 0.3, -0.1)


def test_flaser_line_angles_follow_gmapping() -> None:
    ranges = " ".join(["1.0"] * 180)
    record = parse_line(f"FLASER 180 {ranges} 1 2 0.1 1.1 2.1 0.2 5.5 host 5.6")
    assert isinstance(record, CarmenLaser)
    assert record.pose == (1.0, 2.0, 0.1) and record.odom_pose == (1.1, 2.1, 0.2)
    assert record.angle_min == -math.pi / 2 and record.angle_increment == pytest.approx(math.radians(1.0))
    odd = parse_line("FLASER 3 1 2 3 0 0 0 0 0 0 1 h 1")
    assert isinstance(odd, CarmenLaser) and odd.angle_increment == pytest.approx(math.pi / 3)
    assert parse_line("RLASER 3 1 2 3 0 0 0 0 0 0 1 h 1").kind == "RLASER"  # type: ignore[union-attr]


def test_robotlaser_both_variants_give_the_mount() -> None:
    # robot at (1, 2) facing +y, laser 0.5 m ahead of it: laser at (1, 2.5); mount (0.5, 0, 0)
    head = "ROBOTLASER1 0 -1.5708 3.1416 0.0174533 81.9 0.01 0 3 1.0 2.0 81.9"
    new = parse_line(f"{head} 2 7 8 1 2.5 1.5708 1 2 1.5708 0.1 0.2 0.3 0.4 0.5 10.0 host 10.1")
    old = parse_line(f"{head} 1 2.5 1.5708 1 2 1.5708 0.1 0.2 0.3 0.4 10.0 host 10.1")
    for record in (new, old):
        assert isinstance(record, CarmenLaser)
        assert record.pose == (1.0, 2.0, 1.5708)
        np.testing.assert_allclose(record.laser_offset, (0.5, 0.0, 0.0), atol=1e-5)  # 1.5708 ~ pi/2
        assert record.stamp_s == 10.0 and record.logger_s == 10.1 and record.max_range == 81.9
        assert record.angle_min == -1.5708 and record.angle_increment == 0.0174533
    scan = next(
        msg
        for topic, msg, _ in messages(read_lines([f"{head} 1 2.5 1.5708 1 2 1.5708 0.1 0.2 0.3 0.4 10.0 host 10.1"]))
        if topic == "/scan"
    )
    assert np.isposinf(scan.ranges[2]) and scan.ranges[0] == 1.0  # 81.9 = max range = no return


def read_lines(lines: list[str]):
    from trundle.logs.importers.carmen import CarmenLog
    log = CarmenLog()
    for line in lines:
        record = parse_line(line)
        if isinstance(record, CarmenOdom):
            log.order.append(("odom", len(log.odometry)))
            log.odometry.append(record)
        elif isinstance(record, CarmenLaser):
            log.order.append(("laser", len(log.lasers)))
            log.lasers.append(record)
    return log


@pytest.mark.parametrize(
    "line",
    [
        "ODOM 1 2 3",
        "FLASER 5 1 2",
        "FLASER x 1",
        "ROBOTLASER1 0 0 0",
        "ODOM a b c d e f g h i",
        "FLASER 2 1 2 0 0 0 0 0 0 nan h 1",
        "FLASER -1 0 0 0 0 0 0 0 0 0 0",
    ],
)
def test_malformed_lines_raise_value_error(line: str) -> None:
    with pytest.raises(ValueError):
        parse_line(line)


def test_other_types_and_comments_are_skipped() -> None:
    assert parse_line("# comment") is None
    assert parse_line("PARAM robot_front_laser_max 81.9") is None
    assert parse_line("NEFF 3.5") is None
    assert parse_line("") is None


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["ODOM", "FLASER", "RLASER", "ROBOTLASER1"]),
       st.lists(st.one_of(st.integers(-5, 400).map(str), st.floats(allow_nan=True).map(str), st.text(max_size=3)),
                max_size=30))
def test_fuzzed_lines_parse_or_raise_value_error(kind: str, tokens: list[str]) -> None:
    line = " ".join([kind, *tokens]).replace("\n", " ")
    with contextlib.suppress(ValueError):
        parse_line(line)


def test_intel_gfs_log_counts_ranges_and_times(tmp_path) -> None:
    path = shared_file("intel/intel.gfs.log")
    log = read_carmen(path)
    assert len(log.lasers) == 910 and len(log.odometry) == 14541 and log.skipped == {"NEFF": 910}
    first = log.lasers[0]
    assert first.stamp_s == 32.9068 and first.pose == (0.600266, -0.0320327, -0.354665)
    counts = import_carmen(path, tmp_path / "intel.mcap", log=log)
    assert counts == {"/odom": 14541, "/scan": 910, "/tf_static": 1}
    with LogReader(tmp_path / "intel.mcap") as reader:
        scans = [item for item in reader.messages(["/scan"])]
        info = reader.info()
    assert [s.msg.stamp_ns for s in scans] == [round(laser.stamp_s * 1e9) for laser in log.lasers]  # file order kept
    assert all(b.log_time_ns >= a.log_time_ns for a, b in pairwise(scans))
    assert sum(b.msg.stamp_ns < a.msg.stamp_ns for a, b in pairwise(scans)) == 4  # the log's own step-backs
    ranges = np.concatenate([s.msg.ranges for s in scans])
    assert scans[0].msg.range_max == pytest.approx(81.83)
    assert np.isposinf(ranges).mean() == pytest.approx(0.025, abs=0.003)  # README: 81.83 = no return, 2.5 %
    assert np.nanmin(ranges) == pytest.approx(0.23, abs=0.005)
    np.testing.assert_allclose([s.msg.ranges[0] for s in scans[:3]], [1.09, 1.72, 4.07], rtol=1e-6)  # first beams
    assert info.metadata["trundle"]["command"] == "import carmen"


def test_drifting_odometry_is_exact_without_noise_and_seeded_with() -> None:
    straight = np.column_stack([np.arange(11) * 0.5, np.zeros(11), np.zeros(11)])
    odo = drifting_odometry(straight, scale_error=0.05, heading_drift_rad_per_m=0.0, scale_noise=0.0,
                            heading_noise_rad_per_sqrt_m=0.0, turn_noise=0.0)
    np.testing.assert_allclose(odo[-1], [5.25, 0.0, 0.0], atol=1e-12)
    turned = drifting_odometry(straight, scale_error=0.0, heading_drift_rad_per_m=math.radians(2.0), scale_noise=0.0,
                               heading_noise_rad_per_sqrt_m=0.0, turn_noise=0.0)
    assert turned[-1, 2] == pytest.approx(math.radians(2.0) * 5.0)
    steps = relative(turned[:-1], turned[1:])
    np.testing.assert_allclose(np.hypot(steps[:, 0], steps[:, 1]), 0.5)
    a, b = drifting_odometry(straight, seed=3), drifting_odometry(straight, seed=3)
    assert np.array_equal(a, b) and not np.array_equal(a, drifting_odometry(straight, seed=4))


def test_import_command_with_drift_and_reference(tmp_path, capsys) -> None:
    path = shared_file("intel/intel.gfs.log")
    out, ref = tmp_path / "drift.mcap", tmp_path / "ref.csv"
    assert main(["import", "carmen", str(path), "-o", str(out), "--drift", "--seed", "1", "--reference", str(ref)]) == 0
    assert "/odom 910, /scan 910" in capsys.readouterr().out
    stamps, poses = scan_poses(read_carmen(path))
    table = np.loadtxt(ref, delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 1:], poses, atol=1e-6)
    with LogReader(out) as reader:
        odom = [item.msg for item in reader.messages(["/odom"])]
    assert len(odom) == 910 and all(isinstance(o, m.Odometry) for o in odom)
    np.testing.assert_allclose([odom[0].x, odom[0].y, odom[0].theta], poses[0], atol=1e-9)
    assert np.hypot(odom[-1].x - poses[-1, 0], odom[-1].y - poses[-1, 1]) > 1.0  # it drifted


def test_import_command_user_errors(tmp_path, capsys) -> None:
    bad = tmp_path / "empty.log"
    bad.write_text("# nothing here\nPARAM x 1\n")
    for argv in (["carmen", str(tmp_path / "missing.clf")], ["carmen", str(bad)]):
        assert main(["import", *argv, "-o", str(tmp_path / "o.mcap")]) == 2
        stderr = capsys.readouterr().err
        assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr


def test_odometry_source_auto_falls_back_to_the_laser_lines() -> None:
    """Many benchmark logs carry odometry only in their FLASER / ROBOTLASER1 lines."""
    from trundle.logs.importers.carmen import choose_odometry

    flaser = [f"FLASER 3 1 2 3 {k} 0 0 {k + 0.5} 0.1 0 {k}.0 h {k}.0" for k in range(5)]
    log = read_lines(flaser)
    assert choose_odometry(log) == ("laser", "no ODOM lines: the FLASER lines' odometry fields (5 poses)")
    odom = list(messages(log, odometry="laser"))
    poses = [(msg.x, msg.y) for topic, msg, _ in odom if topic == "/odom"]
    assert poses == [(k + 0.5, 0.1) for k in range(5)]  # the odometry fields, not the (corrected) pose
    head = "ROBOTLASER1 0 -1.5708 3.1416 0.0174533 81.9 0.01 0 3 1.0 2.0 81.9"  # the variant without remissions
    robot = read_lines([f"{head} {x} 0 0 {x} 0 0 0.1 0.2 0.3 0.4 {x}.0 host {x}.1" for x in range(3)])
    assert choose_odometry(robot)[0] == "laser"
    with_odom = read_lines(flaser + ["ODOM 0 0 0 0 0 0 9.0 h 9.0"])
    assert choose_odometry(with_odom) == ("odom", "1 ODOM lines")
    standing = read_lines(["FLASER 3 1 2 3 0 0 0 0 0 0 1.0 h 1.0"] * 3)
    assert choose_odometry(standing) == ("none", "no odometry: no ODOM lines and the laser lines' odometry fields "
                                                 "never change")
    assert choose_odometry(with_odom, "laser")[0] == "laser" and choose_odometry(with_odom, "none")[0] == "none"
    with pytest.raises(Exception, match="unknown odometry source"):
        choose_odometry(log, "wheels")
