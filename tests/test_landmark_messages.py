"""The landmark observation message (trundle_msgs/LandmarkList) in an MCAP decodes with Foxglove's own
ROS 2 decoder (mcap-ros2-support reads the schema text from the file, as the Foxglove app does), and
Foxglove's encoder makes the same bytes from the same values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.writer import Logger

MARKER = m.LandmarkObservation("23", 2.5, 0.3, [[0.04, 0.001], [0.001, 0.0009]], (2.388, 0.739, 0.4),
                               (0.0, 0.0, math.sin(0.6), math.cos(0.6)), 0.0025)
CORNER = m.LandmarkObservation("", 4.0, -1.2, np.diag([0.01, 0.0004]))


def test_foxglove_decodes_landmarks_from_the_log(tmp_path):
    path = tmp_path / "landmarks.mcap"
    with Logger(path, salvage=False) as logger:
        logger.write("/landmarks", m.LandmarkList(1_700_000_000_123_456_789, "base_link", (MARKER, CORNER)),
                     1_700_000_000_200_000_000)
    with open(path, "rb") as f:
        decoded = [(schema.name, channel.topic, msg) for schema, channel, _, msg in
                   make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert [(name, topic) for name, topic, _ in decoded] == [("trundle_msgs/msg/LandmarkList", "/landmarks")]
    msg = decoded[0][2]
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1_700_000_000, 123_456_789,
                                                                                      "base_link")
    marker, corner = msg.landmarks
    assert marker.id == "23" and corner.id == ""
    assert (marker.range, marker.bearing, corner.range, corner.bearing) == (2.5, 0.3, 4.0, -1.2)
    assert list(marker.range_bearing_covariance) == [0.04, 0.001, 0.001, 0.0009]
    pose = marker.tracking_from_landmark_transform
    assert (pose.position.x, pose.position.y, pose.position.z) == (2.388, 0.739, 0.4)
    assert pose.orientation.z == pytest.approx(math.sin(0.6)) and pose.orientation.w == pytest.approx(math.cos(0.6))
    assert marker.yaw_variance == 0.0025 and marker.rotation_weight == pytest.approx(20.0)
    # Cartographer's weight: 1 / the largest standard deviation of the point, here from the range-bearing covariance
    sigma = math.sqrt(np.linalg.eigvalsh(_xy_covariance(MARKER)).max())
    assert marker.translation_weight == pytest.approx(1.0 / sigma)
    # a point feature: the position is the range-bearing point, its orientation unobserved
    where = corner.tracking_from_landmark_transform.position
    assert (where.x, where.y) == pytest.approx((4.0 * math.cos(-1.2), 4.0 * math.sin(-1.2)))
    assert corner.rotation_weight == 0.0 and corner.yaw_variance == 0.0


def test_foxglove_encoder_makes_our_bytes():
    """mcap-ros2-support's encoder, driven by nothing but our schema text and plain values, writes
    exactly the CDR bytes we write."""
    msg = m.LandmarkList(5_000_000_001, "base_link", (MARKER, CORNER))
    ros_type, ours = ros2.encode(msg)
    weights = [(1.0 / math.sqrt(np.linalg.eigvalsh(_xy_covariance(o)).max()), 1.0 / math.sqrt(o.yaw_variance)
                if o.yaw_variance else 0.0) for o in msg.landmarks]
    entries = [
        {
            "id": o.id,
            "tracking_from_landmark_transform": {
                "position": dict(zip("xyz", map(float, o.translation), strict=True)),
                "orientation": dict(zip("xyzw", map(float, o.rotation), strict=True)),
            },
            "translation_weight": w[0],
            "rotation_weight": w[1],
            "range": o.range,
            "bearing": o.bearing,
            "range_bearing_covariance": [float(v) for v in o.covariance.reshape(-1)],
            "yaw_variance": o.yaw_variance,
        }
        for o, w in zip(msg.landmarks, weights, strict=True)
    ]
    encoder = serialize_dynamic(ros_type, ros2.schema_text(ros_type))[ros_type]
    theirs = encoder({"header": {"stamp": {"sec": 5, "nanosec": 1}, "frame_id": "base_link"}, "landmarks": entries})
    assert bytes(theirs) == ours


def _xy_covariance(o: m.LandmarkObservation) -> np.ndarray:
    c, s = math.cos(o.bearing), math.sin(o.bearing)
    jac = np.array([[c, -o.range * s], [s, o.range * c]])
    return jac @ o.covariance @ jac.T


def test_landmark_map_markers_decode_in_foxglove(tmp_path):
    path = tmp_path / "map.mcap"
    cylinder = m.SceneMarker(7, "map", "landmarks", 12, m.SceneMarker.CYLINDER, 1.5, -2.0, 0.25, 0.0,
                             (0.3, 0.3, 0.5), (0.1, 0.6, 1.0, 1.0))
    label = m.SceneMarker(7, "map", "landmark_ids", 12, m.SceneMarker.TEXT_VIEW_FACING, 1.5, -2.0, 0.8, text="12")
    with Logger(path, salvage=False) as logger:
        logger.write("/landmarks/map", m.SceneMarkers((cylinder, label)), 7)
    with open(path, "rb") as f:
        (schema, _, _, msg), = make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
    assert schema.name == "visualization_msgs/msg/MarkerArray"
    first, second = msg.markers
    assert (first.type, first.id, first.ns, first.pose.position.x, first.pose.position.y) == (
        3,
        12,
        "landmarks",
        1.5,
        -2.0,
    )
    assert (second.type, second.text, first.action) == (9, "12", 0)
