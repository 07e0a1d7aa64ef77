"""Every message type survives ROS 2 CDR encoding; bytes match the ROS 2 wire format."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from strategies import ALL_MESSAGES

from trundle.logs import messages as m
from trundle.logs import ros2

# Planar yaw travels as a quaternion, so it comes back equal only to rounding.
ANGLE_FIELDS = {"theta", "origin_theta", "yaw"}


def assert_same(a: m.Message, b: m.Message) -> None:
    assert type(a) is type(b)
    if isinstance(a, m.LandmarkList | m.SceneMarkers):
        inner = "landmarks" if isinstance(a, m.LandmarkList) else "markers"
        assert len(getattr(a, inner)) == len(getattr(b, inner))
        for x, y in zip(getattr(a, inner), getattr(b, inner), strict=True):
            assert_same(x, y)
        a, b = (dataclasses.replace(v, **{inner: ()}) for v in (a, b))
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ANGLE_FIELDS:
            assert abs(math.remainder(x - y, 2 * math.pi)) < 1e-9
        elif isinstance(a, m.Path) and f.name == "poses":
            np.testing.assert_array_equal(x[:, :2], y[:, :2])
            np.testing.assert_allclose(np.remainder(x[:, 2] - y[:, 2] + np.pi, 2 * np.pi) - np.pi, 0, atol=1e-9)
        else:
            assert m._eq(x, y), f"{type(a).__name__}.{f.name}: {x!r} != {y!r}"


@pytest.mark.parametrize("name", sorted(ALL_MESSAGES))
def test_round_trip(name: str) -> None:
    @settings(max_examples=60, deadline=None)
    @given(ALL_MESSAGES[name])
    def check(msg: m.Message) -> None:
        ros_type, data = ros2.encode(msg)
        assert data[:4] == b"\x00\x01\x00\x00"  # little-endian CDR encapsulation
        assert_same(ros2.decode(ros_type, data), msg)

    check()


def test_every_type_has_a_strategy() -> None:
    mapped = {mp.python_type.__name__ for mp in ros2.MAPPINGS}
    assert mapped - {"TransformStamped"} <= set(ALL_MESSAGES)


def test_laserscan_wire_size_matches_hand_count() -> None:
    """1081 ranges + 1081 intensities, frame 'laser': 4 encapsulation + 8 stamp + 4+6 string,
    pad 2, 7*4 floats, 4+1081*4 ranges, 4+1081*4 intensities = 8708 bytes."""
    scan = m.LaserScan(0, "laser", 0, 0, 0, 0, 0, 0, 0, np.zeros(1081), np.zeros(1081))
    assert len(ros2.encode(scan)[1]) == 8708


def test_laserscan_bytes_by_hand() -> None:
    """A 2-beam scan laid out by the CDR rules, independent of rosbags."""
    scan = m.LaserScan(1_500_000_002, "l", 0.5, 1.0, 0.25, 0.0, 0.1, 0.02, 30.0, [1.5, float("inf")])
    expected = (b"\x00\x01\x00\x00" + (1).to_bytes(4, "little") + (500_000_002).to_bytes(4, "little")
                + (2).to_bytes(4, "little") + b"l\x00" + b"\x00\x00"
                + np.array([0.5, 1.0, 0.25, 0.0, 0.1, 0.02, 30.0], "<f4").tobytes()
                + (2).to_bytes(4, "little") + np.array([1.5, np.inf], "<f4").tobytes()
                + (0).to_bytes(4, "little"))
    assert ros2.encode(scan) == ("sensor_msgs/msg/LaserScan", expected)


def test_schema_text_has_every_dependency() -> None:
    text = ros2.schema_text("nav_msgs/msg/Odometry")
    separator = "=" * 80
    for dep in ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/PoseWithCovariance",
                "geometry_msgs/TwistWithCovariance", "geometry_msgs/Quaternion"):
        assert f"{separator}\nMSG: {dep}\n" in text
    assert "MSG: std_msgs/Header" in ros2.schema_text("can_msgs/msg/Frame")


def test_unmapped_type_is_refused() -> None:
    with pytest.raises(ros2.UnsupportedType):
        ros2.decode("sensor_msgs/msg/PointCloud2", b"")
