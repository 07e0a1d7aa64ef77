"""Slamtec RPLIDAR measurement capsules, the answers EXPRESS_SCAN streams: express (0x82),
HQ (0x83), ultra (0x84), dense (0x85) and ultra-dense (0x86). Framing, decoding and encoding as
pure functions over numpy arrays, vectorised over every capsule a read delivered.

Layouts from ``sl_lidar_cmd.h`` (Slamtec/rplidar_ros @ 2f10ad5b, ``sdk/include``). The sample
arithmetic (angles interpolated between consecutive capsules, the ultra capsules' variable-bit-
scale distances and optical angle compensation, the ultra-dense distance scales) follows
``handler_capsules.cpp`` and ``handler_hqnode.cpp`` (``sdk/src/dataunpacker/unpacker``), the HQ
CRC ``sl_crc.cpp`` of the same SDK; descriptors are those of the interface protocol (A3M1
edition, figures 4-13 to 4-21: ultra ``A5 5A 84 00 00 40 84``, dense ``A5 5A 54 00 00 40 85``).

All but HQ start with two bytes whose high nibbles are 0xA and 0x5 and whose low nibbles hold
the XOR of every following byte; a capsule's u16 start angle (Q6, bit 15 = first capsule of a
scan) and the next capsule's give the angles of its samples, so samples leave one capsule late.
HQ frames carry their own angles and a CRC-32. Decoders never raise: bad capsules are counted,
the stream is realigned on two consecutive good capsules, and samples touched are dropped.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from trundle.drivers import rplidar as rp

FULL_Q8 = 360 << 8
Decoded = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # a decoder's four node arrays
UNPACK = Callable[[np.ndarray, np.ndarray], Decoded]

# Ultra capsules (handler_capsules.cpp): a 12-bit "major" distance in a variable bit scale,
# the scaled value at which each scale starts, its first distance (mm) and its step (2^level).
VBS_SCALED = np.array([0, 512, 1280, 1792, 3328])
VBS_TARGET = np.array([0, 512, 2048, 4096, 16384])
PREDICT_INVALID = (-512, 511)  # the two 10-bit predictions that mean "no measurement"
# the SDK's optical compensation of ultra-capsule angles, in Q16 radians, computed as it does
OFFSET_NEAR_Q16 = int(7.5 * 3.1415926535 * (1 << 16) / 180.0)
OFFSET_FAR_Q16 = int(8 * 3.1415926535 * (1 << 16) / 180)
# ultra-dense distances: 2, 3, 4 or 5 mm steps above these bases (mm) for scales 0..3
ULTRA_DENSE_BASE_MM = (0, 2046, 8187, 24567)


@dataclass(frozen=True)
class CapsuleFormat:
    """One answer type: ``size`` bytes a capsule, ``samples`` in it, ``hold`` capsules kept back
    before their samples leave (the next one gives their angles; one more confirms the framing,
    since an XOR cannot see an inserted byte equal to the one it displaced), whether samples
    carry ``quality``, and the functions that check a capsule and turn capsules into samples."""

    name: str
    answer_type: int
    size: int
    samples: int
    hold: int
    quality: bool
    check: Callable[[np.ndarray], np.ndarray]
    sync: Callable[[np.ndarray], np.ndarray]
    unpack: UNPACK

    @property
    def descriptor(self) -> rp.Descriptor:
        return rp.Descriptor(self.size, rp.MULTIPLE, self.answer_type)


# --- framing ------------------------------------------------------------------------------------

def _xor_check(rows: np.ndarray) -> np.ndarray:
    """Sync nibbles 0xA, 0x5 and the XOR of bytes 2.. in their low nibbles, per row."""
    check = np.bitwise_xor.reduce(rows[:, 2:], axis=1)
    return (((rows[:, 0] >> 4) == 0xA) & ((rows[:, 1] >> 4) == 0x5)
            & ((rows[:, 0] & 0xF) == (check & 0xF)) & ((rows[:, 1] & 0xF) == (check >> 4)))


def _xor_sync(a: np.ndarray) -> np.ndarray:
    return ((a[:-1] >> 4) == 0xA) & ((a[1:] >> 4) == 0x5)


def hq_crc(frame_without_crc: bytes) -> int:
    """CRC-32 (zlib's) of an HQ frame without its CRC field, zero-padded as ``sl_crc.cpp`` does
    (``4 - len % 4`` bytes: one to four, never none)."""
    return zlib.crc32(frame_without_crc + bytes(4 - len(frame_without_crc) % 4))


def _hq_check(rows: np.ndarray) -> np.ndarray:
    out = np.zeros(len(rows), bool)
    for i, row in enumerate(rows):
        if row[0] == rp.SYNC:
            raw = row.tobytes()
            out[i] = hq_crc(raw[:-4]) == struct.unpack("<I", raw[-4:])[0]
    return out


def _hq_sync(a: np.ndarray) -> np.ndarray:
    return a[:-1] == rp.SYNC


# --- sample arithmetic --------------------------------------------------------------------------

def _u16(rows: np.ndarray, at: int) -> np.ndarray:
    return rows[:, at].astype(np.int64) | (rows[:, at + 1].astype(np.int64) << 8)


def _raw_q16(rows: np.ndarray, nxt: np.ndarray, at: int, samples: int) -> np.ndarray:
    """Turret angles (Q16 degrees, not wrapped) of each capsule's samples: from its start angle
    towards the next capsule's, in equal integer steps (the SDK's ``angleInc_q16``)."""
    start = (_u16(rows, at) & 0x7FFF) << 2
    diff = ((_u16(nxt, at) & 0x7FFF) << 2) - start
    diff = np.where(diff < 0, diff + FULL_Q8, diff)
    inc = (diff << 8) // samples
    return (start << 8)[:, None] + inc[:, None] * np.arange(samples)


def _wrap_q6(angle: np.ndarray) -> np.ndarray:
    return np.mod(angle, rp.FULL_CIRCLE_Q6)


def _express(rows: np.ndarray, nxt: np.ndarray) -> Decoded:
    """Express: per cabin two u16 ``distance_angle`` words (distance in bits 15..2, high bits of
    the angle offset in 1..0) and a byte of two 4-bit low offsets, Q3 degrees subtracted."""
    raw = _raw_q16(rows, nxt, 2, 32)
    cab = rows[:, 4:].reshape(len(rows), 16, 5).astype(np.int64)
    w1, w2 = cab[..., 0] | (cab[..., 1] << 8), cab[..., 2] | (cab[..., 3] << 8)
    dist = np.stack((w1 & 0xFFFC, w2 & 0xFFFC), axis=-1).reshape(len(rows), 32)
    dth = np.stack(((cab[..., 4] & 0xF) | ((w1 & 3) << 4), (cab[..., 4] >> 4) | ((w2 & 3) << 4)),
                   axis=-1).reshape(len(rows), 32)
    return _wrap_q6((raw - (dth << 13)) >> 10), _wrap_q6(raw >> 10), dist, np.zeros_like(dist)


def vbs_decode(scaled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ultra ``major`` values -> (distance mm, scale level)."""
    level = np.searchsorted(VBS_SCALED, scaled, side="right") - 1
    return VBS_TARGET[level] + ((scaled - VBS_SCALED[level]) << level), level


def ultra_offset_q6(distance_q2: np.ndarray, raw_q16: np.ndarray) -> np.ndarray:
    """Measurement angles (Q6, wrapped) of ultra samples at turret angles ``raw_q16``: the SDK's
    compensation of the triangulation optics, in its own integer and float steps."""
    d = np.asarray(distance_q2, np.int64)
    k2 = 98361 // np.maximum(d, 1)
    offset = np.where(d >= 50 * 4, OFFSET_FAR_Q16 - (k2 << 6) - (k2 * k2 * k2) // 98304, OFFSET_NEAR_Q16)
    return _wrap_q6((raw_q16 - np.trunc(offset * 180 / 3.14159265).astype(np.int64)) >> 10)


def _ultra(rows: np.ndarray, nxt: np.ndarray) -> Decoded:
    """Ultra: per cabin a u32 of a 12-bit major distance and two signed 10-bit predictions; the
    first sample is the major, the second predicts from it, the third from the next cabin's."""
    n = len(rows)
    cab = np.ascontiguousarray(rows[:, 4:]).view("<u4").astype(np.int64)
    first_next = np.ascontiguousarray(nxt[:, 4:8]).view("<u4").astype(np.int64)[:, 0]
    major = cab & 0xFFF
    p1, p2 = (cab >> 12) & 0x3FF, (cab >> 22) & 0x3FF
    p1, p2 = np.where(p1 >= 512, p1 - 1024, p1), np.where(p2 >= 512, p2 - 1024, p2)
    d0, level0 = vbs_decode(major)
    d_next, level_next = vbs_decode(np.column_stack((major[:, 1:], first_next & 0xFFF)))
    borrow = (d0 == 0) & (d_next != 0)
    base1, level1 = np.where(borrow, d_next, d0), np.where(borrow, level_next, level0)
    d1 = np.where(np.isin(p1, PREDICT_INVALID), 0, (p1 << level1) + base1)
    d2 = np.where(np.isin(p2, PREDICT_INVALID), 0, (p2 << level_next) + d_next)
    dist = np.maximum(np.stack((d0, d1, d2), axis=-1).reshape(n, 96), 0) << 2  # the SDK wraps negatives to u32
    raw = _raw_q16(rows, nxt, 2, 96)
    return ultra_offset_q6(dist, raw), _wrap_q6(raw >> 10), dist, np.zeros_like(dist)


def _dense(rows: np.ndarray, nxt: np.ndarray) -> Decoded:
    """Dense: 40 u16 distances (mm) at equally spaced angles, no per-sample offset."""
    raw = _raw_q16(rows, nxt, 2, 40)
    dist = np.ascontiguousarray(rows[:, 4:]).view("<u2").astype(np.int64) << 2
    encoder = _wrap_q6(raw >> 10)
    return encoder, encoder, dist, np.zeros_like(dist)


def _ultra_dense(rows: np.ndarray, nxt: np.ndarray) -> Decoded:
    """Ultra-dense: after a u32 timestamp and u16 status, 32 cabins of two u16 and a byte of two
    nibbles; each sample's 20 bits hold a 2-bit scale, the distance and an 8-bit quality."""
    n = len(rows)
    raw = _raw_q16(rows, nxt, 8, 64)
    cab = rows[:, 10:].reshape(n, 32, 5).astype(np.int64)
    v = np.stack((cab[..., 0] | (cab[..., 1] << 8) | ((cab[..., 4] & 0xF) << 16),
                  cab[..., 2] | (cab[..., 3] << 8) | ((cab[..., 4] >> 4) << 16)), axis=-1).reshape(n, 64)
    scale = v & 3
    field_ = [(v & 0xFFC) * 2, (v & 0x1FFC) * 3, (v & 0x3FFC) * 4, (v & 0x7FFC) * 5]
    dist = np.choose(scale, [f + (b << 2) for f, b in zip(field_, ULTRA_DENSE_BASE_MM, strict=True)])
    quality = np.choose(scale, [v >> 12, (v >> 13) << 1, (v >> 14) << 2, (v >> 15) << 3])
    encoder = _wrap_q6(raw >> 10)
    return encoder, encoder, dist, quality >> 2


def _hq(rows: np.ndarray, nxt: np.ndarray) -> Decoded:
    """HQ: 96 nodes of u16 angle (Q14 of 90 deg), u32 distance (Q2 mm), quality and flag bytes."""
    nodes = np.ascontiguousarray(rows[:, 9:9 + 96 * 8]).reshape(len(rows), 96, 8)
    q14 = nodes[..., 0:2].copy().view("<u2")[..., 0].astype(np.int64)
    dist = nodes[..., 2:6].copy().view("<u4")[..., 0].astype(np.int64)
    angle = _wrap_q6((q14 * 90) >> 8)  # the SDK's conversion of HQ angles to Q6
    return angle, angle, dist, nodes[..., 6].astype(np.int64) >> 2


EXPRESS = CapsuleFormat("express", rp.ANS_CAPSULED, 84, 32, 2, False, _xor_check, _xor_sync, _express)
HQ = CapsuleFormat("hq", rp.ANS_HQ, 1 + 8 + 96 * 8 + 4, 96, 0, True, _hq_check, _hq_sync, _hq)
ULTRA = CapsuleFormat("ultra", rp.ANS_ULTRA, 132, 96, 2, False, _xor_check, _xor_sync, _ultra)
DENSE = CapsuleFormat("dense", rp.ANS_DENSE, 84, 40, 2, False, _xor_check, _xor_sync, _dense)
ULTRA_DENSE = CapsuleFormat("ultra-dense", rp.ANS_ULTRA_DENSE, 170, 64, 2, True, _xor_check, _xor_sync,
                            _ultra_dense)
FORMATS = {f.answer_type: f for f in (EXPRESS, HQ, ULTRA, DENSE, ULTRA_DENSE)}


# --- stream decoders ----------------------------------------------------------------------------

@dataclass
class CapsuleFramer(rp.Resynchronising):
    """Bytes -> whole capsules that check out, realigning after a bad one on the first offset
    where two capsules in a row check out. Counters: ``bad_capsules``, ``resyncs``, ``skipped_bytes``."""

    format: CapsuleFormat = EXPRESS
    bad_capsules: int = 0

    def feed(self, data: bytes) -> tuple[np.ndarray, np.ndarray]:
        """Rows (k, size) of the good capsules ``data`` completes, and per row whether bytes
        were lost just before it."""
        size, check = self.format.size, self.format.check
        self._buf += data
        a = np.frombuffer(bytes(self._buf), np.uint8)
        rows_out: list[np.ndarray] = []
        broken_out: list[np.ndarray] = []
        p = 0
        while len(a) - p >= size:
            if not self._aligned:
                if len(a) - p < 2 * size:
                    break
                last = len(a) - 2 * size
                cand = p + np.flatnonzero(self.format.sync(a[p:last + 2]))
                good = cand[check(a[cand[:, None] + np.arange(size)])] if cand.size else cand
                good = good[check(a[good[:, None] + size + np.arange(size)])] if good.size else good
                if not good.size:
                    self.skipped_bytes += last + 1 - p
                    p = last + 1
                    continue
                self.skipped_bytes += int(good[0]) - p
                p = int(good[0])
                self._aligned = True
            k = (len(a) - p) // size
            rows = a[p:p + k * size].reshape(k, size)
            bad = np.flatnonzero(~check(rows))
            ok = int(bad[0]) if bad.size else k
            if ok:
                broken = np.zeros(ok, bool)
                broken[0], self._broken = self._broken, False
                rows_out.append(rows[:ok])
                broken_out.append(broken)
            p += ok * size
            if bad.size:
                self.bad_capsules += 1
                p += self._lose_alignment()
        del self._buf[:p]
        if not rows_out:
            return np.zeros((0, size), np.uint8), np.zeros(0, bool)
        return np.concatenate(rows_out), np.concatenate(broken_out)


@dataclass
class CapsuleNodeDecoder:
    """Stream of one capsule format -> ``Nodes`` (the same output as ``rplidar.NodeDecoder``).

    Samples of a capsule leave once ``format.hold`` more capsules followed it without a break;
    ``start`` marks the first sample of a revolution: where the turret angle falls back by more
    than half a turn. Quality is 0 for the formats that do not send it.
    """

    format: CapsuleFormat = EXPRESS
    framer: CapsuleFramer = field(init=False)
    _held: np.ndarray = field(init=False)
    _last_encoder: int = -1
    _broken: bool = False

    def __post_init__(self) -> None:
        self.framer = CapsuleFramer(format=self.format)
        self._held = np.zeros((0, self.format.size), np.uint8)

    @property
    def bad_capsules(self) -> int:
        return self.framer.bad_capsules

    def reset(self) -> None:
        self.framer.reset()
        self._held = self._held[:0]
        self._last_encoder, self._broken = -1, False

    def feed(self, data: bytes) -> rp.Nodes:
        fmt = self.format
        skipped = self.framer.skipped_bytes
        rows, broken = self.framer.feed(data)
        lost = 0
        parts: list[rp.Nodes] = []
        cuts = np.flatnonzero(broken).tolist()
        bounds = sorted({0, *cuts, len(rows)})
        for a, b in pairwise(bounds):
            if broken[a]:
                lost += fmt.samples * len(self._held)
                self._held = self._held[:0]
                self._last_encoder, self._broken = -1, True
            run = np.concatenate((self._held, rows[a:b])) if len(self._held) else rows[a:b]
            emit = len(run) - fmt.hold
            if emit > 0:
                parts.append(self._nodes(run[:emit], run[1:emit + 1] if fmt.hold else run[:emit]))
                self._held = run[emit:]
            else:
                self._held = run
        return rp.Nodes.concat(parts, lost + round((self.framer.skipped_bytes - skipped) * fmt.samples / fmt.size))

    def _nodes(self, rows: np.ndarray, nxt: np.ndarray) -> rp.Nodes:
        angle, encoder, dist, quality = (v.reshape(-1) for v in self.format.unpack(rows, nxt))
        previous = np.empty_like(encoder)
        previous[0], previous[1:] = self._last_encoder, encoder[:-1]
        start = (previous >= 0) & (encoder < previous - rp.FULL_CIRCLE_Q6 // 2)
        broken = np.zeros(encoder.size, bool)
        broken[0], self._broken = self._broken, False
        self._last_encoder = int(encoder[-1])
        return rp.Nodes(start, quality, angle, dist, broken, encoder)


# --- encoders (the emulator's side) -------------------------------------------------------------

def _seal(body: bytes) -> bytes:
    """Prefix the two sync/checksum bytes of the XOR-checked formats."""
    check = rp.xor(body)
    return bytes((0xA0 | (check & 0xF), 0x50 | (check >> 4))) + body


def _start(start_angle_q6: int, new_scan: bool) -> bytes:
    return struct.pack("<H", (start_angle_q6 & 0x7FFF) | (0x8000 if new_scan else 0))


def encode_capsule(
    start_angle_q6: int, distance_q2: np.ndarray, dtheta_q3: np.ndarray, new_scan: bool = False
) -> bytes:
    """An express capsule: 32 distances (1/4 mm, multiples of 4) with their angle offsets (1/8
    deg, 0..63), after a start angle in 1/64 deg."""
    dist = np.asarray(distance_q2, np.int64).reshape(16, 2)
    dth = np.asarray(dtheta_q3, np.int64).reshape(16, 2)
    words = (dist & 0xFFFC) | ((dth >> 4) & 3)
    cabins = np.empty((16, 5), np.uint8)
    cabins[:, 0], cabins[:, 1] = words[:, 0] & 0xFF, words[:, 0] >> 8
    cabins[:, 2], cabins[:, 3] = words[:, 1] & 0xFF, words[:, 1] >> 8
    cabins[:, 4] = (dth[:, 0] & 0xF) | ((dth[:, 1] & 0xF) << 4)
    return _seal(_start(start_angle_q6, new_scan) + cabins.tobytes())


def encode_dense_capsule(start_angle_q6: int, distance_mm: np.ndarray, new_scan: bool = False) -> bytes:
    """A dense capsule: 40 distances in whole millimetres (0..65535)."""
    dist = np.clip(np.asarray(distance_mm, np.int64), 0, 0xFFFF).astype("<u2")
    return _seal(_start(start_angle_q6, new_scan) + dist.tobytes())


def vbs_encode(distance_mm: np.ndarray) -> np.ndarray:
    """The 12-bit major nearest each distance (mm); 0 (no measurement) beyond the scale's reach."""
    d = np.asarray(distance_mm, np.int64)
    level = np.maximum(np.searchsorted(VBS_TARGET, d, side="right") - 1, 0)
    scaled = VBS_SCALED[level] + ((d - VBS_TARGET[level] + ((1 << level) >> 1)) >> level)
    return np.where((d <= 0) | (scaled > 0xFFF), 0, scaled)


def encode_ultra_capsule(start_angle_q6: int, distance_mm: np.ndarray, next_mm: int,
                         new_scan: bool = False) -> tuple[bytes, np.ndarray]:
    """An ultra capsule of 96 distances (mm) and the first distance of the capsule after it;
    returns the bytes and the distances (mm) they represent after quantisation."""
    d = np.asarray(distance_mm, np.int64).reshape(32, 3)
    major = vbs_encode(np.append(d[:, 0], next_mm))
    value, level = vbs_decode(major)
    d0, d_next, level0, level_next = value[:-1], value[1:], level[:-1], level[1:]
    borrow = (d0 == 0) & (d_next != 0)
    base1, level1 = np.where(borrow, d_next, d0), np.where(borrow, level_next, level0)

    def predict(target: np.ndarray, base: np.ndarray, lvl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = (target - base + ((1 << lvl) >> 1)) >> lvl
        shown = base + (p << lvl)
        valid = (target > 0) & (p > -512) & (p < 511) & (shown > 0)
        return np.where(valid, p, 511), np.where(valid, shown, 0)

    p1, shown1 = predict(d[:, 1], base1, level1)
    p2, shown2 = predict(d[:, 2], d_next, level_next)
    words = (major[:-1] | ((p1 & 0x3FF) << 12) | ((p2 & 0x3FF) << 22)).astype("<u4")
    shown = np.stack((d0, shown1, shown2), axis=-1).reshape(96)
    return _seal(_start(start_angle_q6, new_scan) + words.tobytes()), shown


def encode_ultra_dense_capsule(start_angle_q6: int, distance_mm: np.ndarray, quality: np.ndarray,
                               new_scan: bool = False, timestamp: int = 0,
                               status: int = 0) -> tuple[bytes, np.ndarray, np.ndarray]:
    """An ultra-dense capsule of 64 distances (mm) and qualities (0..255), each in the finest
    scale that reaches it; returns the bytes and the distances (mm) and qualities they represent."""
    d = np.clip(np.asarray(distance_mm, np.int64), 0, ULTRA_DENSE_BASE_MM[3] + 5 * 0x1FFF)
    q = np.clip(np.asarray(quality, np.int64), 0, 255)
    scale = np.searchsorted(np.array(ULTRA_DENSE_BASE_MM[1:]), d, side="left")
    step = scale + 2
    units = (d - np.array(ULTRA_DENSE_BASE_MM)[scale] + step // 2) // step
    units = np.minimum(units, (0x3FF << scale) | ((1 << scale) - 1))
    q_bits = q >> scale
    v = scale | (units << 2) | (q_bits << (12 + scale))
    shown = units * step + np.array(ULTRA_DENSE_BASE_MM)[scale]
    cab = np.empty((32, 5), np.uint8)
    pair = v.reshape(32, 2)
    cab[:, 0], cab[:, 1] = pair[:, 0] & 0xFF, (pair[:, 0] >> 8) & 0xFF
    cab[:, 2], cab[:, 3] = pair[:, 1] & 0xFF, (pair[:, 1] >> 8) & 0xFF
    cab[:, 4] = ((pair[:, 0] >> 16) & 0xF) | (((pair[:, 1] >> 16) & 0xF) << 4)
    head = struct.pack("<IH", timestamp & 0xFFFFFFFF, status & 0xFFFF) + _start(start_angle_q6, new_scan)
    return _seal(head + cab.tobytes()), shown, q_bits << scale


def encode_hq_capsule(angle_q6: np.ndarray, distance_q2: np.ndarray, quality: np.ndarray,
                      start: np.ndarray, timestamp: int = 0) -> bytes:
    """An HQ frame of 96 nodes. Angles are rounded up to Q14 so that the SDK's conversion back to
    Q6 (rounding down) returns them exactly."""
    nodes = np.zeros(96, dtype=[("angle", "<u2"), ("dist", "<u4"), ("quality", "u1"), ("flag", "u1")])
    nodes["angle"] = np.minimum((np.asarray(angle_q6, np.int64) * 256 + 89) // 90, 0xFFFF)
    nodes["dist"] = np.asarray(distance_q2, np.int64)
    nodes["quality"] = np.asarray(quality, np.int64)
    s = np.asarray(start, bool)
    nodes["flag"] = np.where(s, 1, 2)
    body = bytes((rp.SYNC,)) + struct.pack("<Q", timestamp) + nodes.tobytes()
    return body + struct.pack("<I", hq_crc(body))
