"""Third-party clients talk to our emulators: proof that they speak the real protocols.

hokuyolx (SCIP 2.0 over TCP), rplidar-roboticia (module ``rplidar``) and pyrplidar (RPLIDAR
on a pty) read scans that must match the scene the emulator looks at.
"""

from __future__ import annotations

import errno
import math
import time

import hokuyolx
import numpy as np
import pyrplidar
import pytest
import rplidar
import serial

from trundle.tools.emulators import rplidar_emulator, scip2_emulator
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.scene import load_scene

SCENE = load_scene()
EXACT = type(SCENE)(SCENE.segments, SCENE.pose, 0.0)  # the same room without range noise


def scene_mm(angles_rad: np.ndarray) -> np.ndarray:
    return np.round(EXACT.ranges(angles_rad) * 1000.0)


def test_hokuyolx_reads_the_scene_over_tcp():
    model = scip2_emulator.MODELS["ust-10lx"]
    device = scip2_emulator.ScipDevice(model, EXACT.range_source(model.angles), now_ns=time.time_ns())
    with DeviceServer(device, tcp_port=0) as server:
        # hokuyolx's own start-up order (time sync, PP, BM), with a shorter time sync than its default
        laser = hokuyolx.HokuyoLX(addr=("127.0.0.1", server.port), tsync=False, info=False, activate=False)
        try:
            laser.time_sync(N=3, dt=0.01)
            laser.update_info()
            laser.activate()
            assert (laser.model, laser.amin, laser.amax, laser.aforw, laser.ares) == ("UST-10LX", 0, 1080, 540, 1440)
            assert laser.laser_state()[0] == 3
            timestamp, dist = laser.get_dist()
            assert abs(timestamp - time.time() * 1000) < 1000  # hokuyolx's own TM-based conversion
            intens_ts, pairs = laser.get_intens()
            # hokuyolx reads until a reply ends and cannot split two replies read at once: one
            # scan in ten (skips=9) keeps a slow client from receiving two in one read
            scans = list(laser.iter_dist(scans=3, skips=9))
            version = laser.version()
        finally:
            laser.close()
    angles = laser.get_angles()
    want = scene_mm(angles)
    np.testing.assert_array_equal(dist, want)
    # hand-computed beams: ahead the far wall at x = 5 m; left the cabinet front at y = 2.9 m;
    # right the wall at y = -3 m; step 0 (-135 deg) meets y = -3 m at x = -3 m: 3 * sqrt(2) m
    assert (dist[540], dist[900], dist[180], dist[0]) == (5000, 2900, 3000, round(3000 * math.sqrt(2)))
    np.testing.assert_array_equal(pairs[:, 0], want)
    assert np.all(pairs[:, 1] > 0)
    assert [pending for _, _, pending in scans] == [2, 1, 0]
    for scan, _, _ in scans:
        np.testing.assert_array_equal(scan, want)
    assert version["SERI"] == "H1400001"
    assert [c[:2] for c in device.commands if c[:2] in (b"TM", b"MD", b"GD", b"GE")][:5] == [
        b"TM", b"TM", b"TM", b"TM", b"TM"]


@pytest.fixture
def pty_modem_lines(monkeypatch):
    """rplidar drives the motor with DTR; a pty has no modem lines (ENOTTY): ignore that, as
    lrf-protocols.md 3.1 describes for running this peer against a pty."""

    def tolerant(original):
        def call(self):
            try:
                original(self)
            except OSError as error:
                if error.errno not in (errno.ENOTTY, errno.EINVAL):
                    raise
        return call

    monkeypatch.setattr(serial.Serial, "_update_dtr_state", tolerant(serial.Serial._update_dtr_state))
    monkeypatch.setattr(serial.Serial, "_update_rts_state", tolerant(serial.Serial._update_rts_state))


def rplidar_expected_mm(angle_deg: np.ndarray, step_mm: float = 0.25) -> np.ndarray:
    """What the emulator should report at device angles: the scene seen at pi - angle, in steps of
    ``step_mm`` (legacy nodes carry 1/4 mm, express capsules whole mm), 0 when out of range."""
    mm = np.round(EXACT.ranges(math.pi - np.radians(angle_deg)) * 1000.0 / step_mm) * step_mm
    return np.where((mm >= 150) & (mm <= 12000), mm, 0.0)


def test_rplidar_roboticia_reads_the_scene_on_a_pty(tmp_path, pty_modem_lines):
    model = rplidar_emulator.MODELS["a2"]
    device = rplidar_emulator.RplidarDevice(model, EXACT.range_source(model.angles), now_ns=time.time_ns())
    with DeviceServer(device, link_path=tmp_path / "ttyUSB0"):
        lidar = rplidar.RPLidar(str(tmp_path / "ttyUSB0"))
        try:
            info = lidar.get_info()
            health = lidar.get_health()
            scans = []
            for scan in lidar.iter_scans(min_len=100):
                scans.append(scan)
                if len(scans) == 3:
                    break
            lidar.stop()
            lidar.stop_motor()
        finally:
            lidar.disconnect()
    assert info["model"] == 0x28 and info["firmware"] == (1, 27) and info["hardware"] == 5
    assert health == ("Good", 0)
    for i, scan in enumerate(scans):
        quality, angle, distance = (np.array(v) for v in zip(*scan, strict=True))
        assert np.all(quality == 47) and (i == 0 or len(scan) >= 150)  # the first may be a partial turn
        # every sample where the scene puts it (rplidar leaves out distance 0; when its reader
        # falls behind it restarts the scan, so a list may hold parts of two turns)
        np.testing.assert_array_equal(distance, rplidar_expected_mm(angle))
    pwm = [int.from_bytes(r.payload, "little") for r in device.requests if r.command == 0xF0]
    assert pwm[0] == 660 and pwm[-1] == 0 and device.pwm == 0 and device.mode is None


def test_pyrplidar_reads_standard_and_express_scans(tmp_path):
    model = rplidar_emulator.MODELS["a1"]
    device = rplidar_emulator.RplidarDevice(model, EXACT.range_source(model.angles), now_ns=time.time_ns())
    with DeviceServer(device, link_path=tmp_path / "ttyUSB0"):
        lidar = pyrplidar.PyRPlidar()
        lidar.connect(port=str(tmp_path / "ttyUSB0"), baudrate=115200, timeout=3)  # unpatched: dsrdtr=True
        try:
            info = lidar.get_info()
            health = lidar.get_health()
            rate = lidar.get_samplerate()
            standard = take_revolution(lidar.start_scan()())
            lidar.stop()
            time.sleep(0.05)
            lidar.lidar_serial._serial.reset_input_buffer()
            express = take_revolution(lidar.start_scan_express(0)())
            lidar.stop()
        finally:
            lidar.disconnect()
    assert (info.model, info.firmware_major, info.firmware_minor, info.hardware) == (0x18, 1, 29, 7)
    assert (health.status, health.error_code) == (0, 0)
    assert (rate.t_standard, rate.t_express) == (508, 254)
    # The SDK's capsule decoding (which pyrplidar ports) flags the sample just before the 360 deg
    # crossing as the first of a revolution, and pyrplidar's angle conversion rounds down by up to
    # 1/64 deg; legacy nodes carry their start flag and angle as sent.
    for revolution, device_angles, tolerance, step in ((standard, np.arange(360.0), 0.0, 0.25),
                                                       (express, np.roll(np.arange(720) * 0.5, 1), 1 / 32, 1.0)):
        angle = np.array([m.angle for m in revolution])
        distance = np.array([m.distance for m in revolution])
        assert len(revolution) == device_angles.size
        np.testing.assert_allclose(angle, device_angles, atol=tolerance)
        np.testing.assert_array_equal(distance, rplidar_expected_mm(device_angles, step))


def test_pyrplidar_lists_the_scan_modes_and_reads_ultra_capsules(tmp_path):
    """pyrplidar's GET_LIDAR_CONF client reads the emulated A1's mode table, and its port of the
    SDK's ultra-capsule decoder reads a Sensitivity revolution: the distances the emulator sent
    after its variable-bit-scale compression, at the angles after the optical compensation."""
    model = rplidar_emulator.MODELS["a1"]
    device = rplidar_emulator.RplidarDevice(model, EXACT.range_source(model.angles), now_ns=time.time_ns())
    with DeviceServer(device, link_path=tmp_path / "ttyUSB0"):
        lidar = pyrplidar.PyRPlidar()
        lidar.connect(port=str(tmp_path / "ttyUSB0"), baudrate=115200, timeout=3)
        try:
            modes = lidar.get_scan_modes()
            typical = lidar.get_scan_mode_typical()
            revolution = take_revolution(lidar.start_scan_express(3)())
            lidar.stop()
        finally:
            lidar.disconnect()
    table = [(m.name, m.us_per_sample / 256, m.max_distance / 256, m.ans_type) for m in modes]  # pyrplidar keeps Q8
    assert table == [(e.mode.name, e.mode.us_per_sample, e.mode.max_distance, e.mode.answer_type) for e in model.modes]
    assert typical == model.typical == 3
    distance = np.array([m.distance for m in revolution])
    angle = np.array([m.angle for m in revolution])
    assert len(revolution) == 1440
    sent = next(r for r in device.sent if np.array_equal(np.roll(r.distance_q2, 1) / 4.0, distance))
    np.testing.assert_allclose(angle, np.roll(sent.angle_q6, 1) / 64.0, atol=1 / 32)
    np.testing.assert_allclose(distance[distance > 0] / 1000, EXACT.ranges(math.pi - np.radians(
        np.roll(np.arange(1440) * 0.25, 1)))[distance > 0], atol=0.008)  # within the compression's step


def take_revolution(measurements) -> list:
    """Samples from one start flag to the next (pyrplidar yields them one by one)."""
    revolution: list = []
    started = False
    for measurement in measurements:
        if measurement.start_flag:
            if started:
                return revolution
            started = True
        if started:
            revolution.append(measurement)
    return revolution
