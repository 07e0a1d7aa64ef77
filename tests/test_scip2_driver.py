"""SCIP 2.0 driver against the emulated sensor on a pty (and TCP), one test per fault kind.

Every logged scan must be one the emulator meant to send (ranges bit-equal, stamp within
half a scan period of the true first-beam time) and the counters must match the faults
injected while the driver streamed.
"""

from __future__ import annotations

import time
from itertools import pairwise

import numpy as np
import pytest

from tests.lrf_harness import Recorder, inject, replug_delay_ns, running, wait_until
from trundle.drivers import lrf
from trundle.drivers.scip2_driver import ScipConfig, ScipDriver
from trundle.logs.errors import UserError
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import FaultPlan, parse_faults
from trundle.tools.emulators.pty_link import PtyLink
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import FLAGS, KINDS, MODELS, ScipDevice

PATIENT = {"timeout_s": 5.0, "error_limit": 50, "reply_timeout_s": 3.0}  # a busy test machine: no reconnects


def expected_ranges(model: str, distances: np.ndarray) -> np.ndarray:
    """REP 117 ranges from the notes' code tables (independent of the driver's code)."""
    p = MODELS[model].params
    out = distances / 1000.0
    for i, d in enumerate(distances):
        if d > p.dmax:
            out[i] = np.inf
        elif d < p.dmin:
            if model == "urg-04lx":
                out[i] = np.inf if d == 0 else np.nan
            else:
                out[i] = {1: np.inf, 2: -np.inf}.get(int(d), np.nan)
    return out.astype(np.float32)


def first_beam_ns(device: ScipDevice, start: int) -> int:
    p = device.params
    return int(round((start - (p.afrt - p.ares / 2)) / p.ares * device.period_ns))


def match(device: ScipDevice, sink: Recorder, start: int) -> list:
    """The sent scan behind every logged one, found by the raw timestamp the driver logs with it
    on /scan/timing: ranges must be bit-equal, nothing faulty logged, stamps the first beam's time."""
    with sink.lock:
        pairs = [(a[1], b[1]) for a, b in pairwise(sink.messages)
                 if a[0] == "/scan" and b[0] == "/scan/timing"]
    offset = first_beam_ns(device, start)
    matched, errors = [], []
    for scan, timing in pairs:
        raw = int(dict(timing.status[0].values)["raw_ms"])
        found = [s for s in device.sent if s.timestamp == raw and s.fault in ("", "garbage", "reboot")]
        assert found, "a logged scan is not an intact scan the sensor sent"
        want = min(found, key=lambda s: abs(s.rear_ns + offset - scan.stamp_ns))  # raw ms repeat after a reset
        np.testing.assert_array_equal(scan.ranges, expected_ranges(device.model.name, want.distances))
        matched.append(want)
        errors.append(scan.stamp_ns - offset - want.rear_ns)
    assert len(pairs) == len(sink.scans())
    if errors:  # TM-synchronised: the emulator shares this (busy) machine, so allow for its delays
        assert np.median(np.abs(errors)) <= 10e6, "stamps are not the first beam's host time"
    return matched


def make(tmp_path, model="utm-30lx", faults="", ranges_at=None, **options):
    plan = parse_faults(faults, KINDS, FLAGS) if isinstance(faults, str) else faults
    scene = load_scene()
    device = ScipDevice(MODELS[model], ranges_at or scene.range_source(MODELS[model].angles, seed=2), plan,
                        time.time_ns())
    server = DeviceServer(device, link_path=tmp_path / "lrf", backlog=1 << 24)  # a driver starved by a busy
    sink = Recorder()                                                           # machine must not lose data
    driver = ScipDriver(ScipConfig(port=str(tmp_path / "lrf"), **{**PATIENT, **options}), sink)
    return device, server, driver, sink


def test_clean_stream_equals_what_the_sensor_sent(tmp_path):
    device, server, driver, sink = make(tmp_path, "urg-04lx", yaw=0.5, x=0.1)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 12, "12 scans")
    scans = sink.scans()
    match(device, sink, 44)
    scan = scans[0]
    assert scan.frame_id == "laser" and scan.ranges.size == 682
    assert scan.angle_min == pytest.approx(np.radians(-119.53), abs=1e-4)
    assert scan.angle_max == pytest.approx(np.radians(119.88), abs=1e-4)
    assert scan.angle_increment == pytest.approx(2 * np.pi / 1024)
    assert scan.time_increment == pytest.approx(0.1 / 1024) and scan.scan_time == pytest.approx(0.1)
    assert (scan.range_min, scan.range_max) == (pytest.approx(0.02), pytest.approx(5.6))
    assert all(b.stamp_ns - a.stamp_ns == pytest.approx(1e8, abs=2e6) for a, b in pairwise(scans))
    (tf,) = driver.static_messages()[0][1].transforms
    assert (tf.frame_id, tf.child_frame_id, tf.translation[0], tf.yaw) == (
        "base_link",
        "laser",
        0.1,
        pytest.approx(0.5),
    )
    names = [c[:3] for c in device.commands]
    assert names[0] == b"QT" and names[-1] == b"QT"  # stopped at start-up and at shutdown
    assert [n for n in names if n in (b"PP", b"VV", b"II", b"TM0")] == [b"PP", b"VV", b"II", b"TM0"]
    assert names.count(b"TM1") == 10 and b"MD0" in names
    assert "H0614967" in driver.hardware_id
    assert dict(driver.diagnostics().values)["serial"] == "H0614967"
    assert len(sink.topic("/scan/timing")) == len(scans)
    assert driver.counters["errors"] == driver.counters["reconnects"] == 0


def test_rep117_ranges_and_window_from_a_range_callable(tmp_path):
    pattern = np.array([1.0, np.inf, -np.inf, np.nan, 0.01, 70.0, 12.3456])
    ranges_at = lambda t: np.resize(pattern, 1081)  # noqa: E731 - the world simulator's interface
    device, server, driver, sink = make(tmp_path, "utm-30lx", ranges_at=ranges_at, angle_min=-1.0, angle_max=1.0,
                                        cluster=1)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 scans")
    start = device.params.angle_step(-1.0)
    scan = sink.scans()[-1]
    steps = np.arange(start, device.params.angle_step(1.0) + 1)
    want = np.resize(pattern, 1081)[steps]
    assert scan.ranges.size == steps.size
    np.testing.assert_array_equal(scan.ranges[want == 1.0], 1.0)
    np.testing.assert_array_equal(scan.ranges[want == 12.3456], np.float32(12.346))
    assert np.all(np.isposinf(scan.ranges[np.isposinf(want) | (want == 70.0)]))  # no return, beyond DMAX
    assert np.all(np.isneginf(scan.ranges[np.isneginf(want) | (want == 0.01)]))  # too near (code 2)
    assert np.all(np.isnan(scan.ranges[np.isnan(want)]))  # measurement error (code 3)
    assert scan.angle_min == pytest.approx(device.params.step_angle(start))
    match(device, sink, start)


def test_line_faults_are_counted_exactly_and_never_logged(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", angle_min=-0.8, angle_max=0.8)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 3, "streaming")
        with server.lock:
            device.faults.rates = {"checksum": 0.1, "truncate": 0.1, "garbage": 0.1, "unstable": 0.06, "stall": 0.04}
            device.faults.stall_s = 0.1
        wait_until(lambda: sum(device.injected.values()) >= 40, "40 faults")
        with server.lock:
            device.faults.clear()
            last_rear = device.sent[-1].rear_ns
        # the stream is in order: a scan sent after the faults stopped means all of them were read
        wait_until(lambda: max(s.stamp_ns for s in sink.scans()) > last_rear + 2 * device.period_ns,
                   "the driver to catch up")
    c, f = driver.counters, device.injected
    assert (c["checksum_errors"], c["truncated"], c["resyncs"], c["unstable"]) == (
        f["checksum"], f["truncate"], f["garbage"], f["unstable"])
    assert 1 <= c["stalls"] <= f["stall"] and c["missed_scans"] >= c["stalls"]
    assert c["reconnects"] == c["errors"] == server.dropped_bytes == 0
    logged = match(device, sink, device.params.angle_step(-0.8))
    assert len(logged) == c["scans"]


def test_sensor_still_streaming_at_connect_is_stopped_and_drained(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults="streaming")
    server.start()
    # nobody reads: the pty fills up and the rest waits in the device (opening the port flushes the pty)
    wait_until(lambda: len(device.sent) >= 40, "the stale stream")
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 scans")
    assert driver.counters["stale_streams"] == 1 and driver.counters["drained_bytes"] > 0
    assert driver.counters["errors"] == 0   # a data line of the stale stream that ends in "QT" is not its echo
    logged = match(device, sink, 0)
    assert {s.session for s in logged} == {2}  # nothing of the old session's stream (string OLD)
    assert device.commands[0] == b"QT"


def test_24_bit_clock_wrap_is_unwrapped(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults="wrap=1.5", angle_min=-0.5, angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["clock_wraps"] == 1 and driver.counters["scans"] >= 70, "a wrap")
    scans = sink.scans()
    logged = match(device, sink, device.params.angle_step(-0.5))
    raws = [s.timestamp for s in logged]
    assert any(b < a for a, b in pairwise(raws))  # the raw clock did wrap under our eyes
    gaps = np.diff([s.stamp_ns for s in scans])
    assert np.all(gaps > 0) and np.all(np.abs(gaps - np.rint(gaps / 25e6) * 25e6) < 3e6)
    assert driver.counters["clock_resets"] == 0


def test_clock_reset_mid_stream_keeps_stamps_continuous(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", angle_min=-0.5, angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 40, "40 scans")
        inject(server, "reboot")
        wait_until(lambda: device.injected["reboot"] == 1 and driver.counters["scans"] >= 80, "scans after the reset")
    # the driver stops the stream, synchronises the clock again with TM and restarts; the scans
    # in between, stamped only from receive times, are not logged
    assert driver.counters["clock_resets"] == 1 and driver.counters["tm_syncs"] == 2
    assert driver.counters["reconnects"] == 0
    scans = sink.scans()
    match(device, sink, device.params.angle_step(-0.5))
    assert np.all(np.diff([s.stamp_ns for s in scans]) > 0)


def test_abnormal_status_reboots_the_sensor_and_recovers(tmp_path):
    plan = FaultPlan(reboot_s=0.3)
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults=plan, angle_min=-0.5, angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 10, "10 scans")
        inject(server, "abnormal")
        wait_until(lambda: driver.counters["reconnects"] >= 1 and driver.counters["scans"] >= 30, "recovery")
    assert driver.counters["abnormal"] == 1 and driver.counters["reboots"] == 1
    assert server.unplugs == 1  # the reboot dropped the link
    i = next(i for i, c in enumerate(device.commands) if c == b"RB")
    assert device.commands[i:i + 2] == [b"RB", b"RB"]
    assert "abnormal" in driver.last_error
    match(device, sink, device.params.angle_step(-0.5))


def test_abnormal_state_at_connect_is_rebooted(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", angle_min=-0.5, angle_max=0.5)
    device.abnormal = True
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 scans")
    assert driver.counters["reboots"] == 1 and driver.counters["abnormal"] == 1
    assert device.commands[:3] == [b"QT", b"RB", b"RB"]


def test_time_adjust_mode_and_scip11_at_connect(tmp_path):
    device, server, driver, sink = make(tmp_path, "urg-04lx")
    device.tm = True
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 2, "2 scans")
    assert device.commands[:3] == [b"QT", b"TM2", b"QT"]
    device, server, driver, sink = make(tmp_path, "urg-04lx")
    device.scip1 = True
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 2, "2 scans")
    assert device.commands[:3] == [b"QT", b"SCIP2.0", b"QT"]


def test_unplug_and_replug_recovers_within_two_seconds(tmp_path):
    plan = FaultPlan(unplug_s=0.4)
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults=plan, angle_min=-0.5, angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 10, "10 scans")
        assert replug_delay_ns(server, driver, sink) < 2e9
    assert driver.counters["reconnects"] == 1
    match(device, sink, device.params.angle_step(-0.5))


def test_long_stall_times_out_and_reconnects(tmp_path):
    plan = FaultPlan(stall_s=1.5)
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults=plan, timeout_s=0.6, angle_min=-0.5,
                                        angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 10, "10 scans")
        inject(server, "stall")
        wait_until(lambda: driver.counters["timeouts"] >= 1 and driver.counters["reconnects"] >= 1, "a timeout")
        before = driver.counters["scans"]
        wait_until(lambda: driver.counters["scans"] >= before + 10, "scans after the stall")
    assert driver.counters["timeouts"] == 1
    match(device, sink, device.params.angle_step(-0.5))


def test_consecutive_bad_scans_force_a_reconnect(tmp_path):
    device, server, driver, sink = make(tmp_path, "utm-30lx", faults="checksum=1", error_limit=4, timeout_s=5.0,
                                        angle_min=-0.5, angle_max=0.5)
    with running(server, driver):
        wait_until(lambda: driver.counters["reconnects"] >= 2, "two reconnects")
    assert sink.scans() == [] and "4 bad scans in a row" in driver.last_error
    assert driver.counters["checksum_errors"] >= 8


def test_unavailable_intensity_mode_fails_loudly(tmp_path):
    device, server, driver, sink = make(tmp_path, "urg-04lx", intensity=True)
    with running(server, driver):
        wait_until(lambda: "intensities" in driver.last_error, "the refusal")
    assert "refused intensities (ME)" in driver.last_error and sink.scans() == []


def test_ethernet_model_over_tcp_with_intensities():
    model = MODELS["ust-10lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles, seed=3), now_ns=time.time_ns())
    server = DeviceServer(device, tcp_port=0)
    sink = Recorder()
    driver = lrf.driver_from_url(f"scip2+tcp://127.0.0.1:{server.port}?intensity=true&timeout_s=5", sink, {})
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 scans")
    logged = match(device, sink, 0)
    for scan, want in zip(sink.scans(), logged, strict=True):
        np.testing.assert_array_equal(scan.intensities, want.intensities.astype(np.float32))


def test_driver_from_url_rejects_mistakes():
    sink = Recorder()
    for url in ("sick:///dev/ttyUSB0", "scip2://", "scip2+tcp:///x", "scip2+tcp://host:99999"):
        with pytest.raises(UserError):
            lrf.driver_from_url(url, sink, {})
    with pytest.raises(UserError, match=r"unknown key lrf\.colour \(known in \[lrf\]: angle_max, "):
        lrf.driver_from_url("scip2:///dev/ttyACM0", sink, {"colour": "red"})
    with pytest.raises(UserError, match="cluster"):
        lrf.driver_from_url("scip2:///dev/ttyACM0?cluster=0", sink, {})
    driver = lrf.driver_from_url("scip2:///dev/ttyACM0", sink, {"url": "x", "intensity": True, "yaw": 1})
    assert driver.config.port == "/dev/ttyACM0" and driver.config.intensity and driver.config.yaw == 1.0
    assert lrf.driver_from_url("scip2+tcp://10.0.0.2", sink).config.port == "socket://10.0.0.2:10940"


def test_absent_sensor_keeps_retrying_without_crashing(tmp_path):
    sink = Recorder()
    driver = ScipDriver(ScipConfig(port=str(tmp_path / "nothing"), backoff_max_s=0.05), sink)
    driver.start()
    wait_until(lambda: driver.counters["errors"] >= 3, "three failed attempts")
    driver.stop()
    assert driver.state == "stopped" and "could not open port" in driver.last_error


def test_silent_port_names_the_bauds_it_tried(tmp_path):
    with PtyLink(tmp_path / "quiet"):  # a serial port with nothing behind it
        driver = lrf.driver_from_url(f"scip2://{tmp_path / 'quiet'}", Recorder(), {"reply_timeout_s": 0.1})
        driver.start()
        wait_until(lambda: driver.counters["errors"] >= 1, "a failed start")
        driver.stop()
    assert "no SCIP answer" in driver.last_error and "115200, 19200, 38400 baud" in driver.last_error


def test_ethernet_link_drop_reconnects_to_the_same_port():
    model = MODELS["ust-10lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles, seed=5), FaultPlan(unplug_s=0.4),
                        time.time_ns())
    server = DeviceServer(device, tcp_port=0)
    sink = Recorder()
    driver = lrf.driver_from_url(f"scip2+tcp://127.0.0.1:{server.port}", sink, {**PATIENT, "angle_max": 0.5})
    with running(server, driver):
        wait_until(lambda: driver.counters["scans"] >= 5, "5 scans")
        assert replug_delay_ns(server, driver, sink) < 2e9
    assert driver.counters["reconnects"] == 1 and server.unplugs == 1
    match(device, sink, 0)
