"""BreezySLAM .dat importer: the real exp2 log, its README facts, fuzzing and the CLI."""

from __future__ import annotations

import contextlib
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import shared_file
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.logs.importers.breezyslam import ANGLE_MIN, ANGLE_STEP, import_breezyslam, parse_line, ranges_to_metres
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main


@pytest.fixture(scope="module")
def exp2_log(tmp_path_factory) -> tuple:
    path = shared_file("breezyslam/exp2.dat")
    out = tmp_path_factory.mktemp("exp2") / "exp2.mcap"
    counts = import_breezyslam(path, out)
    with LogReader(out) as reader:
        items = list(reader.messages())
        info = reader.info()
    return path, counts, items, info


def test_first_line_fields() -> None:
    line = shared_file("breezyslam/exp2.dat").read_text().splitlines()[0]
    parsed = parse_line(line)
    assert parsed is not None
    assert (parsed.time_us, parsed.left_ticks, parsed.right_ticks) == (361431443, 234835, 231727)
    assert parsed.ranges_mm.shape == (682,) and parsed.ranges_mm[:34].tolist() == [0] * 34
    assert parsed.ranges_mm.tolist() == [int(t) for t in line.split()[24:706]]


def test_range_codes_follow_rep_117() -> None:
    ranges = ranges_to_metres(np.array([0, 1, 19, 20, 5580]))
    assert np.isposinf(ranges[0]) and np.isnan(ranges[1]) and np.isnan(ranges[2])
    assert ranges[3:].tolist() == [0.02, 5.58]


def test_urg04lx_geometry() -> None:
    # steps 44..725 of 1024 per turn, front step 384: beam i at (i - 340) * 360/1024 deg
    assert math.degrees(ANGLE_MIN) == pytest.approx(-119.53125)
    assert math.degrees(ANGLE_MIN + 681 * ANGLE_STEP) == pytest.approx(119.8828125)


def test_exp2_import_counts_times_and_model(exp2_log) -> None:
    _, counts, items, info = exp2_log
    assert counts == {"/tf_static": 1, "/joint_states": 641, "/scan": 641}
    assert info.duration_s == pytest.approx(63.162132)
    robot = json.loads(info.metadata["trundle"]["robot"])
    assert robot["wheel_radius_m"] == 0.077 and robot["track_m"] == 0.33
    mount = items[0].msg.transforms[0]
    assert (mount.frame_id, mount.child_frame_id) == ("base_link", "laser")
    assert mount.translation.tolist() == [0.145, 0.0, 0.0]
    joints = [i.msg for i in items if i.topic == "/joint_states"]
    np.testing.assert_allclose(joints[0].position, np.array([234835, 231727]) * 2 * math.pi / 2000)
    np.testing.assert_allclose(joints[-1].position, np.array([412369, 411147]) * 2 * math.pi / 2000)
    scans = [i.msg for i in items if i.topic == "/scan"]
    ranges = np.concatenate([s.ranges for s in scans])
    assert np.isposinf(ranges).mean() == pytest.approx(0.55, abs=0.01)  # README: 55 % zeros
    assert np.isnan(ranges).sum() == 10795 - sum(  # README counts error codes over all 683 tokens
        int(t) in range(1, 20) for line in shared_file("breezyslam/exp2.dat").read_text().splitlines()
        for t in line.split()[706:707])
    assert np.nanmax(ranges[np.isfinite(ranges)]) == pytest.approx(5.58)


def test_exp2_dead_reckoning_matches_the_readme(exp2_log) -> None:
    """Wheel angles through our odometry: ~44.5 m of travel and +79 deg net heading (README)."""
    _, _, items, _ = exp2_log
    odometry = DiffDriveOdometry(0.077, 0.33)
    for item in items:
        if item.topic == "/joint_states":
            odometry.update(item.msg)
    assert odometry.distance_m == pytest.approx(44.5, abs=0.1)
    assert math.degrees(odometry.pose[2]) == pytest.approx(79.0, abs=1.0)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.one_of(st.integers(-10, 10**6).map(str), st.text(max_size=4)), max_size=720))
def test_fuzzed_lines_parse_or_raise_value_error(tokens: list[str]) -> None:
    with contextlib.suppress(ValueError):
        parse_line(" ".join(tokens))


def test_cli_imports_and_reports_user_errors(tmp_path, capsys) -> None:
    path = shared_file("breezyslam/exp2.dat")
    short = tmp_path / "short.dat"
    short.write_text("\n".join(path.read_text().splitlines()[:5]) + "\nbroken line\n")
    assert main(["import", "breezyslam", str(short), "-o", str(tmp_path / "short.mcap")]) == 0
    assert "/scan 5" in capsys.readouterr().out
    with LogReader(tmp_path / "short.mcap") as reader:
        assert reader.info().metadata["trundle"]["malformed_lines"] == "1"
    for bad in (tmp_path / "missing.dat", tmp_path):
        assert main(["import", "breezyslam", str(bad), "-o", str(tmp_path / "x.mcap")]) == 2
        stderr = capsys.readouterr().err
        assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
