"""Wheel positions from ODrive axes over CAN Simple: cyclic encoder estimates (or polled
encoder counts), heartbeat and axis-error watch, and the firmware line of each axis.

The heartbeat's bytes 5..7 mean different things in firmware 0.5 (error flags: byte 6 is the
encoder error flag) and 0.6 (procedure result, trajectory-done flag): reading a 0.6 heartbeat
as 0.5 takes every axis in velocity control for a broken encoder. With ``firmware = "auto"``
(the default) each axis is asked for Get_Version (an RTR, which 0.6 answers and 0.5 does not);
until it is known, the heartbeat flags are not used against the positions.
"""

from __future__ import annotations

import math

import can

from trundle.drivers import odrive
from trundle.drivers.can_bus import CanBus
from trundle.drivers.encoder_protocol import EncoderProtocol, HeartbeatWatchdog, WheelReading

VERSION_REQUESTS = 3  # Get_Version RTRs sent to an axis before it is taken for 0.5 (no answer)
VERSION_RETRY_S = 0.3  # between two Get_Version requests
AXIS_STATES = {0: "undefined", 1: "idle", 2: "startup", 3: "full calibration", 4: "motor calibration",
               6: "index search", 7: "offset calibration", 8: "closed loop", 9: "lockin spin",
               10: "direction find", 11: "homing"}


class OdriveEncoders(EncoderProtocol):
    """ODrive axes ``node_ids`` (one per wheel, in the order of ``wheels``).

    Parameters
    ----------
    firmware : ``"auto"`` (detect each axis's line by Get_Version, recorded in the diagnostics),
        or ``"0.5"`` / ``"0.6"`` to pin the heartbeat layout (and send no Get_Version).
    source : ``"estimates"`` (0x009, position in turns, cyclic by default) or ``"counts"``
        (0x00A shadow count, exact integers; needs ``counts_per_rev`` and usually ``poll_hz``).
    poll_hz : if > 0, request the source message by RTR at this rate (for axes whose cyclic
        message is off).
    heartbeat_timeout_s : an axis is stale after this long without a heartbeat (0 = no watch;
        ODrive sends one every 100 ms by default).
    data_timeout_s : a wheel is stale after this long without a position.
    """

    name = "odrive"

    def __init__(self, node_ids: tuple[int, ...], wheels: tuple[int, ...], *, firmware: str = "auto",
                 source: str = "estimates", counts_per_rev: int | None = None, poll_hz: float = 0.0,
                 heartbeat_timeout_s: float = 0.35, data_timeout_s: float = 0.25) -> None:
        super().__init__(wheels)
        if len(node_ids) != len(wheels):
            raise ValueError("one ODrive node id per wheel")
        if firmware not in ("auto", *odrive.FIRMWARES):
            raise ValueError(f"ODrive firmware must be auto or one of {', '.join(odrive.FIRMWARES)}, got {firmware!r}")
        if source not in ("estimates", "counts"):
            raise ValueError(f"ODrive source must be estimates or counts, got {source!r}")
        if source == "counts" and not counts_per_rev:
            raise ValueError("ODrive source counts needs counts_per_rev (the encoder CPR)")
        for node in node_ids:
            odrive.arbitration_id(node, 0)
        self.node_ids = tuple(node_ids)
        self.firmware, self.source = firmware, source
        self.poll_period_ns = int(1e9 / poll_hz) if poll_hz > 0 else 0
        self._wheel_of = dict(zip(self.node_ids, wheels, strict=True))
        cpr = 1.0 if source == "estimates" else float(counts_per_rev)  # type: ignore[arg-type]
        self.counts_per_rev = {w: cpr for w in wheels}
        self._cmd = odrive.GET_ENCODER_ESTIMATES if source == "estimates" else odrive.GET_ENCODER_COUNT
        self.heartbeats = HeartbeatWatchdog(heartbeat_timeout_s)
        self.watch_heartbeat = heartbeat_timeout_s > 0
        self.data = HeartbeatWatchdog(data_timeout_s)
        self.last_heartbeat: dict[int, odrive.Heartbeat] = {}
        self.versions: dict[int, odrive.Version] = {}
        self.lines: dict[int, str] = {}  # node -> "0.5" / "0.6": the layout its heartbeat is read with
        self._version_asked: dict[int, tuple[int, int]] = {}  # node -> (requests sent, last request ns)
        self._vel_turns: dict[int, float] = {}
        self._bus: CanBus | None = None
        self._next_poll = 0

    def start(self, bus: CanBus, now_ns: int) -> None:
        self._bus = bus
        self.heartbeats.reset()
        self.data.reset()
        self.last_heartbeat.clear()
        self._version_asked.clear()
        self.lines = {} if self.firmware == "auto" else {n: self.firmware for n in self.node_ids}
        self._next_poll = now_ns

    def handle(self, msg: can.Message, now_ns: int) -> list[WheelReading]:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return []
        node, cmd = odrive.split_id(msg.arbitration_id)
        wheel = self._wheel_of.get(node)
        if wheel is None:
            return []
        if cmd == odrive.GET_VERSION:
            version = self.versions[node] = odrive.decode_version(msg.data)
            if self.firmware == "auto":
                self.lines[node] = version.line
            return []
        if cmd == odrive.HEARTBEAT:
            heartbeat = odrive.decode_heartbeat(msg.data, self.lines.get(node, "0.5"))
            previous = self.last_heartbeat.get(node)
            if heartbeat.axis_error and (previous is None or previous.axis_error != heartbeat.axis_error):
                self.counters["axis_errors"] += 1
            self.last_heartbeat[node] = heartbeat
            self.heartbeats.beat(node, now_ns)
            return []
        if cmd == odrive.GET_ENCODER_ESTIMATES:
            pos, vel = odrive.decode_encoder_estimates(msg.data)
            self._vel_turns[node] = vel
            if self.source == "estimates":
                self.data.beat(node, now_ns)
                return [WheelReading(wheel, pos, vel)]
            return []
        if cmd == odrive.GET_ENCODER_COUNT and self.source == "counts":
            shadow, _ = odrive.decode_encoder_count(msg.data)
            self.data.beat(node, now_ns)
            vel = self._vel_turns.get(node, math.nan) * self.counts_per_rev[wheel]
            return [WheelReading(wheel, shadow, vel, 2**32)]
        return []

    def _encoder_fault(self, node: int) -> bool:
        """0.5 firmware flags an encoder error in heartbeat byte 6: positions are not trusted."""
        heartbeat = self.last_heartbeat.get(node)
        return heartbeat is not None and self.lines.get(node) == "0.5" and bool(heartbeat.flags[1] & 1)

    def healthy_wheels(self, now_ns: int) -> set[int]:
        return {self._wheel_of[n] for n in self.node_ids
                if self.data.alive(n, now_ns) and not self._encoder_fault(n)
                and (not self.watch_heartbeat or self.heartbeats.alive(n, now_ns))}

    def poll(self, now_ns: int) -> None:
        lost = self.heartbeats.check(now_ns) if self.watch_heartbeat else set()
        self.counters["heartbeat_losses"] += len(lost)
        self.counters["data_losses"] += len(self.data.check(now_ns))
        if self._bus is None:
            return
        for node in self.node_ids:
            self._ask_version(node, now_ns)
        if self.poll_period_ns and now_ns >= self._next_poll:
            self._next_poll = now_ns + self.poll_period_ns
            for node in self.node_ids:
                self._request(node, self._cmd)

    def _request(self, node: int, cmd: int) -> None:
        assert self._bus is not None
        self._bus.send(can.Message(arbitration_id=odrive.arbitration_id(node, cmd), is_extended_id=False,
                                   is_remote_frame=True, dlc=8))

    def _ask_version(self, node: int, now_ns: int) -> None:
        """Get_Version by RTR to an axis that is heard but not yet answered; no answer after
        ``VERSION_REQUESTS`` tries means firmware 0.5 (which has no Get_Version)."""
        if self.firmware != "auto" or node in self.versions or node not in self.last_heartbeat:
            return
        sent, last_ns = self._version_asked.get(node, (0, 0))
        if now_ns - last_ns < VERSION_RETRY_S * 1e9:
            return
        if sent >= VERSION_REQUESTS:
            self.lines.setdefault(node, "0.5")
            return
        self._version_asked[node] = (sent + 1, now_ns)
        self._request(node, odrive.GET_VERSION)

    def firmware_of(self, node: int) -> str:
        """What is known of an axis's firmware, for the diagnostics."""
        version = self.versions.get(node)
        line = self.lines.get(node)
        if version is not None:
            how = f"{version.firmware_text} (Get_Version, hw {'.'.join(map(str, version.hardware))})"
            return how if self.firmware in ("auto", version.line) else f"{how}, but pinned to {self.firmware}"
        if line is None:
            return "detecting"
        return f"{line} ({'pinned' if self.firmware != 'auto' else 'no Get_Version answer'})"

    def silence_hint(self, seen_ids: set[int]) -> str:
        heard = {odrive.split_id(i)[0] for i in seen_ids if i <= 0x7FF}
        missing = [n for n in self.node_ids if n not in heard]
        if missing:
            return (f"no frames from ODrive node(s) {','.join(map(str, missing))}; ODrive node ids heard on the bus: "
                    f"{','.join(map(str, sorted(heard))) or 'none'} (check --encoders odrive:IDS)")
        faulty = [n for n in self.node_ids if self._encoder_fault(n)]
        if faulty:
            return (f"the heartbeat of node(s) {','.join(map(str, faulty))} flags an encoder error in the 0.5 layout; "
                    "for ODrive Pro/S1 (firmware 0.6) set [can.odrive] firmware = \"auto\" or \"0.6\"")
        silent = [n for n in self.node_ids if n not in self.data.last_ns]
        if silent:
            what = "encoder estimates (0x009)" if self.source == "estimates" else "encoder counts (0x00A)"
            return (f"node(s) {','.join(map(str, silent))} send no {what}: enable the cyclic message or set "
                    "[can.odrive] poll_hz")
        return ""

    def diagnostics(self) -> list[tuple[str, str]]:
        values = super().diagnostics()
        for node in self.node_ids:
            heartbeat = self.last_heartbeat.get(node)
            if heartbeat is None:
                values.append((f"odrive.{node}", "no heartbeat"))
            else:
                state = AXIS_STATES.get(heartbeat.axis_state, str(heartbeat.axis_state))
                values.append((f"odrive.{node}", f"{state}, axis_error=0x{heartbeat.axis_error:08X}"))
            values.append((f"odrive.{node}.firmware", self.firmware_of(node)))
        return values
