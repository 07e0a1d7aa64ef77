"""RPLIDAR driver against the emulated A1/A2 on a pty, one test per fault kind.

Each logged scan must be one whole revolution the emulator measured (ranges bit-equal, stamp
near the true time of beam 0), revolutions touched by a fault must be dropped and counted,
and the shutdown must stop the scan and then the motor.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from trundle.drivers import lrf
from trundle.drivers import rplidar as rp
from trundle.drivers.rplidar_driver import RplidarConfig, RplidarDriver, revolution_scan, Revolution
from trundle.logs import messages as m
from tests.lrf_harness import Recorder, inject, replug_delay_ns, running, wait_until
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import FaultPlan, parse_faults
from trundle.tools.emulators.pty_link import PtyLink
from trundle.tools.emulators.rplidar_emulator import FLAGS, KINDS, MODELS, RplidarDevice
from trundle.tools.emulators.scene import load_scene

PATIENT = {"timeout_s": 5.0, "error_limit": 50, "reply_timeout_s": 3.0}  # a busy test machine: no reconnects


def make(tmp_path, model="a1", mode="standard", faults=""):
    plan = parse_faults(faults, KINDS, FLAGS) if isinstance(faults, str) else faults
    device = RplidarDevice(MODELS[model], load_scene().range_source(MODELS[model].angles, seed=4), plan,
                           time.time_ns())
    server = DeviceServer(device, link_path=tmp_path / "lidar", backlog=1 << 24)  # keep all a starved driver misses
    sink = Recorder()
    beams = MODELS[model].samples * (2 if mode == "express" else 1)
    driver = lrf.driver_from_url(f"rplidar://{tmp_path / 'lidar'}?model={model}&mode={mode}&beams={beams}",
                                 sink, PATIENT)
    return device, server, driver, sink


def match(device: RplidarDevice, scans: list[m.LaserScan], stamps: bool = True) -> list:
    """The revolution behind every logged scan: the one whose ranges it equals bit for bit
    (range noise makes every revolution different), searched near the scan's time. It must be
    intact, and with ``stamps`` the scan's time must be right (times come from receipt: no
    device clock, and the emulator runs in this busy process)."""
    starts = np.array([r.start_ns for r in device.sent])
    matched, errors = [], []
    for scan in scans:
        n = scan.ranges.size
        first = scan.stamp_ns - int(scan.scan_time * 1e9 * (n - 1) / n)
        near = int(np.argmin(np.abs(starts - first)))
        found = [r for r in device.sent[max(near - 3, 0):near + 4] if np.array_equal(
            scan.ranges, np.where(r.distance_q2 == 0, np.inf, r.distance_q2 / 4000.0).astype(np.float32)[::-1])]
        assert len(found) == 1, "a logged scan is not a revolution the device measured"
        rev = found[0]
        assert set(rev.faults) <= {"stall"}, f"a revolution with {rev.faults} was logged"  # a stall only delays
        errors.append(first - rev.start_ns)
        matched.append(rev)
    if stamps and errors:  # on an idle machine within a millisecond; a starved emulator is late
        assert np.median(np.abs(errors)) <= scans[0].scan_time * 1e9
    return matched


def test_a1_standard_scan_and_shutdown(tmp_path):
    device, server, driver, sink = make(tmp_path, "a1")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 10, "10 revolutions")
    scans = sink.scans()
    match(device, scans)
    scan = scans[0]
    assert scan.ranges.size == 360 and scan.angle_max == pytest.approx(np.pi)
    assert scan.angle_min == pytest.approx(-np.pi + np.radians(1))
    assert scan.scan_time == pytest.approx(0.18) and scan.time_increment == pytest.approx(-0.0005)
    assert np.all(scan.intensities[np.isfinite(scan.ranges)] == 47)
    commands = [r.command for r in device.requests]
    assert commands[:2] == [rp.STOP, rp.GET_HEALTH] and rp.SCAN in commands and commands[-1] == rp.STOP
    assert rp.SET_MOTOR_PWM not in commands  # A1: DTR drives the motor, which a pty cannot carry
    assert driver.motor == "dtr" and driver.counters["modem_lines_unsupported"] == 2  # start and stop
    assert "model 0x18" in driver.hardware_id


def test_a2_express_scan_motor_on_pwm(tmp_path):
    device, server, driver, sink = make(tmp_path, "a2", "express")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 8, "8 revolutions")
    match(device, sink.scans())
    assert sink.scans()[0].intensities.size == 0
    requests = device.requests
    pwm = [int.from_bytes(r.payload, "little") for r in requests if r.command == rp.SET_MOTOR_PWM]
    assert pwm == [660, 0] and driver.motor == "pwm"
    stop = max(i for i, r in enumerate(requests) if r.command == rp.STOP)
    assert requests[stop + 1].command == rp.SET_MOTOR_PWM  # scan stopped first, then the motor
    assert device.pwm == 0


@pytest.mark.parametrize("mode", ["standard", "express"])
def test_corrupt_bytes_drop_exactly_the_revolutions_they_touch(tmp_path, mode):
    device, server, driver, sink = make(tmp_path, "a2", mode)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 2, "streaming")
        with server.lock:
            dropped = driver.counters["corrupt_revolutions"] + driver.counters["incomplete_revolutions"]
            first = len(device.sent)
            device.faults.rates = {"checksum": 0.3, "truncate": 0.3, "garbage": 0.3}
        wait_until(lambda: sum(device.injected.values()) >= 12, "12 faults")
        with server.lock:
            device.faults.clear()
            last = len(device.sent)
        # revolutions arrive in order: one logged after the faults stopped means all were read
        wait_until(lambda: match(device, sink.scans()[-1:], False)[0].index > device.sent[last - 1].index,
                   "the driver to catch up")
    faulted = sum(bool(r.faults) for r in device.sent[first:last])
    c = driver.counters
    assert c["corrupt_revolutions"] + c["incomplete_revolutions"] - dropped == faulted
    assert c["bad_capsules" if mode == "express" else "bad_nodes"] >= device.injected["checksum"]
    assert c["reconnects"] == server.dropped_bytes == 0
    match(device, sink.scans())


def test_sensor_left_scanning_is_stopped_and_flushed(tmp_path):
    device, server, driver, sink = make(tmp_path, "a1", faults="streaming")
    server.start()
    wait_until(lambda: len(device.sent) >= 3, "the stale scan")
    assert device.mode == "standard" and device.requests == []
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    # opening the port flushes what the pty held; whatever came after it and before STOP is drained
    assert device.requests[0].command == rp.STOP and driver.counters["stale_streams"] <= 1
    match(device, sink.scans())


def test_health_error_is_reset(tmp_path):
    device, server, driver, sink = make(tmp_path, "a2", faults="health_error")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    assert driver.counters["health_resets"] == 1
    commands = [r.command for r in device.requests]
    assert commands[:4] == [rp.STOP, rp.GET_HEALTH, rp.RESET, rp.GET_HEALTH]
    match(device, sink.scans())


def test_unplug_and_replug_recovers_within_two_seconds(tmp_path):
    device, server, driver, sink = make(tmp_path, "a2", faults=FaultPlan(unplug_s=0.4))
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
        assert replug_delay_ns(server, driver, sink) < 2e9
    assert driver.counters["reconnects"] == 1
    match(device, sink.scans())


def test_stall_holds_data_back_without_losing_or_mis_stamping_it(tmp_path):
    device, server, driver, sink = make(tmp_path, "a2", faults=FaultPlan(stall_s=0.35))
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
        inject(server, "stall")
        wait_until(lambda: device.injected["stall"] == 1, "the stall")
        before = driver.counters["scans"]
        wait_until(lambda: driver.counters["scans"] >= before + 8, "revolutions after the stall")
    c = driver.counters
    assert c["corrupt_revolutions"] == c["incomplete_revolutions"] == c["reconnects"] == 0
    match(device, sink.scans())  # the burst's samples are back-dated by the sample clock


def test_binning_by_hand():
    # 8 samples at 0, 45, ..., 315 deg (device frame); 4 beams: sectors centred on 0, 90, 180, 270
    angle = np.arange(8) * 45 * 64
    dist = np.array([4000, 8000, 0, 12000, 16000, 20000, 24000, 28000]) * 4
    rev = Revolution(angle, dist, np.full(8, 10), 1_000_000_000, 8_000_000)
    scan = revolution_scan(rev, 4, 0.15, 20.0, intensities=True)
    # beam i holds device sector 3 - i: 270, 180, 90, 0 deg -> ROS angles -pi/2, 0, pi/2, pi;
    # per sector the sample at its centre wins over those on its edges (45, 135, 225, 315 deg);
    # 270 deg: 24 m is beyond range_max (+inf), 90 deg: distance 0 is no return (+inf)
    assert scan.angle_min == pytest.approx(-np.pi / 2) and scan.angle_max == pytest.approx(np.pi)
    np.testing.assert_array_equal(scan.ranges, np.float32([np.inf, 16.0, np.inf, 4.0]))
    np.testing.assert_array_equal(scan.intensities, np.float32([10, 10, 10, 10]))
    assert scan.stamp_ns == 1_000_000_000 + 6_000_000 and scan.time_increment == pytest.approx(-0.002)


def test_rplidar_options_are_checked():
    sink = Recorder()
    driver = lrf.driver_from_url("rplidar:///dev/ttyUSB0?model=a2&mode=express", sink, {"beams": 720})
    assert isinstance(driver, RplidarDriver) and driver.config.limits == (115200, 0.15, 12.0)
    with pytest.raises(lrf.UserError, match="unknown RPLIDAR model"):
        lrf.driver_from_url("rplidar:///dev/ttyUSB0?model=z9", sink, {})
    with pytest.raises(lrf.UserError, match="mode"):
        RplidarConfig(port="/x", mode="turbo")


def test_silent_port_names_the_bauds_it_tried(tmp_path):
    with PtyLink(tmp_path / "quiet"):  # a serial port with nothing behind it
        driver = lrf.driver_from_url(f"rplidar://{tmp_path / 'quiet'}", Recorder(), {"reply_timeout_s": 0.1})
        driver.start()
        wait_until(lambda: driver.counters["errors"] >= 1, "a failed start")
        driver.stop()
    assert "no RPLIDAR answer" in driver.last_error and "115200, 256000, 460800, 1000000 baud" in driver.last_error
