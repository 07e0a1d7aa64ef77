"""Slamtec RPLIDAR serial protocol codec: requests, response descriptors, device info, health,
the configuration queries that enumerate scan modes, and legacy 5-byte scan nodes.

Pure functions over bytes and numpy arrays (no I/O), shared by the driver and the emulator.
Little-endian throughout. The capsule answers of EXPRESS_SCAN (express, ultra, dense,
ultra-dense, HQ) are in ``rplidar_capsules``. Scan data never raise: ``NodeDecoder`` drops bytes
until the check bits hold again and counts what it dropped, where the SDK's
``handler_normalnode.cpp`` resynchronises and the Python libraries raise.

Sources (lrf-protocols.md section 2): Slamtec's ``sl_lidar_cmd.h`` and ``sl_lidar_protocol.h``
(Slamtec/rplidar_ros @ 2f10ad5b, ``sdk/include``), ``sl_lidar_driver.cpp`` (Slamtec/rplidar_sdk,
SDK 2.1) and the RPLIDAR interface protocol document (A3M1 edition, 2019, GET_LIDAR_CONF pages).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from trundle.logs.errors import ProtocolError

SYNC, SYNC2 = 0xA5, 0x5A
STOP, RESET, SCAN, FORCE_SCAN, EXPRESS_SCAN = 0x25, 0x40, 0x20, 0x21, 0x82
GET_INFO, GET_HEALTH, GET_SAMPLERATE, GET_LIDAR_CONF = 0x50, 0x52, 0x59, 0x84
SET_MOTOR_PWM, GET_ACC_BOARD_FLAG, HQ_MOTOR_SPEED_CTRL = 0xF0, 0xFF, 0xA8
ANS_INFO, ANS_HEALTH, ANS_MEASUREMENT, ANS_CAPSULED = 0x04, 0x06, 0x81, 0x82
ANS_HQ, ANS_ULTRA, ANS_DENSE, ANS_ULTRA_DENSE = 0x83, 0x84, 0x85, 0x86
ANS_SAMPLERATE, ANS_CONF, ANS_ACC_BOARD_FLAG = 0x15, 0x20, 0xFF
SINGLE, MULTIPLE = 0, 1
DESCRIPTOR_SIZE, NODE_SIZE = 7, 5
FULL_CIRCLE_Q6 = 360 << 6
HEALTH_GOOD, HEALTH_WARNING, HEALTH_ERROR = 0, 1, 2

# GET_LIDAR_CONF entries (sl_lidar_cmd.h SL_LIDAR_CONF_*): the mode count and the typical mode
# take no payload; the others take the mode id as a u16 after the type.
CONF_DESIRED_ROT_FREQ = 0x01  # u16 rpm, u16 PWM reference
CONF_SCAN_MODE_COUNT = 0x70  # u16
CONF_SCAN_MODE_US_PER_SAMPLE = 0x71  # u32, Q8 microseconds
CONF_SCAN_MODE_MAX_DISTANCE = 0x74  # u32, Q8 metres
CONF_SCAN_MODE_ANS_TYPE = 0x75  # u8, the answer type EXPRESS_SCAN streams in that mode
CONF_SCAN_MODE_TYPICAL = 0x7C  # u16, the mode Slamtec recommends for the model
CONF_SCAN_MODE_NAME = 0x7F  # NUL-terminated ASCII
MODE_ENTRIES = (CONF_SCAN_MODE_US_PER_SAMPLE, CONF_SCAN_MODE_MAX_DISTANCE, CONF_SCAN_MODE_ANS_TYPE,
                CONF_SCAN_MODE_NAME)


class RplidarError(ProtocolError):
    """A response that does not fit the protocol (a device fault: the driver reconnects)."""


def xor(data: bytes) -> int:
    """XOR of all bytes (the request checksum and the capsule checksum)."""
    return int(np.bitwise_xor.reduce(np.frombuffer(data, np.uint8))) if data else 0


def request(command: int, payload: bytes | None = None) -> bytes:
    """A request packet: ``A5 cmd`` and, for commands with bit 7 set, ``size payload checksum``."""
    if not 0 <= command <= 0xFF:
        raise ValueError(f"command byte out of range: {command}")
    if payload is None and command & 0x80:
        payload = b""
    if payload is None:
        return bytes((SYNC, command))
    if len(payload) > 0xFF:
        raise ValueError("request payload longer than 255 bytes")
    head = bytes((SYNC, command, len(payload))) + payload
    return head + bytes((xor(head),))


@dataclass(frozen=True)
class Request:
    """A parsed request (the emulator's side of ``request``)."""

    command: int
    payload: bytes = b""


class RequestParser:
    """Splits the host's byte stream into requests; bytes that are not a request are counted."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_bytes = 0
        self.bad_checksums = 0

    def feed(self, data: bytes) -> list[Request]:
        self._buf += data
        out: list[Request] = []
        while True:
            start = self._buf.find(bytes((SYNC,)))
            if start < 0:
                self.bad_bytes += len(self._buf)
                self._buf.clear()
                break
            if start:
                self.bad_bytes += start
                del self._buf[:start]
            if len(self._buf) < 2:
                break
            command = self._buf[1]
            if not command & 0x80:
                out.append(Request(command))
                del self._buf[:2]
                continue
            if len(self._buf) < 3 or len(self._buf) < 4 + self._buf[2]:
                break
            size = self._buf[2]
            packet = bytes(self._buf[:4 + size])
            if xor(packet[:-1]) != packet[-1]:
                self.bad_checksums += 1
                del self._buf[:1]
                continue
            out.append(Request(command, packet[3:-1]))
            del self._buf[:4 + size]
        return out


@dataclass(frozen=True)
class Descriptor:
    """Response descriptor: payload ``length`` in bytes, send ``mode`` (0 single, 1 multiple), ``type``."""

    length: int
    mode: int
    type: int

    def encode(self) -> bytes:
        return bytes((SYNC, SYNC2)) + struct.pack("<IB", (self.length & 0x3FFFFFFF) | (self.mode << 30), self.type)

    @classmethod
    def parse(cls, data: bytes) -> Descriptor:
        if len(data) != DESCRIPTOR_SIZE or data[0] != SYNC or data[1] != SYNC2:
            raise RplidarError(f"not a response descriptor: {data.hex(' ')}")
        word, kind = struct.unpack("<IB", data[2:])
        return cls(word & 0x3FFFFFFF, word >> 30, kind)


INFO_DESCRIPTOR = Descriptor(20, SINGLE, ANS_INFO)
HEALTH_DESCRIPTOR = Descriptor(3, SINGLE, ANS_HEALTH)
SAMPLERATE_DESCRIPTOR = Descriptor(4, SINGLE, ANS_SAMPLERATE)
ACC_BOARD_DESCRIPTOR = Descriptor(4, SINGLE, ANS_ACC_BOARD_FLAG)
SCAN_DESCRIPTOR = Descriptor(5, MULTIPLE, ANS_MEASUREMENT)


def conf_request(entry: int, mode: int | None = None) -> bytes:
    """GET_LIDAR_CONF payload: u32 entry type, then the u16 mode id for per-mode entries (SDK 2.1)."""
    return struct.pack("<I", entry) + (b"" if mode is None else struct.pack("<H", mode))


def conf_answer(entry: int, value: bytes) -> bytes:
    """The GET_LIDAR_CONF answer payload: the entry type echoed, then its value."""
    return struct.pack("<I", entry) + value


def parse_conf(entry: int, payload: bytes) -> bytes:
    """The value of a GET_LIDAR_CONF answer; RplidarError unless it echoes ``entry``."""
    if len(payload) < 4 or struct.unpack("<I", payload[:4])[0] != entry:
        raise RplidarError(f"configuration answer for entry {entry:#x} does not echo it: {payload[:8].hex(' ')}")
    return payload[4:]


@dataclass(frozen=True)
class ScanMode:
    """One scan mode as GET_LIDAR_CONF describes it: ``id`` (the EXPRESS_SCAN working mode),
    ``name``, ``us_per_sample`` (microseconds), ``max_distance`` (m), ``answer_type``."""

    id: int
    name: str
    us_per_sample: float
    max_distance: float
    answer_type: int

    def conf_values(self) -> dict[int, bytes]:
        """The value of every per-mode entry (the emulator's answers)."""
        return {CONF_SCAN_MODE_US_PER_SAMPLE: struct.pack("<I", round(self.us_per_sample * 256)),
                CONF_SCAN_MODE_MAX_DISTANCE: struct.pack("<I", round(self.max_distance * 256)),
                CONF_SCAN_MODE_ANS_TYPE: bytes((self.answer_type,)),
                CONF_SCAN_MODE_NAME: self.name.encode("ascii") + b"\0"}

    @classmethod
    def from_conf(cls, mode: int, values: dict[int, bytes]) -> ScanMode:
        """A mode from the values of its four entries (RplidarError when one is malformed)."""
        us, distance, kind, name = (values.get(e, b"") for e in MODE_ENTRIES)
        if len(us) < 4 or len(distance) < 4 or len(kind) < 1 or not name:
            raise RplidarError(f"incomplete description of scan mode {mode}")
        # Q8 fixed point (protocol: 64000 means 250 us); SDK 2.1 keeps the fraction of the duration
        return cls(mode, name.split(b"\0")[0].decode("ascii", "replace"), struct.unpack("<I", us[:4])[0] / 256,
                   struct.unpack("<I", distance[:4])[0] / 256, kind[0])


@dataclass(frozen=True)
class DeviceInfo:
    """GET_INFO payload: ``model`` id (major series = model >> 4), firmware (major, minor),
    ``hardware`` version and 16-byte ``serial``."""

    model: int
    firmware: tuple[int, int]
    hardware: int
    serial: bytes

    def encode(self) -> bytes:
        return struct.pack("<BBBB16s", self.model, self.firmware[1], self.firmware[0], self.hardware, self.serial)

    @classmethod
    def parse(cls, data: bytes) -> DeviceInfo:
        if len(data) != 20:
            raise RplidarError(f"device info of {len(data)} bytes")
        model, minor, major, hardware, serial = struct.unpack("<BBBB16s", data)
        return cls(model, (major, minor), hardware, serial)

    @property
    def major_model(self) -> int:
        return self.model >> 4

    @property
    def model_name(self) -> str:
        """Slamtec's name for the model id (SDK 2.1 ``GetModelNameStringByModelID``): the major
        number picks the series (1-3 A, 4-5 C, 6-8 S, 9-11 T, 12+ M), the low nibble the variant."""
        major, minor = self.model >> 4, self.model & 0xF
        for first, series in ((12, "M"), (9, "T"), (6, "S"), (4, "C")):
            if major >= first:
                return f"{series}{major - first + 1}M{minor}"
        return f"A{major}M{minor}"

    @property
    def supports_conf(self) -> bool:
        """GET_LIDAR_CONF: firmware 1.24 and later, and every C/S/T/M model whatever its
        firmware number (SDK 2.1 ``checkSupportConfigCommands``: those restart at 1.0x)."""
        return self.firmware >= (1, 24) or self.major_model >= 4

    @property
    def native_baudrate(self) -> int:
        """The SDK's rule for the device's baud rate from model and hardware version."""
        major = self.major_model
        if major in (1, 2, 3):
            return 256000 if self.hardware >= 6 else 115200
        if major == 4:
            return 460800
        if major == 6:
            return 256000
        if major in (7, 8):
            return 460800 if self.model == 0x82 else 1000000
        return 115200


@dataclass(frozen=True)
class Health:
    """GET_HEALTH payload: ``status`` 0 good, 1 warning, 2 error; ``error_code`` u16."""

    status: int
    error_code: int = 0

    def encode(self) -> bytes:
        return struct.pack("<BH", self.status, self.error_code)

    @classmethod
    def parse(cls, data: bytes) -> Health:
        if len(data) != 3:
            raise RplidarError(f"health of {len(data)} bytes")
        return cls(*struct.unpack("<BH", data))


def encode_nodes(start: np.ndarray, quality: np.ndarray, angle_q6: np.ndarray, distance_q2: np.ndarray) -> bytes:
    """Legacy 5-byte scan nodes (start flag, quality 0..63, angle in 1/64 deg, distance in 1/4 mm)."""
    start = np.asarray(start, bool)
    angle = np.asarray(angle_q6, np.int64)
    dist = np.asarray(distance_q2, np.int64)
    out = np.empty((start.size, NODE_SIZE), np.uint8)
    out[:, 0] = (np.asarray(quality, np.int64) << 2) | np.where(start, 1, 2)
    out[:, 1] = ((angle & 0x7F) << 1) | 1
    out[:, 2] = angle >> 7
    out[:, 3] = dist & 0xFF
    out[:, 4] = dist >> 8
    return out.tobytes()


def _check(b0: np.ndarray, b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """Node checks: start bit = not inverse start bit, check bit set, angle below 360 deg."""
    return (((b0 ^ (b0 >> 1)) & 1) == 1) & ((b1 & 1) == 1) & (b2 < (FULL_CIRCLE_Q6 >> 7))


def _node_ok(b: np.ndarray) -> np.ndarray:
    """Checks of a node starting at every offset of ``b`` that has 5 bytes left."""
    return _check(b[:-4], b[1:-3], b[2:-2])


@dataclass
class Nodes:
    """Decoded samples: ``start`` flag (first sample of a revolution), ``quality`` (0..63, the
    legacy scale), ``angle_q6`` (measurement angle, 1/64 deg), ``distance_q2`` (1/4 mm, 0 = no
    measurement), ``broken`` (True where bytes were lost just before this sample) and
    ``encoder_q6``, the angle of the turret when the sample was taken: it rises steadily through
    a revolution and differs from ``angle_q6`` where the format corrects each sample's angle
    (express offsets, the ultra capsules' optical compensation). ``lost`` estimates how many
    samples the lost bytes held."""

    start: np.ndarray
    quality: np.ndarray
    angle_q6: np.ndarray
    distance_q2: np.ndarray
    broken: np.ndarray
    encoder_q6: np.ndarray = None  # type: ignore[assignment]  # None stands for angle_q6 (see __post_init__)
    lost: int = 0

    def __post_init__(self) -> None:
        if self.encoder_q6 is None:
            self.encoder_q6 = self.angle_q6

    def __len__(self) -> int:
        return int(self.start.size)

    @classmethod
    def empty(cls) -> Nodes:
        z = np.zeros(0, np.int64)
        return cls(z.astype(bool), z, z, z, z.astype(bool))

    @classmethod
    def concat(cls, parts: list[Nodes], lost: int = 0) -> Nodes:
        if not parts:
            empty = cls.empty()
            empty.lost = lost
            return empty
        if len(parts) == 1 and not lost:
            return parts[0]
        start, quality, angle, distance, broken, encoder = (
            np.concatenate([getattr(p, f) for p in parts])
            for f in ("start", "quality", "angle_q6", "distance_q2", "broken", "encoder_q6"))
        return cls(start, quality, angle, distance, broken, encoder, lost + sum(p.lost for p in parts))

    def slice(self, a: int, b: int) -> Nodes:
        """Samples ``a`` to ``b - 1`` (no lost count)."""
        return Nodes(self.start[a:b], self.quality[a:b], self.angle_q6[a:b], self.distance_q2[a:b],
                     self.broken[a:b], self.encoder_q6[a:b])


def decode_nodes(data: np.ndarray) -> Nodes:
    """Decode aligned 5-byte nodes (rows of ``data``, shape (n, 5) uint8) without checking them."""
    d = data.astype(np.int64)
    return Nodes((d[:, 0] & 1) == 1, d[:, 0] >> 2, (d[:, 1] >> 1) | (d[:, 2] << 7), d[:, 3] | (d[:, 4] << 8),
                 np.zeros(len(d), bool))


@dataclass
class Resynchronising:
    """State shared by the frame decoders: buffered bytes, whether the next byte starts a frame
    (``_aligned``), whether bytes were lost since the last good frame (``_broken``), counters."""

    resyncs: int = 0
    skipped_bytes: int = 0
    _buf: bytearray = field(default_factory=bytearray)
    _aligned: bool = True
    _broken: bool = False

    def reset(self) -> None:
        """Start of a new response: the next byte is a frame boundary."""
        self._buf.clear()
        self._aligned, self._broken = True, False

    def _lose_alignment(self) -> int:
        """A frame failed its checks: count it, skip its first byte (returned: bytes to advance)
        and look for the next offset where frames check out again."""
        self.resyncs += 1
        self.skipped_bytes += 1
        self._aligned, self._broken = False, True
        return 1


@dataclass
class NodeDecoder(Resynchronising):
    """Stream of legacy scan nodes -> ``Nodes``, resynchronising on bad check bits.

    After a bad node it skips bytes until ``confirm`` nodes in a row pass their checks (the
    check bits alone pass one random node in four). Counters: ``bad_nodes`` check failures,
    ``resyncs`` realignments, ``skipped_bytes``.
    """

    confirm: int = 8
    bad_nodes: int = 0

    def feed(self, data: bytes) -> Nodes:
        self._buf += data
        a = np.frombuffer(bytes(self._buf), np.uint8)
        parts: list[Nodes] = []
        skipped = self.skipped_bytes
        p = 0
        while len(a) - p >= NODE_SIZE:
            if not self._aligned:
                span = NODE_SIZE * self.confirm
                if len(a) - p < span:
                    break
                ok = _node_ok(a[p:])
                run = ok[: len(ok) - NODE_SIZE * (self.confirm - 1)].copy()
                for k in range(1, self.confirm):
                    run &= ok[NODE_SIZE * k: NODE_SIZE * k + run.size]
                hits = np.flatnonzero(run)
                if not hits.size:
                    skip = run.size
                    self.skipped_bytes += skip
                    p += skip
                    continue
                self.skipped_bytes += int(hits[0])
                p += int(hits[0])
                self._aligned = True
            k = (len(a) - p) // NODE_SIZE
            rows = a[p:p + k * NODE_SIZE].reshape(k, NODE_SIZE)
            ok = _check(rows[:, 0], rows[:, 1], rows[:, 2])
            bad = np.flatnonzero(~ok)
            good = int(bad[0]) if bad.size else k
            if good:
                nodes = decode_nodes(rows[:good])
                nodes.broken[0] = self._broken
                self._broken = False
                parts.append(nodes)
            p += good * NODE_SIZE
            if bad.size:
                self.bad_nodes += 1
                p += self._lose_alignment()
        del self._buf[:p]
        return Nodes.concat(parts, round((self.skipped_bytes - skipped) / NODE_SIZE))
