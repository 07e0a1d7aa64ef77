"""Little-endian CDR of the messages logged with every scan (sensor_msgs/LaserScan, a laser's timing
diagnostic_msgs/DiagnosticArray) or at the wheels' and CAN bus's rate (can_msgs/Frame, sensor_msgs/JointState,
nav_msgs/Odometry, tf2_msgs/TFMessage, a Pose2D's PoseWithCovarianceStamped), byte for byte what the rosbags
typestore writes, without building rosbags message objects first.
Per message (thread CPU, us): CanFrame 5.1->0.74, JointState 5.8->1.6, Odometry 10.3->1.7, TF 7.8->1.1, Pose2D 6.5->1.2.

At 40 scans a second the generic path (trundle message -> rosbags objects -> size pass ->
serialise pass) cost 0.1-0.3 ms a message on a busy host, more than decoding the scan
(tools/bench/bench_lrf.py); the daemon logs about 750 CAN, wheel, odometry and transform messages a
second on the drivers' threads. ``trundle.logs.ros2.encode`` uses these; tests hold them to rosbags on
arbitrary messages. Layout (OMG CDR as ROS 2 uses it): a 4-byte encapsulation header
``00 01 00 00``, then each field aligned to its size relative to the first byte after it;
strings are a u32 length counting a final NUL, the UTF-8 bytes and that NUL; sequences a u32
count and their elements.
"""

from __future__ import annotations

import struct
from functools import lru_cache

import numpy as np

from trundle.logs import messages as m

ENCAPSULATION = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_SCALARS = struct.Struct("<7f")
# can_msgs/Frame after its frame id: id, is_rtr, is_extended, is_error, dlc, data zero-padded to 8
_CAN = struct.Struct("<I3?B8s")
# a 3x3 over (x, y, yaw) or (vx, vy, wz) inside ROS's row-major 6x6; the other cells 0.0 (zero bytes)
_COV6 = "2d24xd2d24xd144x2d24xd"
# geometry_msgs/PoseWithCovariance of a planar pose: position (x, y, 0), orientation (0, 0, z, w)
_POSE = "2d24x2d" + _COV6
_POSE_COV = struct.Struct("<" + _POSE)
# ... and nav_msgs/Odometry's TwistWithCovariance after it: linear (vx, vy, 0), angular (0, 0, wz)
_ODOMETRY = struct.Struct("<" + _POSE + "2d24xd" + _COV6)
_TRANSFORM = struct.Struct("<7d")


def _string(parts: list[bytes], pos: int, text: str) -> int:
    """Append a CDR string at ``pos`` (padding to 4 first); returns the position after it."""
    data = text.encode()
    pad = -pos % 4
    parts.append(b"\0" * pad + _U32.pack(len(data) + 1) + data + b"\0")
    return pos + pad + 4 + len(data) + 1


@lru_cache(maxsize=1024)
def _strings(texts: tuple[str, ...], offset: int, align: int) -> bytes:
    """CDR strings written one after another from ``offset`` (a multiple of 4; only its value
    modulo ``align`` counts), then zeros to the next multiple of ``align``: the same for every
    message of a stream."""
    parts: list[bytes] = []
    pos = offset
    for text in texts:
        pos = _string(parts, pos, text)
    return b"".join(parts) + b"\0" * (-pos % align)


def _stamp(stamp_ns: int) -> bytes:
    return _STAMP.pack(*divmod(int(stamp_ns), 1_000_000_000))


@lru_cache(maxsize=256)
def _scan_fields(frame_id: str, scalars: bytes) -> bytes:
    """A LaserScan's bytes from its frame id to its range count: the same for every scan of a
    stream (keyed on the packed scalars, which tell -0.0 from 0.0)."""
    parts: list[bytes] = []
    pos = _string(parts, 8, frame_id)  # after the stamp
    return b"".join(parts) + b"\0" * (-pos % 4) + scalars


def laser_scan(msg: m.LaserScan) -> bytes:
    """CDR of sensor_msgs/msg/LaserScan."""
    ranges = msg.ranges.astype("<f4", copy=False)
    intensities = msg.intensities.astype("<f4", copy=False)
    head = _scan_fields(msg.frame_id, _SCALARS.pack(msg.angle_min, msg.angle_max, msg.angle_increment,
                                                    msg.time_increment, msg.scan_time, msg.range_min, msg.range_max))
    return b"".join((ENCAPSULATION, _STAMP.pack(*divmod(int(msg.stamp_ns), 1_000_000_000)), head,
                     _U32.pack(ranges.size), ranges.tobytes(), _U32.pack(intensities.size), intensities.tobytes()))


def diagnostic_array(msg: m.DiagnosticArray) -> bytes:
    """CDR of diagnostic_msgs/msg/DiagnosticArray (header frame id empty, as ``ros2`` maps it)."""
    parts = [ENCAPSULATION, _STAMP.pack(*divmod(int(msg.stamp_ns), 1_000_000_000)), b"\x01\0\0\0\0\0\0\0",
             _U32.pack(len(msg.status))]
    pos = 16  # after the stamp, the empty frame id and the status count
    for status in msg.status:
        parts.append(bytes((status.level & 0xFF,)))
        pos = _string(parts, pos + 1, status.name)
        pos = _string(parts, pos, status.message)
        pos = _string(parts, pos, status.hardware_id)
        pad = -pos % 4
        parts.append(b"\0" * pad + _U32.pack(len(status.values)))
        pos += pad + 4
        for key, value in status.values:
            pos = _string(parts, _string(parts, pos, key), value)
    return b"".join(parts)


def can_frame(msg: m.CanFrame) -> bytes:
    """CDR of can_msgs/msg/Frame: data zero-padded or cut to 8 bytes, dlc its length up to 8."""
    return b"".join((ENCAPSULATION, _stamp(msg.stamp_ns), _strings((msg.frame_id,), 8, 4),
                     _CAN.pack(msg.id, msg.is_rtr, msg.is_extended, msg.is_error, min(len(msg.data), 8), msg.data)))


def odometry(msg: m.Odometry) -> bytes:
    """CDR of nav_msgs/msg/Odometry (quaternion from yaw and 6x6 covariances as ``ros2`` maps them)."""
    half = msg.theta / 2.0  # numpy's sin and cos, as ros2._quaternion: equal bits on any numpy build
    return b"".join((ENCAPSULATION, _stamp(msg.stamp_ns), _strings((msg.frame_id, msg.child_frame_id), 8, 8),
                     _ODOMETRY.pack(msg.x, msg.y, np.sin(half), np.cos(half), *msg.pose_covariance.ravel().tolist(),
                                    msg.vx, msg.vy, msg.wz, *msg.twist_covariance.ravel().tolist())))


def pose2d(msg: m.Pose2D) -> bytes:
    """CDR of geometry_msgs/msg/PoseWithCovarianceStamped (as ``ros2`` maps a Pose2D)."""
    half = msg.theta / 2.0
    return b"".join((ENCAPSULATION, _stamp(msg.stamp_ns), _strings((msg.frame_id,), 8, 8),
                     _POSE_COV.pack(msg.x, msg.y, np.sin(half), np.cos(half), *msg.covariance.ravel().tolist())))


def tf_message(msg: m.TFMessage) -> bytes:
    """CDR of tf2_msgs/msg/TFMessage."""
    parts = [ENCAPSULATION, _U32.pack(len(msg.transforms))]
    pos = 4
    for t in msg.transforms:  # each starts 4-aligned and ends 8-aligned
        head = _strings((t.frame_id, t.child_frame_id), pos % 8, 8)  # they start at pos + 8
        parts += (_stamp(t.stamp_ns), head, _TRANSFORM.pack(*t.translation.tolist(), *t.rotation.tolist()))
        pos += 8 + len(head) + 56
    return b"".join(parts)


@lru_cache(maxsize=256)
def _joint_names(frame_id: str, names: tuple[str, ...]) -> bytes:
    """A JointState's bytes from its frame id to its position count: the same for every message
    of a stream."""
    return _strings((frame_id,), 8, 4) + _U32.pack(len(names)) + _strings(names, 0, 4)


def joint_state(msg: m.JointState) -> bytes:
    """CDR of sensor_msgs/msg/JointState."""
    head = _joint_names(msg.frame_id, msg.name)
    parts = [ENCAPSULATION, _stamp(msg.stamp_ns), head]
    pos = 8 + len(head)
    for values in (msg.position, msg.velocity, msg.effort):
        data = values.astype("<f8", copy=False).tobytes()
        pad = -(pos + 4) % 8 if data else 0  # a sequence of float64 aligns to 8 only when not empty
        parts.append(_U32.pack(len(values)) + b"\0" * pad + data)
        pos += 4 + pad + len(data)
    return b"".join(parts)
