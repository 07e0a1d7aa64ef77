"""RPLIDAR driver against the emulated models on a pty: every scan mode of every model, each
answer type with every fault kind, the motor and start-up paths.

Each logged scan must be one whole revolution the emulator measured (ranges bit-equal to that
revolution binned onto the scan's grid, stamp near the true time of its first sample),
revolutions touched by a fault must be dropped and counted, and the shutdown must stop the
scan and then the motor.
"""

from __future__ import annotations

import dataclasses
import struct
import time

import numpy as np
import pytest

from tests.lrf_harness import Recorder, inject, replug_delay_ns, running, wait_until
from trundle.drivers import lrf
from trundle.drivers import rplidar as rp
from trundle.drivers.rplidar_driver import Revolution, RplidarConfig, RplidarDriver, revolution_scan
from trundle.logs import messages as m
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import FaultPlan, parse_faults
from trundle.tools.emulators.pty_link import PtyLink
from trundle.tools.emulators.rplidar_emulator import (
    FLAGS,
    KINDS,
    MODELS,
    EmulatedMode,
    RplidarDevice,
    RplidarModel,
    SentRevolution,
)
from trundle.tools.emulators.scene import load_scene

PATIENT = {"timeout_s": 5.0, "error_limit": 50, "reply_timeout_s": 3.0}  # a busy test machine: no reconnects
ALL_MODES = [(name, mode.mode.name) for name, model in MODELS.items() for mode in model.modes]
# the answer types no current model streams (HQ frames, ultra-dense capsules), on an S2 that would
OTHER_TYPES = dataclasses.replace(MODELS["s2"], modes=(
    EmulatedMode(rp.ScanMode(0, "Standard", 100, 30.0, rp.ANS_MEASUREMENT), 960),
    EmulatedMode(rp.ScanMode(1, "UltraDense", 31.25, 30.0, rp.ANS_ULTRA_DENSE), 2880),
    EmulatedMode(rp.ScanMode(2, "HQ", 62.5, 30.0, rp.ANS_HQ), 1536)))


def make(tmp_path, model: str | RplidarModel = "a1", mode: str = "", faults: str | FaultPlan = "", **options):
    spec = MODELS[model] if isinstance(model, str) else model
    plan = parse_faults(faults, KINDS, FLAGS) if isinstance(faults, str) else faults
    device = RplidarDevice(spec, load_scene().range_source(spec.angles, seed=4), plan, time.time_ns())
    server = DeviceServer(device, link_path=tmp_path / "lidar", backlog=1 << 24)  # keep all a starved driver misses
    sink = Recorder()
    query = "&".join(f"{k}={v}" for k, v in (("model", model if isinstance(model, str) else ""), ("mode", mode)) if v)
    driver = lrf.driver_from_url(f"rplidar://{tmp_path / 'lidar'}?{query}", sink, {**PATIENT, **options})
    return device, server, driver, sink


def binned(rev: SentRevolution, driver: RplidarDriver) -> np.ndarray:
    """The ranges a scan of revolution ``rev`` must carry on the driver's grid."""
    return revolution_scan(Revolution(rev.angle_q6, rev.distance_q2, rev.quality, 0, 1), driver.beams,
                           *driver._limits).ranges


def match(device: RplidarDevice, driver: RplidarDriver, scans: list[m.LaserScan], stamps: bool = True) -> list:
    """The revolution behind every logged scan: the one whose binned ranges it equals bit for bit
    (range noise makes every revolution different), searched near the scan's time. It must be
    intact, and with ``stamps`` the scan's time must be right (times come from receipt: no
    device clock, and the emulator runs in this busy process)."""
    starts = np.array([r.start_ns for r in device.sent])
    matched, errors = [], []
    for scan in scans:
        n = scan.ranges.size
        first = scan.stamp_ns - int(scan.scan_time * 1e9 * (n - 1) / n)
        near = int(np.argmin(np.abs(starts - first)))
        found = [r for r in device.sent[max(near - 3, 0):near + 4]
                 if np.array_equal(scan.ranges, binned(r, driver), equal_nan=True)]
        assert len(found) == 1, "a logged scan is not a revolution the device measured"
        rev = found[0]
        assert set(rev.faults) <= {"stall"}, f"a revolution with {rev.faults} was logged"  # a stall only delays
        errors.append(first - rev.start_ns)
        matched.append(rev)
    if stamps and errors:  # on an idle machine within a millisecond; a starved emulator is late
        assert np.median(np.abs(errors)) <= scans[0].scan_time * 1e9
    return matched


def commands(device: RplidarDevice) -> list[int]:
    return [r.command for r in device.requests]


def test_a1_standard_scan_and_shutdown(tmp_path):
    device, server, driver, sink = make(tmp_path, "a1", "Standard")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 10, "10 revolutions")
    scans = sink.scans()
    match(device, driver, scans)
    scan = scans[0]
    assert scan.ranges.size == 360 and scan.angle_max == pytest.approx(np.pi)
    assert scan.angle_min == pytest.approx(-np.pi + np.radians(1))
    assert scan.scan_time == pytest.approx(360 * 508e-6) and scan.time_increment == pytest.approx(-508e-6)
    assert np.all(scan.intensities[np.isfinite(scan.ranges)] == 47)
    sent = commands(device)
    assert sent[:3] == [rp.STOP, rp.GET_HEALTH, rp.GET_INFO] and rp.SCAN in sent and sent[-1] == rp.STOP
    assert sent.count(rp.GET_LIDAR_CONF) == 2 + 4 * 5  # mode count, typical mode, four entries of five modes
    assert rp.SET_MOTOR_PWM not in sent  # A1: DTR drives the motor, which a pty cannot carry
    assert driver.motor == "dtr" and driver.counters["modem_lines_unsupported"] == 2  # start and stop
    assert "A1M8" in driver.hardware_id and "model 0x18" in driver.hardware_id
    values = dict(driver.diagnostics().values)
    assert values["scan_mode"] == "Standard" and "Sensitivity (0x84, 127 us, 12 m)" in values["scan_modes"]


@pytest.mark.parametrize("model, mode", ALL_MODES)
def test_every_scan_mode_of_every_model(tmp_path, model, mode):
    device, server, driver, sink = make(tmp_path, model, mode)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    spec = MODELS[model].mode(mode)
    assert driver.scan_mode == spec.mode and driver.beams == spec.samples
    scans = sink.scans()
    match(device, driver, scans)
    assert scans[0].range_max == pytest.approx(spec.mode.max_distance)
    assert scans[0].range_min == pytest.approx(MODELS[model].range_min)
    assert scans[0].scan_time == pytest.approx(spec.samples * spec.mode.us_per_sample * 1e-6)
    has_quality = spec.mode.answer_type in (rp.ANS_MEASUREMENT, rp.ANS_HQ, rp.ANS_ULTRA_DENSE)
    assert scans[0].intensities.size == (spec.samples if has_quality else 0)
    express = [r.payload for r in device.requests if r.command == rp.EXPRESS_SCAN]
    if spec.mode.answer_type == rp.ANS_MEASUREMENT:
        assert rp.SCAN in commands(device) and not express
    else:
        assert express == [struct.pack("<BHH", spec.mode.id, 0, 0)]  # the mode's id as working mode
    c = driver.counters
    assert c["corrupt_revolutions"] == c["incomplete_revolutions"] == c["bad_capsules"] == c["bad_nodes"] == 0


@pytest.mark.parametrize("model", MODELS)
def test_typical_mode_and_motor_control_of_each_model(tmp_path, model):
    device, server, driver, sink = make(tmp_path, model)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    spec = MODELS[model]
    assert driver.scan_mode == spec.modes[spec.typical].mode
    match(device, driver, sink.scans())
    sent = device.requests
    stop = max(i for i, r in enumerate(sent) if r.command == rp.STOP)
    pwm = [int.from_bytes(r.payload, "little") for r in sent if r.command == rp.SET_MOTOR_PWM]
    rpm = [int.from_bytes(r.payload, "little") for r in sent if r.command == rp.HQ_MOTOR_SPEED_CTRL]
    assert driver.motor == spec.motor
    if spec.motor == "pwm":  # the device's desired PWM (GET_LIDAR_CONF), after the scan stopped 0
        assert pwm == [spec.desired[1], 0] and sent[stop + 1].command == rp.SET_MOTOR_PWM and device.pwm == 0
    elif spec.motor == "rpm":
        assert rpm == [spec.desired[0], 0] and sent[stop + 1].command == rp.HQ_MOTOR_SPEED_CTRL and device.rpm == 0
    else:  # DTR (a pty has none: counted) or the C1's motor, which follows the scan
        assert not pwm and not rpm
        assert driver.counters["modem_lines_unsupported"] == (2 if spec.motor == "dtr" else 0)
    assert (rp.GET_ACC_BOARD_FLAG in commands(device)) == (spec.info.major_model in range(2, 6))


@pytest.mark.parametrize("model, mode", [("a2", "Standard"), ("a2", "Express"), ("a1", "Boost"),
                                         ("s2", "DenseBoost"), (OTHER_TYPES, "UltraDense"), (OTHER_TYPES, "HQ")],
                         ids=["legacy", "express", "ultra", "dense", "ultra-dense", "hq"])
def test_corrupt_bytes_drop_exactly_the_revolutions_they_touch(tmp_path, model, mode):
    device, server, driver, sink = make(tmp_path, model, mode)
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
        wait_until(lambda: match(device, driver, sink.scans()[-1:], False)[0].index > device.sent[last - 1].index,
                   "the driver to catch up")
    faulted = sum(bool(r.faults) for r in device.sent[first:last])
    c = driver.counters
    assert c["corrupt_revolutions"] + c["incomplete_revolutions"] - dropped == faulted
    legacy = device.format is None
    assert c["bad_nodes" if legacy else "bad_capsules"] >= device.injected["checksum"]
    assert c["bad_capsules" if legacy else "bad_nodes"] == 0
    assert c["reconnects"] == server.dropped_bytes == 0
    match(device, driver, sink.scans())


def test_sensor_left_scanning_is_stopped_and_flushed(tmp_path):
    device, server, driver, sink = make(tmp_path, "a1", "Standard", faults="streaming")
    server.start()
    wait_until(lambda: len(device.sent) >= 3, "the stale scan")
    assert device.mode == MODELS["a1"].standard and device.requests == []
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    # opening the port flushes what the pty held; whatever came after it and before STOP is drained
    assert device.requests[0].command == rp.STOP and driver.counters["stale_streams"] <= 1
    match(device, driver, sink.scans())


def test_health_error_is_reset(tmp_path):
    device, server, driver, sink = make(tmp_path, "a2", faults="health_error")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    assert driver.counters["health_resets"] == 1
    assert commands(device)[:4] == [rp.STOP, rp.GET_HEALTH, rp.RESET, rp.GET_HEALTH]
    match(device, driver, sink.scans())


def test_unplug_and_replug_recovers_within_two_seconds(tmp_path):
    device, server, driver, sink = make(tmp_path, "s2", faults=FaultPlan(unplug_s=0.4))
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
        assert replug_delay_ns(server, driver, sink) < 2e9
    assert driver.counters["reconnects"] == 1
    match(device, driver, sink.scans())


@pytest.mark.parametrize("mode", ["Standard", "Boost"])
def test_stall_holds_data_back_without_losing_or_mis_stamping_it(tmp_path, mode):
    device, server, driver, sink = make(tmp_path, "a2", mode, faults=FaultPlan(stall_s=0.35))
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
        inject(server, "stall")
        wait_until(lambda: device.injected["stall"] == 1, "the stall")
        before = driver.counters["scans"]
        wait_until(lambda: driver.counters["scans"] >= before + 8, "revolutions after the stall")
    c = driver.counters
    assert c["corrupt_revolutions"] == c["incomplete_revolutions"] == c["reconnects"] == 0
    match(device, driver, sink.scans())  # the burst's samples are back-dated by the sample clock


def test_firmware_without_scan_modes_gets_standard_and_express(tmp_path):
    """Before firmware 1.24 there is no GET_LIDAR_CONF: Standard and Express, timed by GET_SAMPLERATE,
    Express (the SDK's choice) started with working mode 0."""
    old = dataclasses.replace(MODELS["a2"], info=dataclasses.replace(MODELS["a2"].info, firmware=(1, 20)),
                              conf=False, modes=MODELS["a2"].modes[:2], typical=1)
    device, server, driver, sink = make(tmp_path, old)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "3 revolutions")
    assert rp.GET_LIDAR_CONF not in commands(device) and rp.GET_SAMPLERATE in commands(device)
    assert [mode.name for mode in driver.modes] == ["Standard", "Express"] and driver.scan_mode.name == "Express"
    assert driver.scan_mode.us_per_sample == 250 and driver.scan_mode.max_distance == 12.0
    assert [r.payload for r in device.requests if r.command == rp.EXPRESS_SCAN] == [bytes(5)]
    match(device, driver, sink.scans())


def test_a_mode_reported_without_sample_time_is_timed_by_get_samplerate(tmp_path):
    """S3 firmware 1.02 reports DenseBoost with 0 us per sample (Slamtec/rplidar_ros #155, where
    rplidar_ros crashed on it): the driver uses GET_SAMPLERATE's express figure."""
    s3 = MODELS["s3"]
    dense = s3.mode("DenseBoost")
    broken = dataclasses.replace(s3, modes=(s3.modes[0], EmulatedMode(dataclasses.replace(dense.mode, us_per_sample=0),
                                                                      dense.samples, true_us=31.25)))
    device, server, driver, sink = make(tmp_path, broken)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 revolutions")
    assert driver.scan_mode.name == "DenseBoost" and driver.scan_mode.us_per_sample == s3.samplerate[1]
    match(device, driver, sink.scans())


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
    driver = lrf.driver_from_url("rplidar:///dev/ttyUSB0?model=s2&mode=DenseBoost", sink, {"beams": 720})
    assert isinstance(driver, RplidarDriver) and driver.config.first_baud == 1000000
    assert driver.config.mode == "DenseBoost" and driver.config.beams == 720
    assert RplidarConfig(port="/x").first_baud == 115200 and RplidarConfig(port="/x", model="c1").first_baud == 460800
    with pytest.raises(lrf.UserError, match="unknown RPLIDAR model"):
        lrf.driver_from_url("rplidar:///dev/ttyUSB0?model=z9", sink, {})
    with pytest.raises(lrf.UserError, match=r"^lrf\.beams = 4: expected 0 \(one per sample\) or 8-23040$"):
        lrf.driver_from_url("rplidar:///dev/ttyUSB0", sink, {"beams": 4})
    with pytest.raises(lrf.UserError, match=r"^lrf\.motor_pwm = '2000': expected a number <= 1023$"):
        lrf.driver_from_url("rplidar:///dev/ttyUSB0?motor_pwm=2000", sink, {})


def test_a_mode_the_device_lacks_is_named_with_the_ones_it_has(tmp_path):
    device, server, driver, sink = make(tmp_path, "c1", "Boost", reply_timeout_s=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["errors"] >= 1, "a failed start")
    assert "RPLIDAR C1M1 has no scan mode 'Boost'; it offers Standard, DenseBoost" in driver.last_error
    assert not sink.scans()


def test_a_named_model_that_is_another_is_counted(tmp_path):
    """The device's GET_INFO wins over the configured model (here found at the S2's baud rate)."""
    device, server, driver, sink = make(tmp_path, MODELS["s2"])
    driver = lrf.driver_from_url(f"rplidar://{tmp_path / 'lidar'}?model=a1", sink, PATIENT)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 2, "2 revolutions")
    assert driver.counters["model_mismatches"] == 1 and driver.motor == "rpm" and "S2M1" in driver.hardware_id
    match(device, driver, sink.scans())


def test_silent_port_names_the_bauds_it_tried(tmp_path):
    with PtyLink(tmp_path / "quiet"):  # a serial port with nothing behind it
        driver = lrf.driver_from_url(f"rplidar://{tmp_path / 'quiet'}", Recorder(), {"reply_timeout_s": 0.1})
        driver.start()
        wait_until(lambda: driver.counters["errors"] >= 1, "a failed start")
        driver.stop()
    assert "no RPLIDAR answer" in driver.last_error and "115200, 256000, 460800, 1000000 baud" in driver.last_error
