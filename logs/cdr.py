"""Little-endian CDR of the messages a laser logs with every scan (sensor_msgs/LaserScan and the
diagnostic_msgs/DiagnosticArray of its timing topic), byte for byte what the rosbags typestore
writes, without building rosbags message objects first.

At 40 scans a second the generic path (trundle message -> rosbags objects -> size pass ->
serialise pass) cost 0.1-0.3 ms a message on a busy host, more than decoding the scan
(tools/bench/bench_lrf.py). ``trundle.logs.ros2.encode`` uses these two; tests hold them to
rosbags on arbitrary messages. Layout (OMG CDR as ROS 2 uses it): a 4-byte encapsulation header
``00 01 00 00``, then each field aligned to its size relative to the first byte after it;
strings are a u32 length counting a final NUL, the UTF-8 bytes and that NUL; sequences a u32
count and their elements.
"""

from __future__ import annotations

import struct
from functools import lru_cache

from trundle.logs import messages as m

ENCAPSULATION = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_SCALARS = struct.Struct("<7f")


def _string(parts: list[bytes], pos: int, text: str) -> int:
    """Append a CDR string at ``pos`` (padding to 4 first); returns the position after it."""
    data = text.encode()
    pad = -pos % 4
    parts.append(b"\0" * pad + _U32.pack(len(data) + 1) + data + b"\0")
    return pos + pad + 4 + len(data) + 1


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
