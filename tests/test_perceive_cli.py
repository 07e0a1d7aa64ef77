"""`trundle perceive`: pipelines over a small log, detections read back, user errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from trundle.drivers.camera import OPTICAL_ROTATION
from trundle.logs import messages as m
from trundle.logs.reader import LogReader, read_messages
from trundle.logs.writer import Logger
from trundle.perception.markers import dictionary_by_name
from trundle.tools.cli.main import main

ORANGE = (0, 128, 255)
CENTRES = [(80.0, 60.0), (230.0, 150.0), (150.0, 205.0)]
MARKERS = {3: (200, 20), 17: (40, 130)}      # id -> top-left corner of a 60 px DICT_4X4_50 marker
SIDE_PX, FOCAL = 60, 500.0
K = np.array([[FOCAL, 0, 160], [0, FOCAL, 120], [0, 0, 1]])
T0 = 1_700_000_000_000_000_000


def _frame(shift: int) -> np.ndarray:
    image = np.full((240, 320, 3), 170, np.uint8)
    for x, y in CENTRES:
        cv2.ellipse(image, (int(x) + shift, int(y)), (18, 10), 30, 0, 360, ORANGE, -1)
    dictionary = dictionary_by_name("DICT_4X4_50")
    for marker_id, (x, y) in MARKERS.items():
        image[y - 10:y + SIDE_PX + 10, x - 10 + shift:x + SIDE_PX + 10 + shift] = 255   # quiet zone
        image[y:y + SIDE_PX, x + shift:x + SIDE_PX + shift] = cv2.aruco.generateImageMarker(dictionary, marker_id,
                                                                                               SIDE_PX)[:, :, None]
    return image


@pytest.fixture()
def log(tmp_path: Path) -> Path:
    path = tmp_path / "camera.mcap"
    with Logger(path, salvage=False) as logger:
        calibration = m.CameraInfo(T0, "camera_optical", 240, 320, "plumb_bob", np.zeros(5), K)
        logger.write("/camera/camera_info", calibration, T0)
        for i, fmt in enumerate(["png", "png", "jpeg"]):
            data = cv2.imencode(f".{fmt}", _frame(i), (cv2.IMWRITE_JPEG_QUALITY, 98))[1].tobytes()
            stamp = T0 + (i + 1) * 100_000_000
            logger.write("/camera/image_raw/compressed", m.CompressedImage(stamp, "camera_optical", fmt, data), stamp)
        stamp = T0 + 400_000_000
        corrupt = m.CompressedImage(stamp, "camera_optical", "jpeg", b"\xff\xd8junk")
        logger.write("/camera/image_raw/compressed", corrupt, stamp)
    return path


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict]:
    code = main(["perceive", *argv, "--json"])
    out = capsys.readouterr().out
    return code, json.loads(out) if code in (0, 1) else {}


def _by_topic(path: Path) -> dict[str, list]:
    topics: dict[str, list] = {}
    for item in read_messages(path):
        topics.setdefault(item.topic, []).append(item)
    return topics


def test_color_bounds_pipeline_draws_each_region(log: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "color.mcap"
    code, summary = _run(capsys, str(log), "--pipeline", "color", "--lower", "20,0.8,0.8", "--upper", "40,1,1",
                         "-o", str(out))
    assert code == 0
    assert summary["frames"] == 3 and summary["corrupt_messages"] == 1 and summary["regions"] == 9
    assert summary["detections_per_frame"] == {"mean": 3.0, "min": 3, "max": 3} and summary["dropped"] == 0
    topics = _by_topic(out)
    assert len(topics["/camera/image_raw/compressed"]) == 4          # every image copied, corrupt one too
    assert len(topics["/camera/camera_info"]) == 1
    centroids = topics["/camera/image_raw/compressed/color_centroids"]
    ellipses = topics["/camera/image_raw/compressed/color_ellipses"]
    assert len(centroids) == len(ellipses) == 3
    for shift, item in enumerate(centroids):
        marker = item.msg
        assert isinstance(marker, m.ImageMarker) and marker.type == m.POINTS
        assert marker.stamp_ns == T0 + (shift + 1) * 100_000_000 == item.log_time_ns
        assert marker.frame_id == "camera_optical"
        expected = np.array(sorted((x + shift, y) for x, y in CENTRES))
        assert np.abs(np.array(sorted(map(tuple, marker.points))) - expected).max() < 0.6
    outline = ellipses[0].msg
    assert outline.type == m.LINE_LIST and len(outline.points) == 3 * 2 * 36
    # each outline lies on its drawn ellipse: semi-axes 18 and 10 px at 30 deg (+0.5 px rasterisation)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    for points in outline.points.reshape(3, 72, 2):
        centre = min(CENTRES, key=lambda p: np.hypot(*(points.mean(axis=0) - p)))
        d = points - centre
        u, v = d @ [c, s], d @ [-s, c]
        assert np.abs(np.hypot(u / 18.5, v / 10.5) - 1).max() < 0.05


def test_color_template_pipeline(log: Path, tmp_path: Path, capsys) -> None:
    template = tmp_path / "orange.png"
    cv2.imwrite(str(template), np.full((10, 10, 3), ORANGE, np.uint8))
    code, summary = _run(capsys, str(log), "--pipeline", "color", "--template", str(template), "-o",
                         str(tmp_path / "t.mcap"), "--no-images")
    assert code == 0 and summary["regions"] == 9
    assert set(_by_topic(tmp_path / "t.mcap")) == {"/camera/image_raw/compressed/color_ellipses",
                                                   "/camera/image_raw/compressed/color_centroids"}


def test_markers_pipeline_with_poses(log: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "markers.mcap"
    code, summary = _run(capsys, str(log), "--pipeline", "markers", "--dictionary", "DICT_4X4_50",
                         "--marker-size", "0.12", "-o", str(out))
    assert code == 0
    assert summary["marker_ids"] == {"3": 3, "17": 3} and summary["poses"] == 6
    topics = _by_topic(out)
    outlines = topics["/camera/image_raw/compressed/aruco_outlines"]
    assert [len(o.msg.points) for o in outlines] == [16, 16, 16]   # 2 markers x 4 edges x 2 ends
    first = outlines[0].msg.points.reshape(-1, 2)
    assert np.abs(first.min(axis=0) - [40 - 0.5, 20 - 0.5]).max() < 1.0
    tf = topics["/tf"]
    assert len(tf) == 3
    children = {t.child_frame_id: t for t in tf[0].msg.transforms}
    assert set(children) == {"aruco_3", "aruco_17"}
    # fronto-parallel: depth = f L / side = 500 * 0.12 / 60 = 1.0 m; x from the marker centre
    pose = children["aruco_3"]
    assert pose.frame_id == "camera_optical" and pose.stamp_ns == tf[0].msg.transforms[0].stamp_ns
    assert pose.translation[2] == pytest.approx(1.0, rel=0.02)
    assert pose.translation[0] == pytest.approx((200 + 30 - 0.5 - 160) / FOCAL, abs=0.01)


def test_markers_become_landmarks_in_the_robot_frame(log: Path, tmp_path: Path, capsys) -> None:
    """With the camera's mount on /tf_static (0.2 m ahead, 0.5 m up, looking forward) each frame's markers
    are one LandmarkList in base_link: the optical (x right, z forward) pose turned into (x forward, y left)."""
    mounted = tmp_path / "mounted.mcap"
    with LogReader(log) as reader, Logger(mounted, salvage=False) as logger:
        logger.write("/tf_static", m.TFMessage((
            m.TransformStamped.planar(T0, "base_link", "camera", 0.2, 0.0, 0.0, z=0.5),
            m.TransformStamped(T0, "camera", "camera_optical", (0, 0, 0), OPTICAL_ROTATION))), T0)
        for raw in reader.raw_messages():
            logger.write_encoded(raw.topic, raw.ros_type, raw.data, raw.log_time_ns)
    out = tmp_path / "landmarks.mcap"
    code, summary = _run(capsys, str(mounted), "--pipeline", "markers", "--dictionary", "DICT_4X4_50",
                         "--marker-size", "0.12", "-o", str(out))
    assert code == 0 and summary["landmark_messages"] == 3 and summary["poses_without_camera_mount"] == 0
    topics = _by_topic(out)
    lists = [item.msg for item in topics["/landmarks"]]
    assert len(lists) == 3 and all(s.frame_id == "base_link" for s in lists) and "/tf_static" in topics
    by_id = {o.id: o for o in lists[0].landmarks}
    optical = {t.child_frame_id: t.translation for t in topics["/tf"][0].msg.transforms}["aruco_3"]
    np.testing.assert_allclose(by_id["3"].translation, [0.2 + optical[2], -optical[0], 0.5 - optical[1]], atol=1e-9)
    assert by_id["3"].oriented and by_id["3"].range == pytest.approx(math.hypot(0.2 + optical[2], optical[0]))


def test_markers_without_camera_info_count_missing_poses(log: Path, tmp_path: Path, capsys) -> None:
    code, summary = _run(capsys, str(log), "--pipeline", "markers", "--dictionary", "4x4_50", "--marker-size",
                         "0.1", "--camera-info", "/nowhere/camera_info", "-o", str(tmp_path / "x.mcap"))
    assert code == 0 and summary["poses"] == 0 and summary["poses_missing_camera_info"] == 6


def test_features_pipeline(log: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "features.mcap"
    code, summary = _run(capsys, str(log), "--pipeline", "features", "--method", "orb", "-o", str(out))
    assert code == 0 and summary["keypoints"] > 0
    topics = _by_topic(out)
    points = topics["/camera/image_raw/compressed/keypoints"]
    assert len(points) == 3 and all(len(p.msg.points) > 0 for p in points)
    assert sum(len(p.msg.points) for p in points) == summary["keypoints"]
    ticks = topics["/camera/image_raw/compressed/keypoint_orientations"]
    assert all(
        len(t.msg.points) == 2 * len(p.msg.points) for t, p in zip(ticks, points, strict=True)
    )  # ORB orients all
    assert main(["perceive", str(log), "--pipeline", "features", "--method", "nope",
                 "-o", str(tmp_path / "n.mcap")]) == 2
    assert "unknown feature detector 'nope'" in capsys.readouterr().err


def test_text_summary(log: Path, tmp_path: Path, capsys) -> None:
    assert main(["perceive", str(log), "--pipeline", "markers", "--dictionary", "DICT_4X4_50",
                 "-o", str(tmp_path / "s.mcap")]) == 0
    text = capsys.readouterr().out
    assert "frames: 3 processed, 1 corrupt messages skipped" in text and "marker ids: {'3': 3, '17': 3}" in text


@pytest.mark.parametrize("extra, message", [
    (["--pipeline", "color"], "needs either --template or --lower and --upper"),
    (["--pipeline", "color", "--lower", "1,2"], "--lower needs three comma-separated finite numbers, got '1,2'"),
    (["--pipeline", "color", "--lower", "15,0.6,0.5", "--upper", "20,1,nan"],
     "trundle perceive: --upper needs three comma-separated finite numbers, got '20,1,nan'"),
    (["--pipeline", "color", "--lower", "1,2,3"], "--lower and --upper go together"),
    (["--pipeline", "markers", "--dictionary", "DICT_99"], "unknown ArUco dictionary"),
    (["--pipeline", "markers", "--marker-size", "-1"], "--marker-size: -1 must be above 0"),
    (["--pipeline", "markers", "--topics", "/camera/camera_info"], "not an image topic"),
    (["--pipeline", "color", "--template", "/no/such.png"], "no such image: /no/such.png"),
])
def test_user_errors_are_one_line(log: Path, tmp_path: Path, capsys, extra: list[str], message: str) -> None:
    assert main(["perceive", str(log), "-o", str(tmp_path / "e.mcap"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_bad_logs_are_user_errors(log: Path, tmp_path: Path, capsys) -> None:
    assert main(["perceive", str(tmp_path / "missing.mcap"), "--pipeline", "markers",
                 "-o", str(tmp_path / "o.mcap")]) == 2
    no_images = tmp_path / "scan.mcap"
    with Logger(no_images, salvage=False) as logger:
        logger.write("/camera/camera_info", m.CameraInfo(T0, "cam", 2, 2, "plumb_bob", np.zeros(5), K), T0)
    assert main(["perceive", str(no_images), "--pipeline", "markers", "-o", str(tmp_path / "o.mcap")]) == 2
    assert main(["perceive", str(log), "--pipeline", "markers", "-o", str(log)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and "no Image or CompressedImage topic" in err[1] and "must not be the input" in err[2]
