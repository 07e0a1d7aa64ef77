"""Sensor clock: TM round-trip offset, 24-bit unwrap, reboot detection and drift, on synthetic timelines."""

from __future__ import annotations

import numpy as np
import pytest

from trundle.drivers.sensor_clock import SensorClock

MS = 1_000_000
T0 = 1_700_000_000 * 10**9  # host epoch of the synthetic run


def sensor_ms(true_ns: np.ndarray, boot_ns: int, drift_ppm: float = 0.0, start_ms: int = 0) -> np.ndarray:
    """Raw 24-bit readings of a clock booted at boot_ns that runs drift_ppm slow."""
    return (start_ms + np.floor((true_ns - boot_ns) / MS / (1 + drift_ppm * 1e-6)).astype(np.int64)) & 0xFFFFFF


def tm_samples(clock_true_ns: list[int], boot_ns: int, start_ms: int, drift_ppm: float = 0.0,
               rtt_ns: int = 2 * MS) -> list[tuple[int, int, int]]:
    return [(t - rtt_ns // 2, int(sensor_ms(np.array([t]), boot_ns, drift_ppm, start_ms)[0]), t + rtt_ns // 2)
            for t in clock_true_ns]


def test_round_trip_median_offset():
    boot = T0 - 5_000 * MS
    clock = SensorClock()
    samples = tm_samples([T0 + k * 3 * MS + 137_000 for k in range(10)], boot, 0)
    samples[3] = (samples[3][0] - 50 * MS, samples[3][1], samples[3][2] + 90 * MS)  # one slow round trip
    clock.synchronise(samples)
    reading = clock.update(int(sensor_ms(np.array([T0 + 100 * MS]), boot)[0]), T0 + 130 * MS)
    assert abs(reading.stamp_ns - (T0 + 100 * MS)) <= MS


def test_wrap_is_unwrapped_forwards():
    boot = T0
    start = 0xFFFFFF - 200  # clock 200 ms before the wrap
    clock = SensorClock()
    clock.synchronise(tm_samples([T0 + k * MS for k in range(5)], boot, start))
    true = T0 + 10 * MS + np.arange(40) * 25 * MS
    raws = sensor_ms(true, boot, 0.0, start)
    out = [clock.update(int(r), int(t) + 30 * MS) for r, t in zip(raws, true, strict=True)]
    assert sum(o.event == "wrap" for o in out) == 1 and clock.wraps == 1 and clock.resets == 0
    assert np.all(np.abs(np.array([o.stamp_ns for o in out]) - true) <= MS)
    assert np.all(np.diff([o.unwrapped for o in out]) == 25)
    assert out[-1].unwrapped > 0xFFFFFF


def test_reboot_is_detected_and_stamps_stay_continuous():
    boot = T0 - 3_000 * MS
    clock = SensorClock()
    clock.synchronise(tm_samples([T0 + k * MS for k in range(5)], boot, 0))
    true = T0 + 10 * MS + np.arange(80) * 25 * MS
    raws = sensor_ms(true, boot)
    reboot_at = 40
    raws[reboot_at:] = sensor_ms(true[reboot_at:], true[reboot_at] - 7 * MS)  # clock back to ~0
    rng = np.random.default_rng(0)
    latency = 30 * MS + rng.integers(0, 3 * MS, true.size)
    out = [clock.update(int(r), int(t + lat)) for r, t, lat in zip(raws, true, latency, strict=True)]
    assert [o.event for o in out].count("reset") == 1 and out[reboot_at].event == "reset"
    stamps = np.array([o.stamp_ns for o in out])
    assert np.all(np.diff(stamps) > 0)
    assert np.all(np.abs(stamps - true) <= 5 * MS)  # re-anchored on the median receive latency


def test_host_stall_is_not_a_reboot():
    boot = T0
    clock = SensorClock()
    clock.synchronise(tm_samples([T0 + k * MS for k in range(5)], boot, 1000))
    true = T0 + 10 * MS + np.arange(60) * 25 * MS
    rx = true + 30 * MS
    rx[20:30] = rx[30]  # the host read nothing for 250 ms, then got ten scans at once
    out = [clock.update(int(r), int(t)) for r, t in zip(sensor_ms(true, boot, 0.0, 1000), rx, strict=True)]
    assert clock.resets == 0 and clock.resyncs == 0
    assert np.all(np.abs(np.array([o.stamp_ns for o in out]) - true) <= MS)


@pytest.mark.parametrize("drift_ppm", [50.0, -80.0])
def test_drift_is_estimated_from_the_latency_envelope(drift_ppm):
    boot = T0 - 60_000 * MS
    clock = SensorClock()
    clock.synchronise(tm_samples([T0 + k * MS for k in range(10)], boot, 0, drift_ppm))
    true = T0 + np.arange(1, 10 * 60 * 20) * 50 * MS  # 20 Hz for 10 minutes
    raws = sensor_ms(true, boot, drift_ppm)
    rng = np.random.default_rng(1)
    latency = 20 * MS + rng.exponential(4 * MS, true.size).astype(np.int64)
    out = [clock.update(int(r), int(t + lat)) for r, t, lat in zip(raws, true, latency, strict=True)]
    assert clock.drift_ppm == pytest.approx(drift_ppm, abs=5.0)
    late = np.array([o.stamp_ns for o in out[-1000:]]) - true[-1000:]
    assert np.abs(late).max() <= 3 * MS  # without drift tracking the error would be 30-48 ms
    assert clock.resets == 0


def camera_run(seconds: float, drift_ppm: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A camera clock (epoch ns of another machine, 3.2 s ahead, ``drift_ppm`` slow) stamping frames at
    30 Hz: capture times on the host clock, the camera's stamps and the host receive times; every
    10th frame comes in the quickest 1 ms, the others up to 400 ms late (a busy host)."""
    true = T0 + np.arange(int(seconds * 30)) * 33_333_333
    device = true + 3_200 * MS - ((true - T0) * drift_ppm * 1e-6).astype(np.int64)
    rng = np.random.default_rng(seed)
    late = rng.exponential(20 * MS, true.size).astype(np.int64).clip(0, 400 * MS)
    late[::10] = 0
    late[0] = 40 * MS  # the first frame, the anchor, came late
    return true, device, true + MS + late


def test_envelope_offset_follows_the_quickest_delivery_never_the_late_ones():
    true, device, received = camera_run(20.0, 0.0, 1)
    clock = SensorClock(bits=64, tick_ns=1, bin_ticks=10**9, resync_after_ticks=5 * 10**9, envelope=True)
    stamps = np.array([clock.update(int(d), int(r)).stamp_ns for d, r in zip(device, received, strict=True)])
    assert np.array_equal(stamps - true, np.minimum.accumulate(received - true))  # the smallest latency so far
    assert np.all(stamps <= received) and clock.resyncs == 0 and clock.resets == 0
    assert np.all(stamps[10:] - true[10:] == MS)


def test_envelope_drift_from_the_lower_envelope():
    true, device, received = camera_run(90.0, 200.0, 2)
    clock = SensorClock(bits=64, tick_ns=1, bin_ticks=10**9, resync_after_ticks=5 * 10**9, envelope=True)
    stamps = np.array([clock.update(int(d), int(r)).stamp_ns for d, r in zip(device, received, strict=True)])
    assert 190 < clock.drift_ppm < 210
    assert np.all(np.abs(stamps[-900:] - true[-900:] - MS) <= MS // 5)  # the last 30 s
