"""Test rig for the CAN wheel encoders: emulated nodes on a virtual bus or behind the SLCAN pty
emulator, the real wheels driver (python-can slcan / virtual) publishing into a list."""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import can
import numpy as np

from trundle.drivers.dbc_wheels import VESC_DBC
from trundle.drivers.wheels import WheelsDriver, driver_from_url
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry, OdometrySink, odometry_from_config
from trundle.logs import messages as m
from trundle.tools.emulators.can_nodes import (
    CanNodeRunner,
    EmulatedNode,
    VelocityScript,
    WheelMotion,
    cia406_nodes,
    odrive_nodes,
    vesc_nodes,
)
from trundle.tools.emulators.slcan_emulator import SlcanEmulator

RADIUS, TRACK = 0.1, 0.5
POLE_PAIRS = 7


def protocol_setup(protocol: str, node_options: dict[str, Any]) -> tuple[list[EmulatedNode], dict[str, Any]]:
    """Two emulated nodes (left, right) and the driver config that reads them. Timeouts are
    generous (3 s) so a starved test machine does not make wheels stale; fault tests that
    need the protocol's own timeouts pass them in ``config``."""
    if protocol == "odrive":
        return odrive_nodes([0, 1], **node_options), {
            "encoders": "odrive:0,1", "odrive": {"heartbeat_timeout_s": 3.0, "data_timeout_s": 3.0}}
    if protocol == "cia406":
        return cia406_nodes([5, 6], **node_options), {
            "encoders": "cia406:5,6", "cia406": {"heartbeat_timeout_factor": 30, "data_timeout_s": 3.0}}
    if protocol == "dbc":
        return vesc_nodes(VESC_DBC, [9, 10], pole_pairs=POLE_PAIRS, **node_options), {
            "encoders": f"dbc:{VESC_DBC}",
            "dbc": {"signals": ["VESC_Status5_id9.Tachometer", "VESC_Status5_id10.Tachometer"],
                    "velocity_signals": ["VESC_Status1_id9.ERPM", "VESC_Status1_id10.ERPM"],
                    "units_per_rev": 6 * POLE_PAIRS, "velocity_scale": 1 / (60 * POLE_PAIRS), "data_timeout_s": 3.0}}
    raise ValueError(protocol)


@dataclass
class Rig:
    driver: WheelsDriver
    runner: CanNodeRunner
    adapter: SlcanEmulator | None
    script: VelocityScript
    odometry: DiffDriveOdometry | None = None
    log: list[tuple[str, m.Message, int]] = field(default_factory=list)

    @property
    def nodes(self) -> list[EmulatedNode]:
        return self.runner.nodes

    def topic(self, name: str) -> list[m.Message]:
        return [msg for topic, msg, _ in list(self.log) if topic == name]

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.01)
        return predicate()

    def wait_until_script_done(self, settle_s: float = 0.3, timeout_s: float = 30.0) -> None:
        """Until the emulator is past the script's end and the driver has read all it was sent."""
        end = self.runner.motion.start_s + float(self.script.starts[-1]) + settle_s
        assert self.wait_for(lambda: self.runner.t >= end, timeout_s), "emulator did not reach the end of the script"
        # a stalled emulator can jump past the end in one tick: let every node send a few more frames
        after = self.runner.stats["sent"] + 4 * len(self.nodes)
        assert self.wait_for(lambda: self.runner.stats["sent"] >= after, timeout_s), "emulator stopped sending"
        sent = self.runner.stats["sent"]
        assert self.wait_for(lambda: self.driver.counters["frames"] >= sent, timeout_s), "driver did not catch up"

    def last_good_wheels(self) -> m.JointState:
        states = [s for s in self.topic("/wheels") if np.isfinite(s.position).all()]
        assert states, "no wheel state with every wheel valid"
        return states[-1]

    def expected_angles(self) -> np.ndarray:
        return 2 * math.pi * self.script.turns_at(float(self.script.starts[-1]))


@contextmanager
def can_rig(tmp_path: Path, protocol: str, transport: str, script: str, *, node_options: dict[str, Any] | None = None,
            config: dict[str, Any] | None = None) -> Iterator[Rig]:
    nodes, cfg = protocol_setup(protocol, dict(node_options or {}))
    cfg.update(wheel_radius_m=RADIUS, track_m=TRACK)
    for key, value in (config or {}).items():
        if isinstance(value, dict):
            cfg.setdefault(key, {}).update(value)
        else:
            cfg[key] = value
    adapter = None
    if transport == "slcan":
        adapter = SlcanEmulator(str(tmp_path / "ttyCAN0")).start()
        device_bus: can.BusABC = adapter.bus
        url = f"slcan://{tmp_path / 'ttyCAN0'}@500000"
    else:
        channel = f"rig-{uuid.uuid4().hex}"
        device_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        url = f"virtual://{channel}"
    velocity = VelocityScript.parse(script)
    runner = CanNodeRunner(device_bus, nodes, WheelMotion(velocity, start_s=math.inf), adapter=adapter)
    rig = Rig(None, runner, adapter, velocity, odometry_from_config(cfg))  # type: ignore[arg-type]
    sink = OdometrySink(lambda topic, msg, t: rig.log.append((topic, msg, t)), rig.odometry)
    rig.driver = driver_from_url(url, sink, cfg)
    rig.driver.backoff.initial_s = 0.05
    rig.driver.start()
    if transport == "virtual":  # the host bus must exist before the nodes talk
        assert rig.wait_for(lambda: rig.driver.state == "streaming", 2.0)
    runner.start()
    try:
        # the script's clock starts once the driver reports every wheel, so no motion is missed
        assert rig.wait_for(lambda: any(np.isfinite(s.position).all() for s in rig.topic("/wheels"))), \
            "the driver never reported all wheels"
        runner.motion = WheelMotion(velocity, start_s=runner.t)
        yield rig
    finally:
        runner.stop()
        rig.driver.stop()
        if adapter is not None:
            adapter.close()
        else:
            device_bus.shutdown()


def assert_no_jump(rig: Rig, speed_m_s: float) -> int:
    """Every odometry step is explained by the wheel speed over the time between the two stamps
    (a wrong unwrap moves by thousands of turns; frames read in a burst after a stall of the
    loaded test machine share nearly one receive stamp, hence the 0.5 s floor), across every
    stale period too: there the pose is held (the counter restarted) or moved by what the
    cumulative wheel positions say (the motion across the gap is kept). Returns how many stale
    periods were crossed."""
    odoms = rig.topic("/odom")
    for a, b in pairwise(odoms):
        step = math.hypot(b.x - a.x, b.y - a.y)
        assert step <= speed_m_s * max((b.stamp_ns - a.stamp_ns) * 1e-9, 0.5) + 0.005, (step, a, b)
    before, stale, crossed = None, False, 0
    for topic, msg, _ in list(rig.log):
        if topic == "/wheels" and before is not None and not np.isfinite(msg.position).all():
            stale = True
        elif topic == "/odom":
            if stale:
                crossed += 1
                stale = False
            before = msg
    return crossed
