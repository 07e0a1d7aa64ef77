"""The direct CDR encoders of the per-scan and high-rate messages against the rosbags typestore, byte for byte."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs import cdr, ros2
from trundle.logs import messages as m

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)
TEXT = st.text(max_size=12)  # any length: the padding after each string depends on it
DOUBLES = st.floats(allow_nan=True, allow_infinity=True)
STAMPS = st.integers(-(2**31) * 10**9, 2**31 * 10**9 - 1)


def typestore_bytes(msg: m.Message) -> bytes:
    mp = ros2._BY_PYTHON[type(msg)]
    return bytes(ros2.TYPESTORE.serialize_cdr(mp.to_ros(msg), mp.ros_type))


@settings(max_examples=300, deadline=None)
@given(STAMPS, TEXT, st.lists(FLOATS, min_size=7, max_size=7), st.lists(FLOATS, max_size=40),
       st.lists(FLOATS, max_size=40))
def test_laser_scans_encode_as_the_typestore_does(stamp, frame, scalars, ranges, intensities):
    scan = m.LaserScan(stamp, frame, *scalars, np.float32(ranges), np.float32(intensities))
    raw = cdr.laser_scan(scan)
    assert raw == typestore_bytes(scan)
    assert cdr.laser_scan(ros2.decode("sensor_msgs/msg/LaserScan", raw)) == raw  # NaN scalars: compare bytes


@settings(max_examples=300, deadline=None)
@given(STAMPS, st.lists(st.tuples(st.integers(0, 3), TEXT, TEXT, TEXT, st.lists(st.tuples(TEXT, TEXT), max_size=6)),
                        max_size=4))
def test_diagnostic_arrays_encode_as_the_typestore_does(stamp, statuses):
    msg = m.DiagnosticArray(stamp, tuple(m.DiagnosticStatus(level, name, text, hw, tuple(values))
                                         for level, name, text, hw, values in statuses))
    raw = cdr.diagnostic_array(msg)
    assert raw == typestore_bytes(msg)
    assert ros2.decode("diagnostic_msgs/msg/DiagnosticArray", raw) == msg


@settings(max_examples=300, deadline=None)
@given(STAMPS, TEXT, st.integers(0, 2**32 - 1), st.binary(max_size=12), st.booleans(), st.booleans(), st.booleans())
def test_can_frames_encode_as_the_typestore_does(stamp, frame, can_id, data, extended, rtr, error):
    msg = m.CanFrame(stamp, frame, can_id, data, extended, rtr, error)
    raw = cdr.can_frame(msg)
    assert raw == typestore_bytes(msg)
    assert ros2.decode("can_msgs/msg/Frame", raw) == replace(msg, data=data[:8])  # the typestore's 8 bytes


def test_can_frame_bytes():
    msg = m.CanFrame(-1, "can0", 0x181, b"\x01\x02\x03", is_extended=True)
    assert cdr.can_frame(msg) == bytes.fromhex(
        "00010000"  # encapsulation: CDR little-endian
        "ffffffff ffc99a3b"  # stamp -1 ns: sec -1, nanosec 999,999,999
        "05000000 63616e30 00 000000"  # "can0" with its NUL (5 bytes), then 3 bytes to align the id to 4
        "81010000"  # id
        "00 01 00 03"  # is_rtr, is_extended, is_error, dlc
        "0102030000000000")  # data zero-padded to 8


COV3 = st.lists(DOUBLES, min_size=9, max_size=9).map(lambda v: np.array(v).reshape(3, 3))
NO_TRIG_WARNING = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # sin and cos of inf


@NO_TRIG_WARNING
@settings(max_examples=300, deadline=None)
@given(STAMPS, TEXT, TEXT, st.lists(DOUBLES, min_size=6, max_size=6), COV3, COV3)
def test_odometry_encodes_as_the_typestore_does(stamp, frame, child, values, pose_cov, twist_cov):
    msg = m.Odometry(stamp, frame, child, *values, pose_cov, twist_cov)
    raw = cdr.odometry(msg)
    assert raw == typestore_bytes(msg)
    # all but the yaw, which comes back from the quaternion: compare bytes (NaN fields)
    assert cdr.odometry(replace(ros2.decode("nav_msgs/msg/Odometry", raw), theta=msg.theta)) == raw


@NO_TRIG_WARNING
@settings(max_examples=300, deadline=None)
@given(STAMPS, TEXT, st.lists(DOUBLES, min_size=3, max_size=3), COV3)
def test_poses_encode_as_the_typestore_does(stamp, frame, values, cov):
    msg = m.Pose2D(stamp, frame, *values, cov)
    raw = cdr.pose2d(msg)
    assert raw == typestore_bytes(msg)
    decoded = ros2.decode("geometry_msgs/msg/PoseWithCovarianceStamped", raw)
    assert cdr.pose2d(replace(decoded, theta=msg.theta)) == raw


TRANSFORMS = st.builds(m.TransformStamped, STAMPS, TEXT, TEXT, st.lists(DOUBLES, min_size=3, max_size=3),
                       st.lists(DOUBLES, min_size=4, max_size=4))


@settings(max_examples=300, deadline=None)
@given(st.lists(TRANSFORMS, max_size=5))
def test_tf_messages_encode_as_the_typestore_does(transforms):
    msg = m.TFMessage(tuple(transforms))
    raw = cdr.tf_message(msg)
    assert raw == typestore_bytes(msg)
    assert ros2.decode("tf2_msgs/msg/TFMessage", raw) == msg


@settings(max_examples=300, deadline=None)
@given(STAMPS, TEXT, st.lists(TEXT, max_size=4), st.lists(DOUBLES, max_size=5), st.lists(DOUBLES, max_size=5),
       st.lists(DOUBLES, max_size=5))
def test_joint_states_encode_as_the_typestore_does(stamp, frame, names, position, velocity, effort):
    msg = m.JointState(stamp, frame, names, position, velocity, effort)
    raw = cdr.joint_state(msg)
    assert raw == typestore_bytes(msg)
    assert ros2.decode("sensor_msgs/msg/JointState", raw) == msg


def test_encode_uses_them():
    scan = m.LaserScan(1_500_000_000_123, "laser", -1.0, 1.0, 0.5, 0.0, 0.1, 0.1, 30.0, np.ones(5), np.zeros(0))
    assert ros2.encode(scan) == ("sensor_msgs/msg/LaserScan", cdr.laser_scan(scan))
    # stamp 1500 s + 123 ns, frame "laser" (length 6 with its NUL, padded to 8), seven scalars, 5 ranges, 0 intensities
    raw = cdr.laser_scan(scan)
    assert raw[:4] == b"\x00\x01\x00\x00" and raw[4:12] == bytes.fromhex("dc050000 7b000000")
    assert raw[12:24] == b"\x06\x00\x00\x00laser\x00\x00\x00" and len(raw) == 24 + 28 + 4 + 20 + 4
    cov = np.diag([0.1, 0.2, 0.3])
    for msg, encoder in (
            (m.CanFrame(1, "can0", 0x181, b"\x01\x02"), cdr.can_frame),
            (m.Odometry(1, "odom", "base_link", 1.0, 2.0, 0.5, 0.1, 0.0, 0.2, cov, cov), cdr.odometry),
            (m.TFMessage((m.TransformStamped.planar(1, "odom", "base_link", 1.0, 2.0, 0.5),)), cdr.tf_message),
            (m.JointState(1, "base_link", ("left", "right"), np.ones(2)), cdr.joint_state),
            (m.Pose2D(1, "map", 1.0, 2.0, 0.5, cov), cdr.pose2d)):
        assert ros2.encode(msg) == (ros2.ros_type(type(msg)), encoder(msg))
