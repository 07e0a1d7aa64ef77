"""CAN wheel encoders end to end: emulated ODrive / CiA 406 / VESC-DBC nodes, through python-can's
real slcan driver on the pty adapter emulator and through the virtual bus, into /wheels and /odom;
faults: counter wrap, heartbeat loss, unplug/replug, bus errors, dropped frames."""

from __future__ import annotations

import math
import struct

import can
import numpy as np
import pytest

from tests.can_rig import RADIUS, assert_no_jump, can_rig
from trundle.drivers.can_bus import Received
from trundle.drivers.slcan import SlcanBus
from trundle.drivers.wheels import driver_from_url
from trundle.logs import messages as m
from trundle.logs.errors import UserError

# Stand still, then both wheels at 1 turn/s for 0.5 s (half a turn = pi rad), then stop.
STRAIGHT = "0:0,0;0.3:1,1;0.8:0,0"
HALF_TURN_DISTANCE = 0.5 * 2 * math.pi * RADIUS
PROTOCOLS = ["odrive", "cia406", "dbc"]


def assert_straight(rig) -> None:
    why = dict(rig.driver.diagnostics().values)
    assert rig.odometry.gaps == 0, why
    final = rig.last_good_wheels()
    first = next(s for s in rig.topic("/wheels") if np.isfinite(s.position).all())
    assert final.position - first.position == pytest.approx(rig.expected_angles(), abs=1e-5), why
    odom = rig.topic("/odom")[-1]
    # Exact kinematics are tested in test_odometry. Here each node sends on its own clock and the
    # pair is aligned on receive stamps, so at a speed step (or when the loaded test machine
    # stalls the reader) one wheel's reading can be a period or more older than the other's: the
    # heading wobbles by v * T / track. Tolerances catch a lost wheel, a wrong sign or scale.
    assert odom.x == pytest.approx(HALF_TURN_DISTANCE, rel=0.03)
    assert abs(odom.y) < 0.03 and abs(odom.theta) < 0.1
    assert odom.pose_covariance[0, 0] > 0
    tf = rig.topic("/tf")[-1].transforms[0]
    assert (tf.frame_id, tf.child_frame_id) == ("odom", "base_link")
    assert tf.translation[0] == pytest.approx(odom.x)


@pytest.mark.parametrize("transport", ["virtual", "slcan"])
@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_protocol_end_to_end(tmp_path, protocol, transport):
    with can_rig(tmp_path, protocol, transport, STRAIGHT) as rig:
        rig.wait_until_script_done()
        if transport == "slcan":
            assert isinstance(rig.driver.bus.bus, SlcanBus)
        counters = dict(rig.driver.counters)
        status = rig.driver.diagnostics()
    assert_straight(rig)
    assert counters.get("decode_errors", 0) == 0
    assert counters["errors"] == 0 and counters["reconnects"] == 0
    assert status.level == m.OK, status
    frames = rig.topic("/can/rx")
    assert len(frames) > 50 and all(isinstance(f, m.CanFrame) for f in frames)
    assert np.all(np.diff([s.stamp_ns for s in rig.topic("/wheels")]) >= 0)


@pytest.mark.parametrize(
    "protocol,node_options,config",
    [
        (
            "odrive",
            {"count_ms": 10, "count_offset": 2**31 - 2000},
            {"odrive": {"source": "counts", "counts_per_rev": 8192}},
        ),
        ("cia406", {"position_offset": 2**24 - 1000}, {}),
        ("dbc", {"counter_offset": 2**31 - 10}, {}),
    ],
)
def test_counters_wrap_without_a_jump(tmp_path, protocol, node_options, config):
    with can_rig(tmp_path, protocol, "virtual", STRAIGHT, node_options=node_options, config=config) as rig:
        rig.wait_until_script_done()
    assert_straight(rig)
    assert_no_jump(rig, 2 * math.pi * RADIUS)


def test_odrive_polled_counts_over_slcan(tmp_path):
    # cyclic count message off: the driver requests it by RTR, the emulated axis answers
    config = {"odrive": {"source": "counts", "counts_per_rev": 8192, "poll_hz": 100}}
    with can_rig(tmp_path, "odrive", "slcan", STRAIGHT, config=config) as rig:
        rig.wait_until_script_done()
        assert rig.adapter.stats["from_host"] > 50
    assert_straight(rig)


@pytest.mark.parametrize("protocol", ["odrive", "cia406"])
def test_heartbeat_loss_marks_wheel_stale_without_odometry_jump(tmp_path, protocol):
    script = "0:0.5,0.5"
    with can_rig(tmp_path, protocol, "virtual", script) as rig:
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 20)
        rig.nodes[1].heartbeat_enabled = False
        assert rig.wait_for(lambda: "right" in dict(rig.driver.diagnostics().values)["stale_wheels"])
        assert rig.driver.diagnostics().level == m.WARN
        assert rig.odometry.stale
        flagged = [d.status[0] for d in rig.topic("/diagnostics")]
        assert flagged and flagged[-1].level == m.WARN and flagged[-1].name == "odometry"
        stale_state = rig.topic("/wheels")[-1]
        assert math.isnan(stale_state.position[1]) and math.isfinite(stale_state.position[0])
        if protocol == "odrive":
            rig.nodes[1].heartbeat_enabled = True  # the ODrive comes back by itself
        # CiA 406: the driver resets the silent node; its boot-up makes the driver configure it again
        assert rig.wait_for(lambda: rig.odometry.gaps >= 1 and not rig.odometry.stale)
        n = len(rig.topic("/odom"))
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > n + 10)
        diag = dict(rig.driver.diagnostics().values)
    assert diag["stale_wheels"] == "none"
    assert int(diag[f"{protocol}.heartbeat_losses"]) >= 1
    if protocol == "cia406":
        assert int(diag["cia406.resets_sent"]) >= 1 and int(diag["cia406.configured"]) >= 3
    assert assert_no_jump(rig, math.pi * RADIUS) >= 1
    if rig.odometry.bridged:  # cumulative positions: the motion across the gap is kept, none lost
        # the distance rolled, step by step between the logged readings with every wheel valid (the
        # stale ones skipped, so the step across the gap is one): a step can go back a little where
        # the driver carried a wheel forward by a velocity estimated on a loaded machine's stamps
        good = np.array([s.position for s in rig.topic("/wheels") if np.isfinite(s.position).all()])
        rolled = np.abs(np.diff(good, axis=0).mean(axis=1)).sum() * RADIUS
        assert rig.odometry.distance_m == pytest.approx(rolled, rel=1e-9)
    else:  # the counter restarted (a reset CiA 406 node): the unseen motion is in the covariance
        assert covariance_jump_at_gap(rig) > 1e-4


def covariance_jump_at_gap(rig) -> float:
    """Growth of var(x) from the last odometry before a stale wheel to the first one after."""
    before = after = None
    stale = False
    for topic, msg, _ in rig.log:
        if topic == "/wheels" and before is not None and not np.isfinite(msg.position).all():
            stale = True
        elif topic == "/odom":
            if stale and before is not None:
                after = msg
                break
            before = msg
    return after.pose_covariance[0, 0] - before.pose_covariance[0, 0]


def test_dead_node_stays_stale_and_others_keep_publishing(tmp_path):
    with can_rig(tmp_path, "odrive", "virtual", "0:0.5,0.5") as rig:
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 5)
        rig.nodes[0].silent = True
        assert rig.wait_for(lambda: "left" in dict(rig.driver.diagnostics().values)["stale_wheels"])
        n = len(rig.topic("/wheels"))
        assert rig.wait_for(lambda: len(rig.topic("/wheels")) > n + 10)
        late = rig.topic("/wheels")[-5:]
    assert all(math.isnan(s.position[0]) and math.isfinite(s.position[1]) for s in late)
    assert rig.driver.counters["errors"] == 0


def test_unplug_and_replug_the_adapter(tmp_path):
    with can_rig(tmp_path, "odrive", "slcan", "0:0.5,0.5") as rig:
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 10)
        rig.adapter.unplug()
        assert rig.wait_for(lambda: rig.driver.counters["errors"] >= 2)  # the read, then reopening
        assert rig.driver.state in ("waiting", "connecting")
        assert "No such file" in rig.driver.last_error
        assert np.isnan(rig.topic("/wheels")[-1].position).all()
        rig.adapter.replug()
        assert rig.wait_for(lambda: rig.driver.counters["reconnects"] >= 1)
        n = len(rig.topic("/odom"))
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > n + 10)
        assert rig.driver.state == "streaming"
    assert rig.odometry.gaps >= 1
    assert assert_no_jump(rig, math.pi * RADIUS) >= 1


def test_bus_errors_and_bus_off_on_socketcan_style_error_frames(tmp_path):
    with can_rig(tmp_path, "odrive", "virtual", "0:0.5,0.5", config={"odrive": {"data_timeout_s": 0.25}}) as rig:
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 10)
        rig.runner.error_frames(3)
        rig.runner.error_frames(1, passive=True)
        rig.runner.bus_off(0.5)
        assert rig.wait_for(lambda: rig.driver.bus.counters["restarts"] == 1)
        n = len(rig.topic("/odom"))
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > n + 10)
        bus = dict(rig.driver.bus.counters)
        state = rig.driver.bus.state
    assert bus["error_frames"] == 6 and bus["bus_off"] == 1 and bus["error_warnings"] == 3
    assert bus["error_passive"] == 1 and state == "active"
    errors = [f for f in rig.topic("/can/rx") if f.is_error]
    assert len(errors) == 6  # logged raw, never decoded as data
    assert rig.odometry.gaps >= 1  # 0.5 s of silence > the 0.25 s data timeout
    assert assert_no_jump(rig, math.pi * RADIUS) >= 1


def test_slcan_bus_off_is_left_by_close_and_open(tmp_path):
    with can_rig(tmp_path, "odrive", "slcan", "0:0.5,0.5") as rig:
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 10)
        rig.adapter.raise_flags(0x04)
        assert rig.wait_for(lambda: rig.driver.bus.counters["error_warnings"] >= 1)
        rig.adapter.bus_off()
        assert rig.wait_for(lambda: rig.driver.bus.counters["restarts"] >= 1)
        n = len(rig.topic("/odom"))
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > n + 10)
        bus = dict(rig.driver.bus.counters)
    assert bus["bus_off"] >= 1 and rig.adapter.stats["dropped"] > 0
    assert rig.driver.counters["reconnects"] == 0  # recovered in place, no reopen of the port
    assert_no_jump(rig, math.pi * RADIUS)


def test_garbled_serial_lines_are_counted_and_dropped(tmp_path):
    with can_rig(tmp_path, "odrive", "slcan", STRAIGHT) as rig:
        for _ in range(5):
            rig.adapter.inject_noise()
        rig.wait_until_script_done()
    assert rig.driver.bus.counters["corrupt_frames"] >= 5
    assert rig.driver.counters["errors"] == 0 and rig.driver.counters["reconnects"] == 0
    assert_straight(rig)


def test_dropped_frames_do_not_corrupt_positions(tmp_path):
    with can_rig(tmp_path, "cia406", "virtual", STRAIGHT) as rig:
        rig.runner.drop_probability = 0.2
        rig.wait_until_script_done()
        dropped, sent = rig.runner.stats["dropped"], rig.runner.stats["sent"]
    assert dropped > 0.1 * (dropped + sent)
    assert_straight(rig)


def test_frames_read_in_a_burst_do_not_make_the_wheels_jump(tmp_path):
    # Positions without velocity (as CiA 406 sends them): the driver derives a velocity to carry
    # each wheel to the pair's instant. After a stall, frames 10 ms apart on the wire arrive
    # within microseconds; a difference over those stamps would be huge and throw the wheels.
    dbc = tmp_path / "wheels.dbc"
    dbc.write_text('VERSION ""\nBS_:\nBU_: M\n'
                   'BO_ 100 Left: 4 M\n SG_ Turns : 0|32@1- (1,0) [0|0] "" Vector__XXX\n'
                   'BO_ 101 Right: 4 M\n SG_ Turns : 0|32@1- (1,0) [0|0] "" Vector__XXX\n'
                   'SIG_VALTYPE_ 100 Turns : 1;\nSIG_VALTYPE_ 101 Turns : 1;\n')
    states = []
    driver = driver_from_url(
        "virtual://unused",
        lambda topic, msg, t: states.append(msg) if topic == "/wheels" else None,
        {"encoders": f"dbc:{dbc}", "dbc": {"signals": ["Left.Turns", "Right.Turns"]}},
    )
    driver.protocols[0].start(driver.bus, 0)
    frames = [
        (k * 10_000_000 + 5_000_000 * side, 100 + side, k * 0.01 + 0.005 * side) for k in range(60) for side in (0, 1)
    ]
    burst = [i for i, f in enumerate(frames) if 200_000_000 <= f[0] <= 300_000_000]  # L20..R29, L30
    for i, (wire_ns, can_id, turns) in enumerate(frames):
        host_ns = 300_000_000 + (i - burst[0]) * 10_000 if i in burst else wire_ns  # a 100 ms stall
        msg = can.Message(arbitration_id=can_id, data=struct.pack("<f", turns), is_extended_id=False)
        driver.handle(Received(msg, host_ns, None), host_ns)
    positions = np.array([s.position for s in states if np.isfinite(s.position).all()])
    # 0.01 turn per 10 ms frame: no step may exceed a few frames' worth
    assert len(positions) > 50 and np.max(np.abs(np.diff(positions, axis=0))) < 2 * math.pi * 0.03


def test_configuration_mistakes_are_one_line_user_errors():
    sink = lambda *a: None  # noqa: E731
    for url, config in [
        ("can0", {"encoders": "odrive:0,1"}),
        ("slcan:///dev/ttyACM0@12345", {"encoders": "odrive:0,1"}),
        ("virtual://x", {}),
        ("virtual://x", {"encoders": "canopen:1"}),
        ("virtual://x", {"encoders": "odrive:a,b"}),
        ("virtual://x", {"encoders": "odrive:0,99"}),
        ("virtual://x", {"encoders": "odrive:0,1", "wheels": ["a"]}),
        ("virtual://x", {"encoders": "odrive:0,1", "direction": [1, 2]}),
        ("virtual://x", {"encoders": "odrive:0,1", "odrive": {"firmware": "0.4"}}),
        ("virtual://x", {"encoders": "odrive:0,1", "odrive": {"bogus": 1}}),
        ("virtual://x", {"encoders": "cia406:5", "cia406": {"eds": "/nonexistent.eds"}}),
        ("virtual://x", {"encoders": "dbc:/nonexistent.dbc", "dbc": {"signals": ["A.b"]}}),
        ("virtual://x", {"encoders": "dbc:x.dbc"}),
    ]:
        with pytest.raises(UserError) as info:
            driver_from_url(url, sink, config)
        assert "\n" not in str(info.value)
