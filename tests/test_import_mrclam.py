"""UTIAS MRCLAM importer: the real robot 1 of Dataset 2, a hand-made folder with exact expectations,
malformed rows and files, fuzzing, and the CLI."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import shared_file
from trundle.fusion.mapping.map_io import read_landmarks_csv, read_trajectory_csv
from trundle.logs.errors import DataError, UserError
from trundle.logs.importers.mrclam import (
    BEARING_SIGMA_RAD,
    import_mrclam,
    integrate,
    read_mrclam,
    sighting_covariance,
)
from trundle.logs.reader import LogReader
from trundle.logs.stamps import seconds_ns
from trundle.tools.cli.main import main

BARCODES = "# Subject #    Barcode #\n" + "".join(f"{s} {b}\n" for s, b in
                                                  [(1, 5), (2, 14), (3, 41), (4, 32), (5, 23), (6, 18), (7, 45)])
LANDMARKS = "# Subject # x y sx sy\n6 1.0 2.0 0.001 0.002\n7 -1.0 0.5 0.001 0.001\n"


def _folder(tmp_path: Path, odometry: str, measurements: str, truth: str | None = None) -> Path:
    folder = tmp_path / "MRCLAM_test"
    folder.mkdir()
    (folder / "Barcodes.dat").write_text(BARCODES)
    (folder / "Landmark_Groundtruth.dat").write_text(LANDMARKS)
    (folder / "Robot2_Odometry.dat").write_text("# Time [s] v w\n" + odometry)
    (folder / "Robot2_Measurement.dat").write_text("# Time [s] Subject # range bearing\n" + measurements)
    if truth is not None:
        (folder / "Robot2_Groundtruth.dat").write_text("# Time x y theta\n" + truth)
    return folder


def test_hand_made_folder_gives_exact_messages(tmp_path):
    """Two seconds on an arc (0.2 m/s, 0.5 rad/s from t = 100 s), sightings of landmarks 6 and 7, of
    robot 2 (barcode 14) and of an unknown barcode 99."""
    odometry = "".join(f"{100 + 0.5 * k:.3f} 0.2 0.5\n" for k in range(5))
    measurements = ("100.750 18 2.000 0.100\n100.750 45 3.000 -0.200\n101.000 14 1.500 0.000\n"
                    "101.250 99 1.000 0.000\n101.250 18 1.900 0.150\n")
    folder = _folder(tmp_path, odometry, measurements, truth="100.00 0.5 0.5 0.1\n100.02 0.5 0.51 0.1\n")
    out = tmp_path / "r2.mcap"
    counts, run, dropped = import_mrclam(folder, 2, out)
    assert counts == {"/odom": 5, "/landmarks": 2}
    assert dropped == {"robot_sightings": 1, "unknown_barcodes": 1}
    with LogReader(out) as reader:
        items = list(reader.messages())
    odom = [i.msg for i in items if i.topic == "/odom"]
    lists = [i.msg for i in items if i.topic == "/landmarks"]
    # exact arc: radius 0.4 m, after 2 s turned 1 rad
    last = odom[-1]
    assert (last.x, last.y, last.theta) == pytest.approx((0.4 * math.sin(1.0), 0.4 * (1 - math.cos(1.0)), 1.0))
    assert (last.vx, last.wz, last.frame_id, last.child_frame_id) == (0.2, 0.5, "odom", "base_link")
    assert [s.stamp_ns for s in lists] == [100_750_000_000, 101_250_000_000]
    first = lists[0].landmarks
    assert [(o.id, o.range, o.bearing) for o in first] == [("6", 2.0, 0.1), ("7", 3.0, -0.2)]
    np.testing.assert_allclose(first[1].covariance, np.diag([(0.02 + 0.03 * 3.0) ** 2, BEARING_SIGMA_RAD ** 2]))
    assert lists[0].frame_id == "base_link" and [o.id for o in lists[1].landmarks] == ["6"]
    # log order is time order, odometry first at equal stamps
    assert [i.log_time_ns for i in items] == sorted(i.log_time_ns for i in items)
    assert run.groundtruth_ns.tolist() == [100_000_000_000, 100_020_000_000]


def test_integration_is_exact_for_a_straight_line_and_a_turn_on_the_spot():
    stamps = np.array([0, 1_000_000_000, 3_000_000_000])
    poses = integrate(stamps, np.array([[1.0, 0.0], [0.0, math.pi / 4], [0.0, 0.0]]))
    np.testing.assert_allclose(poses, [[0, 0, 0], [1, 0, 0], [1, 0, math.pi / 2]], atol=1e-12)


def test_times_are_exact_nanoseconds():
    assert seconds_ns("1248275403.011") == 1_248_275_403_011_000_000
    assert seconds_ns("1248275403.011") - seconds_ns("1248275403.010") == 1_000_000


@pytest.mark.parametrize("token", ["inf", "-Infinity", "nan", "sNaN", "1e400", "-1", "x"])
def test_a_time_that_is_no_time_is_a_value_error(token):
    """Found by the fuzz test below: Decimal reads "inf", and int() of it raised OverflowError, not the data error."""
    with pytest.raises(ValueError):
        seconds_ns(token)


def test_malformed_rows_are_counted_and_dropped(tmp_path):
    odometry = "100.0 0.1 0.0\n100.5 0.1\nbad 0.1 0.0\n101.0 nan 0.0\n101.5 0.1 0.0\n"
    measurements = "100.5 18 2.0 0.1\n100.6 18.5 2.0 0.1\n100.7 18 -1.0 0.1\n100.8 18 2.0\n"
    folder = _folder(tmp_path, odometry, measurements)
    run = read_mrclam(folder, 2)
    assert run.malformed == {"Robot2_Odometry.dat": 3, "Robot2_Measurement.dat": 3}
    assert len(run.odometry) == 2 and len(run.sightings) == 1
    counts, _, _ = import_mrclam(folder, 2, tmp_path / "x.mcap")
    with LogReader(tmp_path / "x.mcap") as reader:
        assert '"Robot2_Odometry.dat": 3' in reader.info().metadata["trundle"]["malformed_rows"]


def test_missing_or_empty_files_are_one_line_errors(tmp_path):
    folder = _folder(tmp_path, "100.0 0.1 0.0\n", "100.5 18 2.0 0.1\n")
    with pytest.raises(UserError, match="robots 1 to 5"):
        read_mrclam(folder, 6)
    with pytest.raises(UserError, match="no such file .*Robot3_Odometry.dat"):
        read_mrclam(folder, 3)
    (folder / "Robot2_Measurement.dat").write_text("# only a comment\n")
    with pytest.raises(DataError, match="no valid rows"):
        read_mrclam(folder, 2)
    with pytest.raises(UserError, match="not a folder"):
        read_mrclam(folder / "Barcodes.dat", 2)


rows = st.lists(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                                   st.integers(-30, 100).map(str), st.text("0123456789.-e#x", max_size=6)),
                         max_size=5).map(" ".join), max_size=8).map("\n".join)


@settings(max_examples=100, deadline=None)
@given(rows, rows)
def test_any_text_reads_or_is_a_data_error(tmp_path_factory, odometry, measurements):
    folder = _folder(tmp_path_factory.mktemp("fuzz"), odometry, measurements)
    try:
        run = read_mrclam(folder, 2)
    except DataError:
        return
    assert np.all(np.isfinite(run.odometry)) and all(r >= 0 for _, r, _ in run.sightings)


@pytest.fixture(scope="module")
def robot1(tmp_path_factory):
    folder = shared_file("mrclam/Robot1_Odometry.dat").parent
    out = tmp_path_factory.mktemp("mrclam")
    assert main(["import", "mrclam", str(folder), "--robot", "1", "-o", str(out / "r1.mcap"),
                 "--reference", str(out / "truth.csv"), "--landmarks-reference", str(out / "landmarks.csv")]) == 0
    return folder, out


def test_robot1_of_dataset2(robot1):
    folder, out = robot1
    with LogReader(out / "r1.mcap") as reader:
        info = reader.info()
        lists = [i.msg for i in reader.messages(topics=["/landmarks"])]
    assert info.topics["/odom"].count == 121_742 and info.topics["/landmarks"].count == len(lists)
    sightings = [o for s in lists for o in s.landmarks]
    # 8,753 sightings in the file; 1,901 of them are of the other robots (barcodes 5, 14, 41, 32, 23)
    assert len(sightings) == 8_753 - 1_901
    assert {o.id for o in sightings} == {str(s) for s in range(6, 21)}
    stamps, truth = read_trajectory_csv(out / "truth.csv")
    assert len(stamps) == 94_999 and stamps[0] == 1_248_275_397_120_000_000
    np.testing.assert_allclose(truth[0], [1.916028, -2.676211, 0.3905])
    ids, positions, sigmas = read_landmarks_csv(out / "landmarks.csv")
    assert ids == [str(s) for s in range(6, 21)]
    np.testing.assert_allclose(positions[0], [0.19173646, -4.60955233], atol=1e-6)
    np.testing.assert_allclose(sigmas[0], [0.00013267, 0.00100015], atol=1e-6)
    robot_barcodes = {5, 14, 41, 32, 23}
    raw = np.loadtxt(folder / "Robot1_Measurement.dat")
    assert int(np.isin(raw[:, 1].astype(int), list(robot_barcodes)).sum()) == 1_901
    first = lists[0].landmarks[0]
    assert (first.id, first.range, first.bearing) == ("11", 1.910, -0.278)   # barcode 90 is subject 11
    np.testing.assert_allclose(first.covariance, sighting_covariance(1.910))


def test_cli_errors_are_one_line(tmp_path, capsys):
    folder = _folder(tmp_path, "100.0 0.1 0.0\n", "100.5 18 2.0 0.1\n")
    assert main(["import", "mrclam", str(folder), "--robot", "2", "-o", str(tmp_path / "a.mcap"),
                 "--reference", str(tmp_path / "t.csv")]) == 2
    stderr = capsys.readouterr().err
    assert "no Robot2_Groundtruth.dat" in stderr and len(stderr.strip().splitlines()) == 1
    assert main(["import", "mrclam", str(tmp_path / "nowhere"), "--robot", "2", "-o", str(tmp_path / "b.mcap")]) == 2
    stderr = capsys.readouterr().err
    assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
