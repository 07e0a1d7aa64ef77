"""RPLIDAR capsule formats: real device capsules, the SDK's arithmetic by hand and through
pyrplidar (a port of the SDK), round trips through the emulator's encoders, and fuzzing."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pyrplidar_protocol
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.lrf_harness import MUTATIONS, mutate
from trundle.drivers import rplidar as rp
from trundle.drivers import rplidar_capsules as rc

FIXTURE = json.loads((Path(__file__).parent / "data" / "pyrplidar_capsules.json").read_text())
FORMATS = (rc.EXPRESS, rc.HQ, rc.ULTRA, rc.DENSE, rc.ULTRA_DENSE)


def rows_of(capsules: list[bytes]) -> np.ndarray:
    return np.array([np.frombuffer(c, np.uint8) for c in capsules])


def q14(angle_q6: np.ndarray) -> np.ndarray:
    """The SDK's (and pyrplidar's) Q6 -> Q14 angle conversion."""
    return (np.asarray(angle_q6, np.int64) << 8) // 90


@pytest.mark.parametrize("name, fmt", [("express", rc.EXPRESS), ("ultra", rc.ULTRA)])
def test_real_capsules_decode_to_the_samples_pyrplidar_expects(name, fmt):
    """Five consecutive capsules from a device (pyrplidar's test file, see the fixture's _source):
    every sample's distance and angle must be what that test expects, to the last bit."""
    capsules = [bytes.fromhex(c) for c in FIXTURE[name]["capsules"]]
    expected = np.array(FIXTURE[name]["samples"])  # (pairs, samples, [flag, quality, angle_q14, dist_q2])
    rows = rows_of(capsules)
    assert rc._xor_check(rows).all() and rows.shape[1] == fmt.size
    angle, encoder, distance, quality = fmt.unpack(rows[:-1], rows[1:])
    np.testing.assert_array_equal(distance, expected[..., 3])
    np.testing.assert_array_equal(q14(angle), expected[..., 2])
    # the SDK invents quality 47 << 2 for every valid sample of these formats; they carry none
    np.testing.assert_array_equal(expected[..., 1], np.where(expected[..., 3] > 0, 0xBC, 0))
    assert not quality.any()
    # the stream decoder gives the same samples (one capsule later: it holds two back)
    nodes = rc.CapsuleNodeDecoder(fmt).feed(b"".join(capsules))
    np.testing.assert_array_equal(nodes.distance_q2, expected[:3, :, 3].reshape(-1))
    # the SDK flags the sample before the 360 degree crossing, trundle the first after it
    sdk_flags = np.flatnonzero(expected[:3, :, 0].reshape(-1) == 1)
    np.testing.assert_array_equal(np.flatnonzero(nodes.start), sdk_flags + 1)


def test_variable_bit_scale_by_the_pyrplidar_examples():
    # pyrplidar test_varbitscale_decode: majors and their distances (mm) and scale levels
    distance, level = rc.vbs_decode(np.array([0x1E0, 0x20B, 0x219, 0x504, 0x507, 0x51E]))
    assert distance.tolist() == [0x1E0, 0x216, 0x232, 0x810, 0x81C, 0x878] and level.tolist() == [0, 1, 1, 2, 2, 2]
    assert rc.vbs_encode(distance).tolist() == [0x1E0, 0x20B, 0x219, 0x504, 0x507, 0x51E]


def test_ultra_angle_compensation_by_hand():
    # 1000 mm (Q2 4000): k2 = 98361 // 4000 = 24, offset = 9150 - 24 * 64 - 24**3 // 98304 = 7614 (Q16 rad),
    # in Q16 degrees trunc(7614 * 180 / 3.14159265) = 436250, so a turret at 90 deg reads 90 - 6.6566 deg
    assert rc.OFFSET_FAR_Q16 == 9150 and rc.OFFSET_NEAR_Q16 == 8578
    assert int(7614 * 180 / 3.14159265) == 436250
    raw = np.array([90 << 16])
    assert rc.ultra_offset_q6(np.array([4000]), raw).tolist() == [((90 << 16) - 436250) >> 10]
    # below 50 mm (and for no measurement) the fixed 7.5 deg offset
    assert rc.ultra_offset_q6(np.array([0]), raw).tolist() == [((90 << 16) - int(8578 * 180 / 3.14159265)) >> 10]


def test_express_samples_by_hand():
    # start 10 deg, next capsule at 42 deg: 1 deg per sample; sample 3 with dtheta 1.5 deg (12 Q3)
    dth = np.zeros(32, np.int64)
    dth[3] = 12
    rows = rows_of(
        [rc.encode_capsule(640, np.full(32, 4000), dth), rc.encode_capsule(42 * 64, np.full(32, 4000), 0 * dth)]
    )
    angle, encoder, distance, _ = rc.EXPRESS.unpack(rows[:1], rows[1:])
    assert angle[0, :5].tolist() == [640, 704, 768, 832 - 96, 896] and encoder[0, 3] == 832
    assert (distance == 4000).all()


def test_express_arithmetic_matches_the_sdk_port_in_pyrplidar():
    rng = np.random.default_rng(11)
    for start, nxt in [(0, 2048), (22000, 1000), (100, 100 + 5 * 64), (23000, 40)]:
        first = rc.encode_capsule(start, rng.integers(0, 16000, 32) * 4, rng.integers(0, 64, 32))
        second = rc.encode_capsule(nxt, rng.integers(0, 16000, 32) * 4, rng.integers(0, 64, 32))
        angle, _, distance, _ = rc.EXPRESS.unpack(rows_of([first]), rows_of([second]))
        nodes = pyrplidar_protocol.PyRPlidarScanCapsule._parse_capsule(
            pyrplidar_protocol.PyRPlidarScanCapsule(first), pyrplidar_protocol.PyRPlidarScanCapsule(second))
        assert distance[0].tolist() == [n.dist_mm_q2 for n in nodes]
        assert q14(angle[0]).tolist() == [n.angle_z_q14 for n in nodes]


def test_dense_samples_by_hand():
    # sl_lidar_cmd.h: 40 u16 distances (mm); angles step evenly from one start angle to the next
    body = struct.pack("<H", 0x8000 | (30 * 64)) + struct.pack("<40H", *range(1000, 1040))
    capsule = bytes((0xA0 | (rp.xor(body) & 0xF), 0x50 | (rp.xor(body) >> 4))) + body
    assert capsule == rc.encode_dense_capsule(30 * 64, np.arange(1000, 1040), new_scan=True)
    angle, encoder, distance, _ = rc.DENSE.unpack(
        rows_of([capsule]), rows_of([rc.encode_dense_capsule(34 * 64, np.zeros(40))])
    )
    assert (distance[0] == np.arange(1000, 1040) * 4).all()
    assert (
        angle[0, :3].tolist() == [30 * 64, 30 * 64 + 6, 30 * 64 + 12] and (angle == encoder).all()
    )  # 4 deg / 40 = 6.4 Q6


def test_ultra_dense_samples_by_hand():
    # each sample: 2-bit scale, distance, quality in 20 bits (low 16 in a u16, high 4 in a nibble)
    v = [0 | (500 << 2) | (200 << 12),  # scale 0: 2 mm units -> 1000 mm, quality 200
         1 | (1000 << 2) | (100 << 13),  # scale 1: 3 mm above 2046 -> 5046 mm, quality 200
         2 | (2000 << 2) | (50 << 14),  # scale 2: 4 mm above 8187 -> 16187 mm, quality 200
         3 | (3000 << 2) | (25 << 15)]  # scale 3: 5 mm above 24567 -> 39567 mm, quality 200
    cabins = b"".join(struct.pack("<HHB", v[2 * i] & 0xFFFF, v[2 * i + 1] & 0xFFFF,
                                  (v[2 * i] >> 16) | ((v[2 * i + 1] >> 16) << 4)) for i in range(2)) + bytes(30 * 5)
    body = struct.pack("<IHH", 123, 0, 64 * 64) + cabins
    capsule = bytes((0xA0 | (rp.xor(body) & 0xF), 0x50 | (rp.xor(body) >> 4))) + body
    nxt = rc.encode_ultra_dense_capsule(74 * 64, np.zeros(64), np.zeros(64))[0]
    _, _, distance, quality = rc.ULTRA_DENSE.unpack(rows_of([capsule]), rows_of([nxt]))
    assert (distance[0, :4] // 4).tolist() == [1000, 5046, 16187, 39567]
    assert quality[0, :4].tolist() == [200 >> 2] * 4


def test_hq_frame_by_hand():
    # sl_lidar_cmd.h: sync 0xA5, u64 timestamp, 96 x (u16 angle Q14, u32 distance Q2, quality, flag), CRC-32
    frame = rc.encode_hq_capsule(np.arange(96) * 240, np.arange(96) * 1000, np.full(96, 188), np.arange(96) == 0, 7)
    assert len(frame) == 781 and frame[0] == 0xA5 and struct.unpack("<Q", frame[1:9])[0] == 7
    assert struct.unpack("<HIBB", frame[9:17]) == (0, 0, 188, 1)
    assert struct.unpack("<HIBB", frame[17:25]) == ((240 * 256 + 89) // 90, 1000, 188, 2)
    # sl_crc.cpp pads 777 bytes with 3 zero bytes before the standard CRC-32
    assert struct.unpack("<I", frame[-4:])[0] == zlib.crc32(frame[:-4] + bytes(3))
    angle, _, distance, quality = rc.HQ.unpack(rows_of([frame]), rows_of([frame]))
    assert (angle[0] == np.arange(96) * 240).all() and (distance[0] == np.arange(96) * 1000).all()
    assert (quality == 47).all()
    bad = bytearray(frame)
    bad[100] ^= 4
    assert not rc._hq_check(rows_of([bytes(bad)]))[0]


def encode_stream(fmt: rc.CapsuleFormat, n: int, rng: np.random.Generator, step_q6: int = 16):
    """``n`` consecutive capsules of smooth random distances over a turret stepping ``step_q6``;
    returns the bytes and per sample (distance Q2, measurement angle Q6) they represent."""
    spc = fmt.samples
    total = spc * (n + 1)
    mm = np.clip(3000 + np.cumsum(rng.integers(-40, 41, total)), 60, 20000)
    mm[rng.random(total) < 0.05] = 0
    turret = (np.arange(total) * step_q6) % rp.FULL_CIRCLE_Q6
    out, shown_all, angle_all = [], [], []
    for i in range(n):
        s = slice(i * spc, (i + 1) * spc)
        start = int(turret[i * spc])
        if fmt is rc.EXPRESS:
            raw, shown = rc.encode_capsule(start, mm[s] * 4, np.zeros(spc, np.int64)), mm[s]
        elif fmt is rc.DENSE:
            raw, shown = rc.encode_dense_capsule(start, mm[s]), mm[s]
        elif fmt is rc.ULTRA:
            raw, shown = rc.encode_ultra_capsule(start, mm[s], int(mm[(i + 1) * spc]))
        elif fmt is rc.ULTRA_DENSE:
            raw, shown, _ = rc.encode_ultra_dense_capsule(start, mm[s], np.full(spc, 188))
        else:
            raw, shown = rc.encode_hq_capsule(turret[s], mm[s] * 4, np.full(spc, 188), turret[s] == 0), mm[s]
        out.append(raw)
        shown_all.append(shown * 4)
        angle_all.append(rc.ultra_offset_q6(shown * 4, turret[s] << 10) if fmt is rc.ULTRA else turret[s])
    return out, np.concatenate(shown_all), np.concatenate(angle_all)


@pytest.mark.parametrize("fmt", FORMATS, ids=lambda f: f.name)
def test_encoded_streams_decode_to_what_they_represent(fmt):
    rng = np.random.default_rng(3)
    capsules, distance, angle = encode_stream(fmt, 60, rng)
    decoder = rc.CapsuleNodeDecoder(fmt)
    stream = b"".join(capsules)
    nodes = rp.Nodes.concat([decoder.feed(stream[i:i + 333]) for i in range(0, len(stream), 333)])
    emitted = (60 - fmt.hold) * fmt.samples
    assert len(nodes) == emitted and not nodes.broken.any() and decoder.bad_capsules == 0
    np.testing.assert_array_equal(nodes.distance_q2, distance[:emitted])
    np.testing.assert_array_equal(nodes.angle_q6, angle[:emitted])
    np.testing.assert_array_equal(nodes.encoder_q6, (np.arange(emitted) * 16) % rp.FULL_CIRCLE_Q6)
    assert np.flatnonzero(nodes.start).tolist() == [k for k in range(1, emitted) if k * 16 % rp.FULL_CIRCLE_Q6 == 0]
    if fmt.quality:
        assert (nodes.quality[nodes.distance_q2 > 0] == 47).all()


def test_ultra_capsules_read_by_pyrplidar():
    """pyrplidar's port of the SDK decodes the emulator's ultra capsules to the same samples."""
    capsules, distance, _ = encode_stream(rc.ULTRA, 8, np.random.default_rng(8))
    rows = rows_of(capsules)
    angle, _, ours, _ = rc.ULTRA.unpack(rows[:-1], rows[1:])
    for i in range(7):
        nodes = pyrplidar_protocol.PyRPlidarScanUltraCapsule._parse_capsule(
            pyrplidar_protocol.PyRPlidarScanUltraCapsule(capsules[i]),
            pyrplidar_protocol.PyRPlidarScanUltraCapsule(capsules[i + 1]),
        )
        assert [n.dist_mm_q2 for n in nodes] == ours[i].tolist() == distance[96 * i:96 * (i + 1)].tolist()
        assert [n.angle_z_q14 for n in nodes] == q14(angle[i]).tolist()


@pytest.mark.parametrize("fmt", FORMATS, ids=lambda f: f.name)
def test_a_bad_capsule_is_counted_and_the_stream_realigns(fmt):
    capsules, distance, _ = encode_stream(fmt, 12, np.random.default_rng(2))
    stream = bytearray(b"".join(capsules))
    stream[5 * fmt.size + 40] ^= 0x10
    decoder = rc.CapsuleNodeDecoder(fmt)
    nodes = rp.Nodes.concat([decoder.feed(bytes(stream[:500])), decoder.feed(bytes(stream[500:]))])
    assert decoder.bad_capsules == 1 and decoder.framer.resyncs == 1
    # capsule 5 is lost, and with it the held-back ones before it; the samples after the break are intact
    kept = set(zip(nodes.encoder_q6.tolist(), nodes.distance_q2.tolist(), strict=True))
    assert kept <= set(
        zip(((np.arange(distance.size) * 16) % rp.FULL_CIRCLE_Q6).tolist(), distance.tolist(), strict=True)
    )
    assert nodes.broken.sum() == 1 and nodes.encoder_q6[np.flatnonzero(nodes.broken)[0]] == 6 * fmt.samples * 16


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=4000), st.integers(1, 900), st.sampled_from(FORMATS))
def test_random_bytes_never_raise(noise, chunk, fmt):
    decoder = rc.CapsuleNodeDecoder(fmt)
    for i in range(0, len(noise), chunk):
        out = decoder.feed(noise[i:i + chunk])
        assert np.all((out.angle_q6 >= 0) & (out.angle_q6 < rp.FULL_CIRCLE_Q6)) and np.all(out.distance_q2 >= 0)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 1000), st.sampled_from(MUTATIONS), st.integers(0, 255), st.integers(0, 2**32),
       st.sampled_from(FORMATS))
def test_one_mutation_never_yields_a_wrong_sample(seed, how, value, where, fmt):
    capsules, _, _ = encode_stream(fmt, 8, np.random.default_rng(seed))
    stream = bytearray(b"".join(capsules))
    original = rc.CapsuleNodeDecoder(fmt).feed(bytes(stream))
    mutate(stream, how, where, value)
    nodes = rc.CapsuleNodeDecoder(fmt).feed(bytes(stream))
    fields = ("encoder_q6", "angle_q6", "distance_q2", "quality")
    assert set(zip(*(getattr(nodes, f).tolist() for f in fields), strict=True)) <= set(
        zip(*(getattr(original, f).tolist() for f in fields), strict=True)
    )
