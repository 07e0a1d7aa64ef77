"""RPLIDAR codec against the protocol's byte examples and the SDK's capsule arithmetic, plus fuzzing."""

from __future__ import annotations

import numpy as np
import pyrplidar_protocol
import pytest
from hypothesis import given, settings, strategies as st

from trundle.drivers import rplidar as rp
from tests.lrf_harness import MUTATIONS, mutate


def test_request_bytes_from_the_protocol_document():
    assert rp.request(rp.STOP) == bytes.fromhex("A5 25")
    assert rp.request(rp.RESET) == bytes.fromhex("A5 40")
    assert rp.request(rp.SCAN) == bytes.fromhex("A5 20")
    assert rp.request(rp.FORCE_SCAN) == bytes.fromhex("A5 21")
    assert rp.request(rp.GET_INFO) == bytes.fromhex("A5 50")
    assert rp.request(rp.GET_HEALTH) == bytes.fromhex("A5 52")
    assert rp.request(rp.SET_MOTOR_PWM, (660).to_bytes(2, "little")) == bytes.fromhex("A5 F0 02 94 02 C1")
    assert rp.request(rp.EXPRESS_SCAN, bytes(5)) == bytes.fromhex("A5 82 05 00 00 00 00 00 22")


def test_descriptors_from_the_protocol_document():
    assert rp.SCAN_DESCRIPTOR.encode() == bytes.fromhex("A5 5A 05 00 00 40 81")
    assert rp.INFO_DESCRIPTOR.encode() == bytes.fromhex("A5 5A 14 00 00 00 04")
    assert rp.HEALTH_DESCRIPTOR.encode() == bytes.fromhex("A5 5A 03 00 00 00 06")
    assert rp.EXPRESS_DESCRIPTOR.encode() == bytes.fromhex("A5 5A 54 00 00 40 82")
    assert rp.Descriptor.parse(bytes.fromhex("A5 5A 05 00 00 40 81")) == rp.Descriptor(5, rp.MULTIPLE, 0x81)
    with pytest.raises(rp.RplidarError):
        rp.Descriptor.parse(bytes.fromhex("A5 5B 05 00 00 40 81"))


def test_info_and_health_payloads():
    info = rp.DeviceInfo(0x18, (1, 29), 7, bytes(range(16)))
    raw = info.encode()
    assert raw[:4] == bytes((0x18, 29, 1, 7)) and rp.DeviceInfo.parse(raw) == info
    assert info.major_model == 1 and info.native_baudrate == 256000
    assert rp.DeviceInfo(0x28, (1, 27), 5, bytes(16)).native_baudrate == 115200
    assert rp.DeviceInfo(0x61, (1, 29), 18, bytes(16)).native_baudrate == 256000
    assert rp.Health(2, 0x0102).encode() == bytes((2, 0x02, 0x01))
    assert rp.Health.parse(bytes((1, 0x34, 0x12))) == rp.Health(1, 0x1234)


def test_node_examples_from_the_protocol_document():
    nodes = rp.NodeDecoder().feed(bytes.fromhex("BD 01 00 A0 0F BE 01 2D 4A 13"))
    assert nodes.start.tolist() == [True, False]
    assert nodes.quality.tolist() == [47, 47]
    assert (nodes.angle_q6 / 64).tolist() == [0.0, 90.0]
    assert (nodes.distance_q2 / 4).tolist() == [1000.0, 1234.5]
    assert rp.encode_nodes([True, False], [47, 47], [0, 90 * 64], [4000, 4938]) == bytes.fromhex(
        "BD 01 00 A0 0F BE 01 2D 4A 13")


def sample_stream(n: int, seed: int = 0) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(seed)
    angle = (np.arange(n) * 64) % rp.FULL_CIRCLE_Q6
    dist = rng.integers(0, 40000, n)
    return rp.encode_nodes(angle == 0, rng.integers(0, 64, n), angle, dist), dist


def test_node_decoder_resyncs_after_a_bad_check_bit():
    raw, dist = sample_stream(200)
    bad = bytearray(raw)
    bad[50 * 5 + 1] &= 0xFE  # clear node 50's check bit
    bad[120 * 5] |= 0x03  # make node 120's start bits equal
    decoder = rp.NodeDecoder()
    nodes = rp.Nodes.concat([decoder.feed(bytes(bad[i:i + 37])) for i in range(0, len(bad), 37)])
    expected = np.delete(dist, [50, 120])
    np.testing.assert_array_equal(nodes.distance_q2, expected)
    assert np.flatnonzero(nodes.broken).tolist() == [50, 119]
    assert decoder.bad_nodes == 2 and decoder.resyncs == 2


def test_node_decoder_skips_inserted_garbage():
    raw, dist = sample_stream(100, 3)
    decoder = rp.NodeDecoder()
    nodes = decoder.feed(raw[:150] + b"\x00\x00\x00" + raw[150:])
    # node 30 follows the garbage: it and everything after is recovered
    np.testing.assert_array_equal(nodes.distance_q2[-70:], dist[30:])
    assert decoder.bad_nodes == 1 and nodes.broken.sum() == 1


def random_capsule(rng: np.random.Generator, start_q6: int) -> bytes:
    return rp.encode_capsule(start_q6, rng.integers(0, 16000, 32) * 4, rng.integers(0, 16, 32))


def test_capsule_round_trip_and_checksum():
    rng = np.random.default_rng(5)
    dist = rng.integers(0, 16000, 32) * 4
    dth = rng.integers(0, 64, 32)
    raw = rp.encode_capsule(1234, dist, dth, new_scan=True)
    assert len(raw) == 84 and raw[0] >> 4 == 0xA and raw[1] >> 4 == 0x5
    (capsule,) = rp.CapsuleDecoder().feed(raw)
    assert capsule.start_angle_q6 == 1234 and capsule.new_scan
    np.testing.assert_array_equal(capsule.distance_q2, dist)
    np.testing.assert_array_equal(capsule.dtheta_q3, dth)


def test_capsule_angles_match_the_sdk_port_in_pyrplidar():
    rng = np.random.default_rng(11)
    for start, nxt in [(0, 2048), (22000, 1000), (100, 100 + 5 * 64), (23000, 40)]:
        first, second = random_capsule(rng, start), random_capsule(rng, nxt)
        a, b = rp.CapsuleDecoder().feed(first + second)
        angle, dist, sync = rp.capsule_nodes(a, b.start_angle_q6)
        nodes = pyrplidar_protocol.PyRPlidarScanCapsule._parse_capsule(
            pyrplidar_protocol.PyRPlidarScanCapsule(first), pyrplidar_protocol.PyRPlidarScanCapsule(second))
        assert dist.tolist() == [n.dist_mm_q2 for n in nodes]
        assert sync.astype(int).tolist() == [n.start_flag & 1 for n in nodes]
        # pyrplidar stores angle_q6 as (q6 << 8) // 90 (q14 of a quarter turn) and back
        assert [((int(q) << 8) // 90 * 90) >> 8 for q in angle] == [(n.angle_z_q14 * 90) >> 8 for n in nodes]


def test_capsule_sample_angles_by_hand():
    # start 10 deg, next capsule at 42 deg: 1 deg per sample; sample 3 with dtheta 1.5 deg (12 q3)
    dth = np.zeros(32, np.int64)
    dth[3] = 12
    a, b = rp.CapsuleDecoder().feed(rp.encode_capsule(640, np.full(32, 4000), dth) +
                                    rp.encode_capsule(42 * 64, np.full(32, 4000), np.zeros(32)))
    angle, _, _ = rp.capsule_nodes(a, b.start_angle_q6)
    assert angle[:5].tolist() == [640, 704, 768, 832 - 96, 896]


def test_capsule_decoder_resyncs_after_a_bad_checksum():
    rng = np.random.default_rng(2)
    caps = [random_capsule(rng, (i * 2048) % rp.FULL_CIRCLE_Q6) for i in range(10)]
    stream = bytearray(b"".join(caps))
    stream[4 * 84 + 40] ^= 0x10
    decoder = rp.CapsuleDecoder()
    out = decoder.feed(bytes(stream[:500])) + decoder.feed(bytes(stream[500:]))
    assert [c.start_angle_q6 for c in out] == [(i * 2048) % rp.FULL_CIRCLE_Q6 for i in range(10) if i != 4]
    assert [c.broken for c in out].index(True) == 4
    assert decoder.bad_capsules == 1


def test_request_parser_round_trip():
    parser = rp.RequestParser()
    stream = rp.request(rp.STOP) + b"\x00" + rp.request(rp.SET_MOTOR_PWM, b"\x94\x02") + rp.request(rp.GET_INFO)
    assert parser.feed(stream[:4]) + parser.feed(stream[4:]) == [
        rp.Request(rp.STOP), rp.Request(rp.SET_MOTOR_PWM, b"\x94\x02"), rp.Request(rp.GET_INFO)]
    assert parser.bad_bytes == 1


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=4000), st.integers(1, 500))
def test_random_bytes_never_raise(noise, chunk):
    nodes, caps, reqs = rp.NodeDecoder(), rp.CapsuleDecoder(), rp.RequestParser()
    for i in range(0, len(noise), chunk):
        out = nodes.feed(noise[i:i + chunk])
        assert np.all(out.angle_q6 < rp.FULL_CIRCLE_Q6)
        for capsule in caps.feed(noise[i:i + chunk]):
            rp.capsule_nodes(capsule, 0)
        reqs.feed(noise[i:i + chunk])


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 1000), st.sampled_from(MUTATIONS), st.integers(0, 255), st.integers(0, 2**32))
def test_one_mutation_never_yields_a_wrong_express_sample(seed, how, value, where):
    rng = np.random.default_rng(seed)
    stream = bytearray(b"".join(random_capsule(rng, (i * 2048) % rp.FULL_CIRCLE_Q6) for i in range(8)))
    original = rp.ExpressNodeDecoder().feed(bytes(stream))
    mutate(stream, how, where, value)
    nodes = rp.ExpressNodeDecoder().feed(bytes(stream))
    assert set(zip(nodes.angle_q6.tolist(), nodes.distance_q2.tolist())) <= set(
        zip(original.angle_q6.tolist(), original.distance_q2.tolist()))


def test_express_nodes_follow_the_capsules_and_mark_revolutions():
    n = 720  # 0.5 deg per sample, 32 samples per capsule: 16 deg per capsule
    rng = np.random.default_rng(4)
    dist = rng.integers(1, 16000, 3 * n) * 4
    stream = b"".join(rp.encode_capsule((i * 1024) % rp.FULL_CIRCLE_Q6, dist[32 * i:32 * i + 32], np.zeros(32))
                      for i in range(3 * n // 32))
    decoder = rp.ExpressNodeDecoder()
    nodes = decoder.feed(stream)
    assert len(nodes) == (3 * n // 32 - 2) * 32  # the last two capsules wait for their successors
    np.testing.assert_array_equal(nodes.angle_q6, (np.arange(len(nodes)) * 32) % rp.FULL_CIRCLE_Q6)
    np.testing.assert_array_equal(nodes.distance_q2, dist[:len(nodes)])
    assert np.flatnonzero(nodes.start).tolist() == [n, 2 * n]
