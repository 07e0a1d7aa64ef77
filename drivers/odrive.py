"""ODrive "CAN Simple" codec: pure functions between CAN frames and ODrive messages.

Arbitration id = ``node_id << 5 | cmd_id`` (node 0..63, command 0..31), little-endian payloads,
requests are RTR frames answered with the same id. Two firmware lines are supported because the
heartbeat layout changed between them: ``"0.5"`` (ODrive v3.x, firmware 0.5.x) and ``"0.6"``
(ODrive Pro / S1). Firmware 0.6 answers an RTR Get_Version (0x000) with its hardware and firmware
version; 0.5 has no such message (0x000 is reserved for CANopen NMT there), which is how the
line is told apart. Decoders raise ``ValueError`` on frames too short for their layout.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

GET_VERSION = 0x000  # 0.6 only
HEARTBEAT = 0x001
ESTOP = 0x002
GET_ERROR = 0x003  # 0.5: Get_Motor_Error (u64); 0.6: Get_Error (u32 active, u32 disarm reason)
SET_AXIS_STATE = 0x007
GET_ENCODER_ESTIMATES = 0x009
GET_ENCODER_COUNT = 0x00A
SET_INPUT_VEL = 0x00D
REBOOT = 0x016
CLEAR_ERRORS = 0x018

AXIS_STATE_IDLE = 1
AXIS_STATE_CLOSED_LOOP_CONTROL = 8

FIRMWARES = ("0.5", "0.6")

_HEARTBEAT = struct.Struct("<IBBBB")
_TWO_F32 = struct.Struct("<ff")
_TWO_I32 = struct.Struct("<ii")


def arbitration_id(node_id: int, cmd_id: int) -> int:
    """The 11-bit id of command ``cmd_id`` for axis ``node_id``."""
    if not 0 <= node_id <= 0x3F or not 0 <= cmd_id <= 0x1F:
        raise ValueError(f"ODrive node id 0..63 and command 0..31, got {node_id}, {cmd_id}")
    return node_id << 5 | cmd_id


def split_id(can_id: int) -> tuple[int, int]:
    """``(node_id, cmd_id)`` of an ODrive arbitration id."""
    return (can_id >> 5) & 0x3F, can_id & 0x1F


@dataclass(frozen=True)
class Heartbeat:
    """Axis status sent cyclically (0x001): error bits, axis state and flags.

    ``flags`` holds bytes 5..7 as the firmware line defines them: 0.5 = motor error flag,
    encoder error flag, controller error flag (bit 0) | trajectory done (bit 7); 0.6 =
    procedure result, trajectory done flag, 0.
    """

    axis_error: int
    axis_state: int
    flags: tuple[int, int, int] = (0, 0, 0)

    @property
    def healthy(self) -> bool:
        """No axis error bit and (0.5) no motor/encoder/controller error flag."""
        return self.axis_error == 0


def decode_heartbeat(data: bytes | bytearray, firmware: str = "0.5") -> Heartbeat:
    """Decode a heartbeat payload (5..8 bytes; missing flag bytes read as 0)."""
    if firmware not in FIRMWARES:
        raise ValueError(f"unknown ODrive firmware line {firmware!r} (use one of {', '.join(FIRMWARES)})")
    if len(data) < 5:
        raise ValueError(f"ODrive heartbeat needs at least 5 bytes, got {len(data)}")
    error, state, f0, f1, f2 = _HEARTBEAT.unpack(bytes(data[:8]).ljust(8, b"\0"))
    return Heartbeat(error, state, (f0, f1, f2))


def encode_heartbeat(heartbeat: Heartbeat) -> bytes:
    return _HEARTBEAT.pack(heartbeat.axis_error, heartbeat.axis_state, *heartbeat.flags)


@dataclass(frozen=True)
class Version:
    """Get_Version (0x000, firmware 0.6): CAN Simple protocol version, hardware (major, minor,
    variant) and firmware (major, minor, revision; ``unreleased`` for a development build)."""

    protocol: int
    hardware: tuple[int, int, int]
    firmware: tuple[int, int, int]
    unreleased: bool = False

    @property
    def firmware_text(self) -> str:
        return ".".join(map(str, self.firmware)) + ("-dev" if self.unreleased else "")

    @property
    def line(self) -> str:
        """The heartbeat layout this firmware uses: ``"0.5"`` for 0.5.x and older, else ``"0.6"``."""
        return "0.5" if self.firmware[:2] <= (0, 5) else "0.6"


def decode_version(data: bytes | bytearray) -> Version:
    """Get_Version payload: u8 protocol, hw major, minor, variant, fw major, minor, revision, unreleased."""
    if len(data) < 8:
        raise ValueError(f"ODrive Get_Version needs 8 bytes, got {len(data)}")
    b = bytes(data[:8])
    return Version(b[0], (b[1], b[2], b[3]), (b[4], b[5], b[6]), bool(b[7]))


def encode_version(version: Version) -> bytes:
    return bytes((version.protocol, *version.hardware, *version.firmware, int(version.unreleased)))


def decode_encoder_estimates(data: bytes | bytearray) -> tuple[float, float]:
    """``(position turns, velocity turns/s)`` from Get_Encoder_Estimates (0x009).

    Raises ``ValueError`` for a short frame or a non-finite value (a corrupt frame, never data).
    """
    if len(data) < 8:
        raise ValueError(f"ODrive encoder estimates need 8 bytes, got {len(data)}")
    pos, vel = _TWO_F32.unpack_from(data)
    if not (math.isfinite(pos) and math.isfinite(vel)):
        raise ValueError("ODrive encoder estimates are not finite")
    return pos, vel


def encode_encoder_estimates(pos_turns: float, vel_turns_s: float) -> bytes:
    return _TWO_F32.pack(pos_turns, vel_turns_s)


def decode_encoder_count(data: bytes | bytearray) -> tuple[int, int]:
    """``(shadow count, count in CPR)`` from Get_Encoder_Count (0x00A), signed 32-bit counts."""
    if len(data) < 8:
        raise ValueError(f"ODrive encoder count needs 8 bytes, got {len(data)}")
    return _TWO_I32.unpack_from(data)


def encode_encoder_count(shadow_count: int, count_in_cpr: int) -> bytes:
    return _TWO_I32.pack(shadow_count, count_in_cpr)


def encode_axis_state(state: int) -> bytes:
    """Set_Axis_Requested_State (0x007) payload."""
    return struct.pack("<I", state)


def decode_axis_state(data: bytes | bytearray) -> int:
    if len(data) < 4:
        raise ValueError(f"ODrive axis state request needs 4 bytes, got {len(data)}")
    return struct.unpack_from("<I", data)[0]


def encode_input_vel(vel_turns_s: float, torque_ff: float = 0.0) -> bytes:
    """Set_Input_Vel (0x00D) payload."""
    return _TWO_F32.pack(vel_turns_s, torque_ff)


def decode_input_vel(data: bytes | bytearray) -> tuple[float, float]:
    if len(data) < 8:
        raise ValueError(f"ODrive input velocity needs 8 bytes, got {len(data)}")
    return _TWO_F32.unpack_from(data)
