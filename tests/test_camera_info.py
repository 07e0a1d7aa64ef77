"""CameraInfo from ROS camera_calibration YAML, checked against OpenCV's own YAML reader."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.camera_info import camera_info_from_calibration, load_camera_info, uncalibrated_camera_info
from trundle.logs import ros2
from trundle.logs.errors import UserError

# A real cameracalibrator result, published in the README of a ROS camera driver
# (1440x1440 fisheye "kodak" camera, plumb_bob model).
KODAK = """image_width: 1440
image_height: 1440
camera_name: kodak
camera_matrix:
  rows: 3
  cols: 3
  data: [559.7772332675477, 0, 654.6891822497959, 0, 537.9001480261843, 757.5374958985061, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1710342568253523, 0.01562344385534763, -0.006842079559350427, 0.005880933792022186, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [471.8281555175781, 0, 686.7856496391687, 0, 0, 427.0946044921875, 763.6798197288299, 0, 0, 0, 1, 0]
"""


def opencv_reads(path: Path, key: str) -> np.ndarray:
    """The ``data`` list of ``key`` as OpenCV's FileStorage parses it (it needs a YAML directive)."""
    copy = path.with_name("opencv_" + path.name)
    copy.write_text("%YAML:1.0\n---\n" + path.read_text())
    storage = cv2.FileStorage(str(copy), cv2.FILE_STORAGE_READ)
    node = storage.getNode(key).getNode("data")
    values = np.array([node.at(i).real() for i in range(node.size())])
    storage.release()
    return values


def test_calibration_file_matches_opencv_reading(tmp_path: Path) -> None:
    path = tmp_path / "kodak.yaml"
    path.write_text(KODAK)
    info = load_camera_info(path, "camera_optical", 123)
    assert (info.width, info.height, info.distortion_model, info.frame_id, info.stamp_ns) == (
        1440, 1440, "plumb_bob", "camera_optical", 123)
    np.testing.assert_array_equal(info.k.ravel(), opencv_reads(path, "camera_matrix"))
    np.testing.assert_array_equal(info.d, opencv_reads(path, "distortion_coefficients"))
    np.testing.assert_array_equal(info.r.ravel(), opencv_reads(path, "rectification_matrix"))
    np.testing.assert_array_equal(info.p.ravel(), opencv_reads(path, "projection_matrix"))
    assert info.k[0, 0] == 559.7772332675477 and info.k[1, 2] == 757.5374958985061


def test_camera_info_survives_ros2_encoding(tmp_path: Path) -> None:
    path = tmp_path / "kodak.yaml"
    path.write_text(KODAK)
    info = load_camera_info(path, "camera_optical", 5)
    ros_type, data = ros2.encode(info)
    assert ros_type == "sensor_msgs/msg/CameraInfo"
    assert ros2.decode(ros_type, data) == info


def test_optional_matrices_default_as_ros_does(tmp_path: Path) -> None:
    path = tmp_path / "mono.yaml"
    path.write_text(KODAK.split("rectification_matrix")[0])
    info = load_camera_info(path, "cam")
    np.testing.assert_array_equal(info.r, np.eye(3))
    np.testing.assert_array_equal(info.p, np.hstack([info.k, np.zeros((3, 1))]))


def test_uncalibrated_info_has_size_only() -> None:
    info = uncalibrated_camera_info(1280, 720, "camera_optical")
    assert (info.width, info.height, info.distortion_model, info.d.size) == (1280, 720, "", 0)
    assert not info.k.any() and not info.p.any()


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("image_width: [1, 2", "not valid YAML"),
        ("- 1\n- 2\n", "not a camera_calibration"),
        (KODAK.replace("image_width: 1440", "image_width: wide"), "image_width"),
        (
            KODAK.replace("rows: 3\n  cols: 3\n  data: [559", "rows: 2\n  cols: 3\n  data: [559"),
            "camera_matrix must be 3x3",
        ),
        (KODAK.replace("[559.7772332675477, 0,", "[559.7772332675477,"), "camera_matrix must be 3x3"),
        (KODAK.replace("-0.1710342568253523", "abc"), "distortion_coefficients.data must be a list of numbers"),
        (KODAK.replace("559.7772332675477", ".nan"), "non-finite"),
        (KODAK.replace("camera_matrix:", "camera_matrx:"), "camera_matrix must have rows, cols and data"),
    ],
)
def test_bad_files_are_user_errors(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match=fragment) as error:
        load_camera_info(path, "cam")
    assert "\n" not in str(error.value)


def test_missing_file_is_a_user_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="not found"):
        load_camera_info(tmp_path / "none.yaml", "cam")


scalars = st.none() | st.booleans() | st.integers(-5, 5000) | st.floats() | st.text(max_size=5)
yaml_values = scalars | st.lists(scalars, max_size=13)
keys = st.sampled_from(["image_width", "image_height", "camera_matrix", "distortion_coefficients",
                        "rectification_matrix", "projection_matrix", "distortion_model"])
matrices = st.fixed_dictionaries(
    {"rows": scalars, "cols": scalars, "data": st.lists(scalars | st.floats(-1e3, 1e3), max_size=13)}
)


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(keys, yaml_values | matrices))
def test_any_mapping_gives_camera_info_or_user_error(data: dict) -> None:
    try:
        info = camera_info_from_calibration(data, "cam")
    except UserError as error:
        assert "\n" not in str(error)
    else:
        assert info.k.shape == (3, 3) and info.width > 0
