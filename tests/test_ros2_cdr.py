"""The direct CDR encoders of the per-scan messages against the rosbags typestore, byte for byte."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs import cdr, ros2
from trundle.logs import messages as m

FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)
TEXT = st.text(max_size=12)  # any length: the padding after each string depends on it
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


def test_encode_uses_them():
    scan = m.LaserScan(1_500_000_000_123, "laser", -1.0, 1.0, 0.5, 0.0, 0.1, 0.1, 30.0, np.ones(5), np.zeros(0))
    assert ros2.encode(scan) == ("sensor_msgs/msg/LaserScan", cdr.laser_scan(scan))
    # stamp 1500 s + 123 ns, frame "laser" (length 6 with its NUL, padded to 8), seven scalars, 5 ranges, 0 intensities
    raw = cdr.laser_scan(scan)
    assert raw[:4] == b"\x00\x01\x00\x00" and raw[4:12] == bytes.fromhex("dc050000 7b000000")
    assert raw[12:24] == b"\x06\x00\x00\x00laser\x00\x00\x00" and len(raw) == 24 + 28 + 4 + 20 + 4
