"""Thousands of injected faults per protocol, emulator bytes straight into the drivers' stream stages.

No I/O and no wall clock: the emulated devices run on synthetic time and their output is cut
into random chunks, so every count below is exact. Each logged scan must equal what the
emulator meant to send, and the drivers' counters must match the faults the emulator injected.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.lrf_harness import MUTATIONS, mutate
from tests.test_rplidar_driver import OTHER_TYPES
from trundle.drivers import rplidar as rp
from trundle.drivers import rplidar_capsules as rc
from trundle.drivers.rplidar_driver import Revolution, RevolutionAssembler, revolution_scan
from trundle.drivers.scip2 import Measure
from trundle.drivers.scip2_driver import ScipScanStream
from trundle.drivers.sensor_clock import SensorClock
from trundle.tools.emulators import rplidar_emulator, scip2_emulator
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.scene import load_scene

MS = 1_000_000
T0 = 1_700_000_000 * 10**9


def chunks(data: bytes, rng: np.random.Generator, largest: int = 6000):
    i = 0
    while i < len(data):
        n = int(rng.integers(1, largest))
        yield data[i:i + n]
        i += n


def test_scip2_stream_survives_thousands_of_faults():
    model = scip2_emulator.MODELS["utm-30lx"]
    plan = FaultPlan({"checksum": 0.12, "truncate": 0.12, "garbage": 0.12, "unstable": 0.06, "stall": 0.04,
                      "reboot": 0.005}, stall_s=0.06, seed=7)
    scene = load_scene()
    device = scip2_emulator.ScipDevice(model, scene.range_source(model.angles, seed=1), plan, now_ns=T0)
    measure = Measure("MD", 360, 720, string="T1")
    assert device.receive(measure.encode(), T0) == b"MD0360072001000;T1\n00P\n\n"
    clock = SensorClock()
    clock.synchronise([(T0 + k * MS, device.sensor_ms(T0 + k * MS + MS // 2), T0 + (k + 1) * MS) for k in range(5)])
    stream = ScipScanStream(model.params, measure, clock)
    rng = np.random.default_rng(3)
    logged = []
    t = T0
    while sum(device.injected.values()) < 1100:
        t += 10 * MS
        for part in chunks(device.poll(t), rng):
            logged += stream.feed(part, t + 2 * MS)  # received 2 ms after it was sent
    sent = device.sent
    faults = device.injected
    assert sum(faults.values()) >= 1000 and min(faults.values()) >= 5
    counters = stream.counters
    assert counters["checksum_errors"] == faults["checksum"]
    assert counters["truncated"] == faults["truncate"]
    assert counters["resyncs"] == faults["garbage"]
    assert counters["unstable"] == faults["unstable"]
    # a stall is seen as a gap between two readable timestamps: stalls with no readable timestamp
    # between them make one gap, and a gap that ends in a clock reset cannot be measured
    gaps, missed, run = 0, 0, 0
    for s in sent:
        if s.fault in ("stall", "stalled"):
            run += 1
        elif s.fault != "unstable" and s.damaged not in ("status", "timestamp"):
            if run and s.fault != "reboot":
                gaps, missed = gaps + 1, missed + run
            run = 0
    assert faults["stall"] - 10 <= gaps <= faults["stall"]
    assert counters["stalls"] == gaps
    assert counters["missed_scans"] == missed
    assert counters["clock_resets"] == faults["reboot"]
    assert counters["format_errors"] == counters["status_errors"] == counters["abnormal"] == 0
    # every logged scan is one the device meant to send, in order, none lost that was sent intact
    intact = [s for s in sent if s.fault in ("", "garbage", "reboot")]
    if len(logged) == len(intact) - 1:  # the last one may still be in flight
        intact = intact[:-1]
    assert len(logged) == len(intact) == counters["scans"]
    first_beam = int(round((360 - (540 - 720)) / 1440 * device.period_ns))
    reset_seen = False
    for (scan, timing), want in zip(logged, intact, strict=True):
        assert timing.raw == want.timestamp
        np.testing.assert_array_equal(scan.ranges, stream.ranges(want.distances))
        reset_seen |= timing.event == "reset"
        # TM-synchronised: within the 1 ms tick. After a clock reset the offset can only be
        # re-anchored on receive times, so it is only as good as their jitter (polled every 10 ms here).
        tolerance = 15 * MS if reset_seen else 2 * MS
        assert abs(scan.stamp_ns - (want.rear_ns + first_beam)) <= tolerance


def rplidar_run(model: rplidar_emulator.RplidarModel, mode_name: str, rates: dict[str, float], revolutions: int,
                seed: int):
    device = rplidar_emulator.RplidarDevice(model, load_scene().range_source(model.angles, seed=seed),
                                            FaultPlan(rates, seed=seed), now_ns=T0)
    mode = model.mode(mode_name)
    device.receive(rp.request(rp.SET_MOTOR_PWM, (660).to_bytes(2, "little")), T0)
    fmt = rc.FORMATS.get(mode.mode.answer_type)
    start = rp.request(rp.EXPRESS_SCAN, bytes((mode.mode.id, 0, 0, 0, 0))) if fmt else rp.request(rp.SCAN)
    assert device.receive(start, T0) == (fmt.descriptor if fmt else rp.SCAN_DESCRIPTOR).encode()
    decoder = rc.CapsuleNodeDecoder(fmt) if fmt else rp.NodeDecoder()
    assembler = RevolutionAssembler(mode.sample_ns, lag_samples=fmt.hold * fmt.samples if fmt else 0)
    rng = np.random.default_rng(seed)
    out = []
    t = T0
    while len(device.sent) < revolutions:
        t += 7 * MS
        for part in chunks(device.poll(t), rng, 2000):
            out += assembler.feed(decoder.feed(part), t)
    return device, decoder, assembler, out


def check_rplidar(device, assembler, out):
    beams = device.n
    by_start = {rev.start_ns: rev for rev in device.sent}
    dropped = assembler.counters["corrupt_revolutions"] + assembler.counters["incomplete_revolutions"]
    closed = device.sent[1:1 + len(out) + dropped]  # the first one is partial; the last ones still open
    assert len(closed) <= len(device.sent) - 2
    assert len(out) == sum(not rev.faults for rev in closed)
    assert dropped == sum(bool(rev.faults) for rev in closed)
    for rev in out:
        want = by_start[min(by_start, key=lambda s: abs(s - rev.start_ns))]
        assert not want.faults and abs(rev.start_ns - want.start_ns) <= 8 * MS
        np.testing.assert_array_equal(rev.angle_q6, want.angle_q6)
        np.testing.assert_array_equal(rev.distance_q2, want.distance_q2)
        scan = revolution_scan(rev, beams, 0.15, 12.0)
        expected = revolution_scan(Revolution(want.angle_q6, want.distance_q2, want.quality, 0, 1), beams, 0.15, 12.0)
        np.testing.assert_array_equal(scan.ranges, expected.ranges)


def test_rplidar_standard_stream_survives_thousands_of_faults():
    device, decoder, assembler, out = rplidar_run(
        rplidar_emulator.MODELS["a2"], "Standard", {"checksum": 0.45, "truncate": 0.2, "garbage": 0.2}, 1300, seed=5)
    assert sum(device.injected.values()) >= 1000
    assert decoder.bad_nodes >= device.injected["checksum"]
    check_rplidar(device, assembler, out)


CAPSULE_MODES = [("a2", "Express"), ("a1", "Boost"), ("s2", "DenseBoost"), ("other", "UltraDense"), ("other", "HQ")]


@pytest.mark.parametrize("model, mode", CAPSULE_MODES, ids=[m for _, m in CAPSULE_MODES])
def test_rplidar_capsule_streams_survive_faults(model, mode):
    spec = OTHER_TYPES if model == "other" else rplidar_emulator.MODELS[model]
    device, decoder, assembler, out = rplidar_run(spec, mode, {"checksum": 0.4, "truncate": 0.2, "garbage": 0.2},
                                                  150, seed=6)
    assert sum(device.injected.values()) >= 100
    assert decoder.bad_capsules >= device.injected["checksum"]
    check_rplidar(device, assembler, out)


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=5000), st.sampled_from([None, *rc.FORMATS.values()]))
def test_rplidar_assembler_never_raises_on_noise(noise, fmt):
    decoder = rc.CapsuleNodeDecoder(fmt) if fmt else rp.NodeDecoder()
    assembler = RevolutionAssembler(500_000)
    for i in range(0, len(noise), 333):
        for rev in assembler.feed(decoder.feed(noise[i:i + 333]), T0 + i):
            revolution_scan(rev, 360, 0.15, 12.0)


@settings(max_examples=50, deadline=None)
@given(st.binary(max_size=8000))
def test_scip2_stream_never_raises_on_noise(noise):
    model = scip2_emulator.MODELS["urg-04lx"]
    measure = Measure("MD", 44, 725, string="T1")
    stream = ScipScanStream(model.params, measure, SensorClock())
    device = scip2_emulator.ScipDevice(model, now_ns=T0)
    device.receive(measure.encode(), T0)
    valid = device.poll(T0 + 10**9)
    cut = len(noise) // 2
    for i, part in enumerate((noise[:cut], valid, noise[cut:], valid)):
        stream.feed(part, T0 + i * MS)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(MUTATIONS), st.integers(0, 2**31), st.integers(0, 255)),
                max_size=12), st.integers(1, 700))
def test_rplidar_mutated_streams_never_raise(mutations, chunk):
    n = 360
    angle = np.tile(np.arange(n) * 64, 3)
    stream = bytearray(rp.encode_nodes(angle == 0, np.full(3 * n, 47), angle, np.arange(3 * n) * 4 + 400))
    for how, where, value in mutations:
        mutate(stream, how, where, value)
    decoder, assembler = rp.NodeDecoder(), RevolutionAssembler(500_000)
    for i in range(0, len(stream), chunk):
        for rev in assembler.feed(decoder.feed(bytes(stream[i:i + chunk])), T0 + i):
            scan = revolution_scan(rev, 360, 0.15, 12.0)
            assert scan.ranges.size == 360 and np.all(rev.angle_q6 < rp.FULL_CIRCLE_Q6)
