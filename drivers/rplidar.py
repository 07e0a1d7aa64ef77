"""Slamtec RPLIDAR serial protocol codec: requests, response descriptors, scan nodes, express capsules.

Pure functions over bytes and numpy arrays (no I/O), shared by the driver and the emulator.
Little-endian throughout. Scan data never raise: ``NodeDecoder`` and ``CapsuleDecoder`` drop
bytes until the check bits / checksum hold again and count what they dropped, where the SDK's
``handler_normalnode.cpp`` resynchronises and the Python libraries raise.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

SYNC, SYNC2 = 0xA5, 0x5A
STOP, RESET, SCAN, FORCE_SCAN, EXPRESS_SCAN = 0x25, 0x40, 0x20, 0x21, 0x82
GET_INFO, GET_HEALTH, GET_SAMPLERATE, GET_LIDAR_CONF = 0x50, 0x52, 0x59, 0x84
SET_MOTOR_PWM, GET_ACC_BOARD_FLAG, HQ_MOTOR_SPEED_CTRL = 0xF0, 0xFF, 0xA8
ANS_INFO, ANS_HEALTH, ANS_MEASUREMENT, ANS_CAPSULED = 0x04, 0x06, 0x81, 0x82
ANS_SAMPLERATE, ANS_ACC_BOARD_FLAG = 0x15, 0xFF
SINGLE, MULTIPLE = 0, 1
DESCRIPTOR_SIZE, NODE_SIZE, CAPSULE_SIZE, CABINS = 7, 5, 84, 16
FULL_CIRCLE_Q6 = 360 << 6
HEALTH_GOOD, HEALTH_WARNING, HEALTH_ERROR = 0, 1, 2


class RplidarError(ValueError):
    """A response that does not fit the protocol."""


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
EXPRESS_DESCRIPTOR = Descriptor(84, MULTIPLE, ANS_CAPSULED)


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
    """Decoded samples: ``start`` flag, ``quality``, ``angle_q6``, ``distance_q2``, and ``broken``:
    True where bytes were lost just before this sample (the stream is discontinuous there);
    ``lost`` estimates how many samples those lost bytes held."""

    start: np.ndarray
    quality: np.ndarray
    angle_q6: np.ndarray
    distance_q2: np.ndarray
    broken: np.ndarray
    lost: int = 0

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
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                     ("start", "quality", "angle_q6", "distance_q2", "broken")), lost + sum(p.lost for p in parts))


def decode_nodes(data: np.ndarray) -> Nodes:
    """Decode aligned 5-byte nodes (rows of ``data``, shape (n, 5) uint8) without checking them."""
    d = data.astype(np.int64)
    return Nodes((d[:, 0] & 1) == 1, d[:, 0] >> 2, (d[:, 1] >> 1) | (d[:, 2] << 7), d[:, 3] | (d[:, 4] << 8),
                 np.zeros(len(d), bool))


@dataclass
class _Resynchronising:
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


@dataclass
class NodeDecoder(_Resynchronising):
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
                self.resyncs += 1
                self.skipped_bytes += 1
                self._aligned, self._broken = False, True
                p += 1
        del self._buf[:p]
        return Nodes.concat(parts, round((self.skipped_bytes - skipped) / NODE_SIZE))


def encode_capsule(start_angle_q6: int, distance_q2: np.ndarray, dtheta_q3: np.ndarray, new_scan: bool = False) -> bytes:
    """An express capsule (type 0x82): 32 distances (1/4 mm, multiples of 4) with their angle
    offsets (1/8 deg, 0..63), after a start angle in 1/64 deg."""
    dist = np.asarray(distance_q2, np.int64).reshape(CABINS, 2)
    dth = np.asarray(dtheta_q3, np.int64).reshape(CABINS, 2)
    words = (dist & 0xFFFC) | ((dth >> 4) & 3)
    cabins = np.empty((CABINS, 5), np.uint8)
    cabins[:, 0], cabins[:, 1] = words[:, 0] & 0xFF, words[:, 0] >> 8
    cabins[:, 2], cabins[:, 3] = words[:, 1] & 0xFF, words[:, 1] >> 8
    cabins[:, 4] = (dth[:, 0] & 0xF) | ((dth[:, 1] & 0xF) << 4)
    body = struct.pack("<H", (start_angle_q6 & 0x7FFF) | (0x8000 if new_scan else 0)) + cabins.tobytes()
    check = xor(body)
    return bytes((0xA0 | (check & 0xF), 0x50 | (check >> 4))) + body


@dataclass(frozen=True)
class Capsule:
    """A decoded express capsule: ``start_angle_q6``, ``new_scan`` flag, 32 ``distance_q2`` and
    32 ``dtheta_q3``; ``broken`` when bytes were lost just before it."""

    start_angle_q6: int
    new_scan: bool
    distance_q2: np.ndarray
    dtheta_q3: np.ndarray
    broken: bool = False


def _capsule_ok(a: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Whether a valid capsule starts at each of ``offsets`` in ``a`` (all with 84 bytes left)."""
    if not offsets.size:
        return np.zeros(0, bool)
    rows = a[offsets[:, None] + np.arange(CAPSULE_SIZE)]
    check = np.bitwise_xor.reduce(rows[:, 2:], axis=1)
    return (((rows[:, 0] >> 4) == 0xA) & ((rows[:, 1] >> 4) == 0x5)
            & ((rows[:, 0] & 0xF) == (check & 0xF)) & ((rows[:, 1] & 0xF) == (check >> 4)))


def decode_capsule(data: np.ndarray, broken: bool = False) -> Capsule:
    """Decode one 84-byte capsule (checked by the caller)."""
    d = data.astype(np.int64)
    head = int(d[2] | (d[3] << 8))
    cab = d[4:].reshape(CABINS, 5)
    w1, w2 = cab[:, 0] | (cab[:, 1] << 8), cab[:, 2] | (cab[:, 3] << 8)
    dist = np.column_stack((w1 & 0xFFFC, w2 & 0xFFFC)).reshape(-1)
    dth = np.column_stack(((cab[:, 4] & 0xF) | ((w1 & 3) << 4), (cab[:, 4] >> 4) | ((w2 & 3) << 4))).reshape(-1)
    return Capsule(head & 0x7FFF, bool(head & 0x8000), dist, dth, broken)


@dataclass
class CapsuleDecoder(_Resynchronising):
    """Stream of express capsules -> ``Capsule`` list, resynchronising on bad sync nibbles or checksum.

    After a bad capsule it looks for an offset where two capsules in a row check out.
    Counters: ``bad_capsules``, ``resyncs``, ``skipped_bytes``.
    """

    bad_capsules: int = 0

    def feed(self, data: bytes) -> list[Capsule]:
        self._buf += data
        a = np.frombuffer(bytes(self._buf), np.uint8)
        out: list[Capsule] = []
        p = 0
        while len(a) - p >= CAPSULE_SIZE:
            if not self._aligned:
                if len(a) - p < 2 * CAPSULE_SIZE:
                    break
                last = len(a) - 2 * CAPSULE_SIZE
                cand = p + np.flatnonzero(((a[p:last + 1] >> 4) == 0xA) & ((a[p + 1:last + 2] >> 4) == 0x5))
                good = cand[_capsule_ok(a, cand)]
                good = good[_capsule_ok(a, good + CAPSULE_SIZE)]
                if not good.size:
                    self.skipped_bytes += last + 1 - p
                    p = last + 1
                    continue
                self.skipped_bytes += int(good[0]) - p
                p = int(good[0])
                self._aligned = True
            if _capsule_ok(a, np.array([p]))[0]:
                out.append(decode_capsule(a[p:p + CAPSULE_SIZE], self._broken))
                self._broken = False
                p += CAPSULE_SIZE
            else:
                self.bad_capsules += 1
                self.resyncs += 1
                self.skipped_bytes += 1
                self._aligned, self._broken = False, True
                p += 1
        del self._buf[:p]
        return out


def capsule_nodes(capsule: Capsule, next_start_q6: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (1/64 deg, in [0, 360)), distances (1/4 mm) and sync flags of a capsule's 32 samples.

    Sample k lies at ``start + delta * k / 32 - dtheta_k`` with ``delta`` the angle to the next
    capsule's start; computed in the SDK's fixed point (q16 accumulation, >> 10 to q6). The sync
    flag marks the sample after which the raw angle crosses 360 deg (a new revolution).
    """
    start_q8 = capsule.start_angle_q6 << 2
    diff_q8 = (next_start_q6 << 2) - start_q8
    if diff_q8 < 0:
        diff_q8 += 360 << 8
    inc_q16 = diff_q8 << 3
    raw_q16 = (start_q8 << 8) + inc_q16 * np.arange(2 * CABINS, dtype=np.int64)
    angle = (raw_q16 - (capsule.dtheta_q3 << 13)) >> 10
    angle = np.mod(angle, FULL_CIRCLE_Q6)
    sync = ((raw_q16 + inc_q16) % (360 << 16)) < inc_q16
    return angle, capsule.distance_q2.copy(), sync


@dataclass
class ExpressNodeDecoder:
    """Stream of express capsules -> ``Nodes`` (the same output as ``NodeDecoder``).

    A capsule's samples need the next capsule's start angle, and an XOR checksum cannot see
    an inserted or lost byte that happens to equal the one it displaces, so the samples of
    capsule i are only emitted once capsules i+1 and i+2 have followed it without a break.
    ``start`` marks the first sample of a revolution (the angle falls back by more than half a
    turn); quality is not sent in this mode and is reported as 0.
    """

    capsules: CapsuleDecoder = field(default_factory=CapsuleDecoder)
    _held: list[Capsule] = field(default_factory=list)
    _last_angle: int = -1
    _broken: bool = False

    @property
    def bad_capsules(self) -> int:
        return self.capsules.bad_capsules

    def reset(self) -> None:
        self.capsules.reset()
        self._held.clear()
        self._last_angle, self._broken = -1, False

    def feed(self, data: bytes) -> Nodes:
        parts: list[Nodes] = []
        skipped = self.capsules.skipped_bytes
        lost = 0
        for capsule in self.capsules.feed(data):
            if capsule.broken:
                lost += 2 * CABINS * len(self._held)
                self._held.clear()
                self._last_angle, self._broken = -1, True
            self._held.append(capsule)
            if len(self._held) < 3:
                continue
            first, second = self._held[0], self._held[1]
            del self._held[0]
            angle, dist, _ = capsule_nodes(first, second.start_angle_q6)
            previous = np.concatenate(([self._last_angle], angle[:-1]))
            start = (previous >= 0) & (angle < previous - FULL_CIRCLE_Q6 // 2)
            broken = np.zeros(angle.size, bool)
            broken[0] = self._broken
            self._broken = False
            self._last_angle = int(angle[-1])
            parts.append(Nodes(start, np.zeros(angle.size, np.int64), angle, dist, broken))
        return Nodes.concat(parts, lost + round((self.capsules.skipped_bytes - skipped) * 2 * CABINS / CAPSULE_SIZE))
