"""RPLIDAR codec against the protocol's byte examples: requests, descriptors, info, health,
the scan-mode configuration entries and legacy nodes (capsules: test_rplidar_capsules.py)."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers import rplidar as rp


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


def test_request_parser_round_trip():
    parser = rp.RequestParser()
    stream = rp.request(rp.STOP) + b"\x00" + rp.request(rp.SET_MOTOR_PWM, b"\x94\x02") + rp.request(rp.GET_INFO)
    assert parser.feed(stream[:4]) + parser.feed(stream[4:]) == [
        rp.Request(rp.STOP), rp.Request(rp.SET_MOTOR_PWM, b"\x94\x02"), rp.Request(rp.GET_INFO)]
    assert parser.bad_bytes == 1


def test_model_names_follow_the_sdk():
    # SDK 2.1 GetModelNameStringByModelID: A<major>M<minor>, C<major-3>, S<major-5>, T<major-8>, M<major-11>
    names = {0x18: "A1M8", 0x28: "A2M8", 0x2C: "A2M12", 0x31: "A3M1", 0x41: "C1M1", 0x61: "S1M1", 0x71: "S2M1",
             0x81: "S3M1", 0x91: "T1M1", 0xC1: "M1M1"}
    for model, name in names.items():
        assert rp.DeviceInfo(model, (1, 0), 0, bytes(16)).model_name == name
    # configuration entries: firmware 1.24+, and every new-design (C, S, ...) model whatever its firmware
    assert not rp.DeviceInfo(0x28, (1, 23), 5, bytes(16)).supports_conf
    assert rp.DeviceInfo(0x28, (1, 24), 5, bytes(16)).supports_conf
    assert rp.DeviceInfo(0x81, (1, 2), 18, bytes(16)).supports_conf


def test_configuration_entries_by_hand():
    # protocol: "LIDAR returns 64000 for Express scan mode, which means 250 microseconds" (Q8)
    assert rp.conf_request(rp.CONF_SCAN_MODE_COUNT) == bytes.fromhex("70 00 00 00")
    assert rp.conf_request(rp.CONF_SCAN_MODE_US_PER_SAMPLE, 3) == bytes.fromhex("71 00 00 00 03 00")
    request = rp.request(rp.GET_LIDAR_CONF, rp.conf_request(rp.CONF_SCAN_MODE_TYPICAL))
    assert request == bytes.fromhex("A5 84 04 7C 00 00 00") + bytes((0xA5 ^ 0x84 ^ 0x04 ^ 0x7C,))
    values = {rp.CONF_SCAN_MODE_US_PER_SAMPLE: struct.pack("<I", 64000),
              rp.CONF_SCAN_MODE_MAX_DISTANCE: struct.pack("<I", 12 * 256),
              rp.CONF_SCAN_MODE_ANS_TYPE: bytes((0x82,)), rp.CONF_SCAN_MODE_NAME: b"Express\0"}
    mode = rp.ScanMode.from_conf(1, values)
    assert mode == rp.ScanMode(1, "Express", 250.0, 12.0, 0x82)
    assert mode.conf_values() == values
    assert rp.ScanMode(1, "DenseBoost", 31.25, 30.0, 0x85).conf_values()[rp.CONF_SCAN_MODE_US_PER_SAMPLE] == \
        struct.pack("<I", 8000)
    assert rp.parse_conf(0x70, bytes.fromhex("70 00 00 00 05 00")) == b"\x05\x00"
    with pytest.raises(rp.RplidarError):
        rp.parse_conf(0x70, bytes.fromhex("71 00 00 00 05 00"))
    with pytest.raises(rp.RplidarError):
        rp.ScanMode.from_conf(0, {rp.CONF_SCAN_MODE_NAME: b"Standard\0"})


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 0xFFFF), st.text("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz", min_size=1, max_size=24),
       st.integers(1, 1 << 24), st.integers(1, 1 << 20), st.integers(0, 255))
def test_scan_mode_entries_round_trip(mode_id, name, us_q8, distance_q8, kind):
    mode = rp.ScanMode(mode_id, name, us_q8 / 256, distance_q8 / 256, kind)
    assert rp.ScanMode.from_conf(mode_id, mode.conf_values()) == mode


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=4000), st.integers(1, 500))
def test_random_bytes_never_raise(noise, chunk):
    nodes, reqs = rp.NodeDecoder(), rp.RequestParser()
    for i in range(0, len(noise), chunk):
        out = nodes.feed(noise[i:i + chunk])
        assert np.all(out.angle_q6 < rp.FULL_CIRCLE_Q6)
        reqs.feed(noise[i:i + chunk])
        try:
            rp.Descriptor.parse(noise[i:i + 7])
            rp.DeviceInfo.parse(noise[i:i + 20])
            rp.Health.parse(noise[i:i + 3])
            rp.parse_conf(rp.CONF_SCAN_MODE_NAME, noise[i:i + chunk])
        except rp.RplidarError:
            pass
