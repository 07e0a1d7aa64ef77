"""Emulated wheel-encoder nodes on a python-can bus: ODrive axes, CiA 406 encoders, DBC-described
controllers (a VESC, say), with wheels turned by a velocity script or a ``wheel_speeds_at(t_s)``
callable, and faults: dropped frames, error frames, bus-off, counter wrap, a node that stops
its heartbeat or goes silent.

The bus is whatever the devices would sit on: the device side of the SLCAN adapter emulator
(:class:`trundle.tools.emulators.slcan_emulator.AdapterBus`) or a python-can ``virtual`` bus. The CiA 406
node's object dictionary and SDO server are the ``canopen`` package's ``LocalNode``, loaded from
the same kind of EDS a real encoder ships with; its NMT state machine and heartbeat are modelled
here so faults can be injected.
"""

from __future__ import annotations

import random
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen
import cantools
import numpy as np
from canopen.sdo import SdoArray, SdoRecord, SdoVariable

from trundle.drivers import cia406, odrive
from trundle.drivers.can_bus import CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_PROT, CAN_ERR_RESTARTED
from trundle.logs.errors import UserError

if TYPE_CHECKING:
    from trundle.tools.emulators.slcan_emulator import SlcanEmulator

SpeedSource = Callable[[float], Sequence[float] | np.ndarray]
VERSION_0_6 = odrive.Version(protocol=2, hardware=(4, 4, 58), firmware=(0, 6, 10))  # an ODrive Pro, firmware 0.6.10


class VelocityScript:
    """Piecewise-constant motor speeds in turns/s per wheel, from ``"T:v0,v1;T:v0,v1;..."``
    (each segment starts at T seconds; before the first, the wheels stand still). Positions
    are the exact integral, so expected wheel angles and odometry can be computed by hand."""

    def __init__(self, segments: Sequence[tuple[float, Sequence[float]]]) -> None:
        if not segments:
            raise UserError("empty velocity script")
        starts = [float(t) for t, _ in segments]
        if starts != sorted(starts) or starts[0] < 0:
            raise UserError("velocity script times must start at >= 0 and increase")
        widths = {len(v) for _, v in segments}
        if len(widths) != 1:
            raise UserError("every velocity script segment needs one speed per wheel")
        self.starts = np.asarray(starts)
        self.speeds = np.asarray([list(map(float, v)) for _, v in segments])
        durations = np.diff(self.starts)
        self._turns_at_start = np.vstack((np.zeros(self.speeds.shape[1]),
                                          np.cumsum(self.speeds[:-1] * durations[:, None], axis=0)))

    @classmethod
    def parse(cls, text: str) -> VelocityScript:
        segments = []
        for part in filter(None, (p.strip() for p in text.split(";"))):
            start, sep, speeds = part.partition(":")
            try:
                if not sep:
                    raise ValueError
                segments.append((float(start), [float(v) for v in speeds.split(",")]))
            except ValueError:
                raise UserError(f"bad velocity script segment {part!r}: write T:v_left,v_right (turns/s)") from None
        return cls(segments)

    @property
    def wheels(self) -> int:
        return int(self.speeds.shape[1])

    def _segment(self, t: float) -> int:
        return int(np.searchsorted(self.starts, t, side="right")) - 1

    def speeds_at(self, t: float) -> np.ndarray:
        k = self._segment(t)
        return np.zeros(self.wheels) if k < 0 else self.speeds[k].copy()

    def turns_at(self, t: float) -> np.ndarray:
        k = self._segment(t)
        if k < 0:
            return np.zeros(self.wheels)
        return self._turns_at_start[k] + self.speeds[k] * (t - self.starts[k])


class WheelMotion:
    """Motor turns and speeds of the wheels over time: exact for a :class:`VelocityScript`,
    trapezoid-integrated per tick for a ``wheel_speeds_at(t_s)`` callable (the world simulator).
    The motion's clock starts at ``start_s`` on the emulator's clock (standing still before)."""

    def __init__(self, source: VelocityScript | SpeedSource, wheels: int | None = None, start_s: float = 0.0) -> None:
        self.source = source
        n = source.wheels if isinstance(source, VelocityScript) else wheels
        if not n:
            raise ValueError("give the wheel count for a speed callable")
        self.start_s = start_s
        self.turns = np.zeros(n)
        self.speeds = np.zeros(n)
        self._t = 0.0

    def advance(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if t < self.start_s:
            return self.turns, self.speeds  # still standing
        t -= self.start_s
        if isinstance(self.source, VelocityScript):
            self.turns, self.speeds = self.source.turns_at(t), self.source.speeds_at(t)
        else:
            speeds = np.asarray(self.source(t), dtype=np.float64)
            self.turns = self.turns + 0.5 * (self.speeds + speeds) * (t - self._t)
            self.speeds = speeds
        self._t = t
        return self.turns, self.speeds


class EmulatedNode:
    """A device on the bus turning wheel ``wheel``. ``silent`` = dead (no frames, no answers);
    ``heartbeat_enabled = False`` = alive but its heartbeat stopped."""

    def __init__(self, wheel: int) -> None:
        self.wheel = wheel
        self.silent = False
        self.heartbeat_enabled = True

    def cyclic(self, t: float, turns: float, speed: float) -> list[can.Message]:
        return []

    def on_frame(self, msg: can.Message, t: float, turns: float, speed: float) -> list[can.Message]:
        return []


class _Every:
    """A period timer: ``due(t)`` is True once per ``period_s`` (never if the period is 0)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.next = 0.0

    def due(self, t: float) -> bool:
        if self.period_s <= 0 or t < self.next:
            return False
        self.next = max(self.next + self.period_s, t)
        return True


def _std(can_id: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


class OdriveNode(EmulatedNode):
    """One ODrive axis speaking CAN Simple: heartbeat, encoder estimates (and optionally encoder
    counts) cyclically, RTR requests answered, state requests, clear errors and reboot obeyed.
    ``count_offset`` starts the i32 shadow count near its wrap; ``encoder_error`` raises the
    0.5 heartbeat's encoder error flag.

    ``firmware = "0.6"`` is an ODrive Pro / S1: it answers Get_Version (0x000, ``VERSION_0_6``)
    and its heartbeat carries procedure result and trajectory-done flag in bytes 5 and 6; in
    velocity control the trajectory is always "done", so byte 6 is 1 (where 0.5 keeps its
    encoder error flag). ``"0.5"`` has no Get_Version and ignores the request.
    """

    def __init__(self, node_id: int, wheel: int, *, firmware: str = "0.5", heartbeat_ms: int = 100,
                 encoder_ms: int = 10, count_ms: int = 0, cpr: int = 8192, count_offset: int = 0) -> None:
        super().__init__(wheel)
        odrive.arbitration_id(node_id, 0)
        self.node_id, self.firmware, self.cpr = node_id, firmware, cpr
        self.heartbeat = _Every(heartbeat_ms / 1000)
        self.estimates = _Every(encoder_ms / 1000)
        self.counts = _Every(count_ms / 1000)
        self.count_offset = count_offset
        self.turns_offset = 0.0
        self.axis_state = odrive.AXIS_STATE_CLOSED_LOOP_CONTROL
        self.axis_error = 0
        self.encoder_error = False

    def _payload(self, cmd: int, turns: float, speed: float) -> bytes | None:
        if cmd == odrive.HEARTBEAT:
            flags = (0, int(self.encoder_error), 0) if self.firmware == "0.5" else (0, 1, 0)  # 0.6: trajectory done
            return odrive.encode_heartbeat(odrive.Heartbeat(self.axis_error, self.axis_state, flags))
        if cmd == odrive.GET_VERSION:
            return None if self.firmware == "0.5" else odrive.encode_version(VERSION_0_6)
        if cmd == odrive.GET_ENCODER_ESTIMATES:
            return odrive.encode_encoder_estimates(turns + self.turns_offset, speed)
        if cmd == odrive.GET_ENCODER_COUNT:
            count = round((turns + self.turns_offset) * self.cpr) + self.count_offset
            shadow = (count + 2**31) % 2**32 - 2**31
            return odrive.encode_encoder_count(shadow, count % self.cpr)
        return None

    def cyclic(self, t: float, turns: float, speed: float) -> list[can.Message]:
        out = []
        for timer, cmd in ((self.heartbeat, odrive.HEARTBEAT), (self.estimates, odrive.GET_ENCODER_ESTIMATES),
                           (self.counts, odrive.GET_ENCODER_COUNT)):
            if timer.due(t) and (cmd != odrive.HEARTBEAT or self.heartbeat_enabled):
                payload = self._payload(cmd, turns, speed)
                assert payload is not None  # heartbeat, estimates and counts always have one
                out.append(_std(odrive.arbitration_id(self.node_id, cmd), payload))
        return out

    def on_frame(self, msg: can.Message, t: float, turns: float, speed: float) -> list[can.Message]:
        if msg.is_extended_id:
            return []
        node, cmd = odrive.split_id(msg.arbitration_id)
        if node != self.node_id:
            return []
        if msg.is_remote_frame:
            payload = self._payload(cmd, turns, speed)
            return [] if payload is None else [_std(msg.arbitration_id, payload)]
        if cmd == odrive.SET_AXIS_STATE and len(msg.data) >= 4:
            self.axis_state = odrive.decode_axis_state(msg.data)
        elif cmd == odrive.CLEAR_ERRORS:
            self.axis_error, self.encoder_error = 0, False
        elif cmd == odrive.REBOOT:
            self.turns_offset = -turns  # the position estimate restarts at zero
            self.axis_state = odrive.AXIS_STATE_IDLE
        return []


class Cia406Node(EmulatedNode):
    """A CiA 406 encoder: object dictionary and SDO server from ``canopen.LocalNode`` (EDS),
    NMT state machine, heartbeat per 0x1017, TPDO1 as configured in 0x1800/0x1A00 while
    operational. The position 0x6004 = turns * 0x6001 + ``position_offset``, modulo 0x6002.
    NMT reset (node or communication) restores the EDS defaults (a simplification: a real
    reset-communication keeps the application objects), sends boot-up and re-enables a stopped
    heartbeat, as a real device's reset would."""

    def __init__(
        self, node_id: int, wheel: int, *, eds: str | Path = cia406.DEFAULT_EDS, position_offset: int = 0
    ) -> None:
        super().__init__(wheel)
        self.node_id = node_id
        self.local = canopen.LocalNode(node_id, str(eds))
        # canopen's NmtSlave starts its own heartbeat thread when 0x1017 is written; this model
        # produces the heartbeat itself (from its own NMT state, and so it can be stopped).
        self.local._write_callbacks.remove(self.local.nmt.on_write)
        self.network = canopen.Network()
        self.network.add_node(self.local)
        self.position_offset = position_offset
        self.state = cia406.BOOT_UP
        self._turns = 0.0
        self.local.add_read_callback(self._read_position)
        self._heartbeat = _Every(0)
        self._tpdo = _Every(0)

    def attach(self, bus: can.BusABC) -> None:
        self.network.bus = bus

    def _get(self, index: int, sub: int | None = None) -> int:
        entry = self.local.sdo[index]
        if sub is not None:
            assert isinstance(entry, (SdoArray, SdoRecord)), f"0x{index:04X} has no sub-indices"
            entry = entry[sub]
        assert isinstance(entry, SdoVariable), f"0x{index:04X} is not a variable"
        return int(entry.raw)

    def position(self) -> int:
        units = self._get(cia406.UNITS_PER_REV)
        total = self._get(cia406.TOTAL_RANGE) or 2**32
        return (round(self._turns * units) + self.position_offset) % total

    def _read_position(self, index: int, subindex: int, od: object) -> int | None:
        return self.position() if index == cia406.POSITION_VALUE else None

    def _boot(self) -> list[can.Message]:
        self.local.data_store.clear()
        self.heartbeat_enabled = True
        self.state = cia406.PRE_OPERATIONAL
        self._heartbeat = _Every(0)
        return [_std(cia406.HEARTBEAT + self.node_id, bytes((cia406.BOOT_UP,)))]

    def cyclic(self, t: float, turns: float, speed: float) -> list[can.Message]:
        self._turns = turns
        if self.state == cia406.BOOT_UP:
            return self._boot()
        out = []
        period = self._get(cia406.HEARTBEAT_TIME) / 1000
        if period != self._heartbeat.period_s:
            self._heartbeat = _Every(period)
        if self._heartbeat.due(t) and self.heartbeat_enabled:
            out.append(_std(cia406.HEARTBEAT + self.node_id, bytes((self.state,))))
        if self.state == cia406.OPERATIONAL:
            cob_id = self._get(0x1800, 1)
            period = (self._get(0x1800, 5) or self._get(cia406.CYCLIC_TIMER)) / 1000
            if period != self._tpdo.period_s:
                self._tpdo = _Every(period)
            if self._tpdo.due(t) and not cob_id & 0x80000000:
                out.append(_std(cob_id & 0x7FF, self._tpdo_data()))
        return out

    def _tpdo_data(self) -> bytes:
        data = b""
        for sub in range(1, self._get(0x1A00, 0) + 1):
            entry = self._get(0x1A00, sub)
            index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            value = self.local.get_data(index, subindex)
            data += value[: bits // 8]
        return data

    def on_frame(self, msg: can.Message, t: float, turns: float, speed: float) -> list[can.Message]:
        self._turns = turns
        if msg.is_extended_id or msg.is_remote_frame:
            return []
        if msg.arbitration_id == cia406.NMT and len(msg.data) >= 2 and msg.data[1] in (0, self.node_id):
            command = msg.data[0]
            if command == cia406.NMT_START:
                self.state = cia406.OPERATIONAL
            elif command == cia406.NMT_STOP:
                self.state = cia406.STOPPED
            elif command == cia406.NMT_PRE_OPERATIONAL:
                self.state = cia406.PRE_OPERATIONAL
            elif command in (cia406.NMT_RESET_NODE, cia406.NMT_RESET_COMMUNICATION):
                return self._boot()
        elif msg.arbitration_id == cia406.SDO_RX + self.node_id and self.state != cia406.STOPPED:
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)  # replies via the bus
        return []


class DbcNode(EmulatedNode):
    """A controller described by a DBC: sends the message holding its position signal (and its
    velocity signal) every ``period_ms``, encoded by cantools. Position raw value =
    turns * ``units_per_rev`` + ``counter_offset``, wrapped at the signal's width."""

    def __init__(self, dbc: str | Path | cantools.database.Database, wheel: int, position_signal: str, *,
                 velocity_signal: str | None = None, units_per_rev: float = 1.0, velocity_per_turn_s: float = 1.0,
                 period_ms: int = 20, counter_offset: int = 0) -> None:
        super().__init__(wheel)
        self.db = dbc if isinstance(dbc, cantools.database.Database) else _can_database(dbc)
        self.position = self._lookup(position_signal)
        self.velocity = self._lookup(velocity_signal) if velocity_signal else None
        self.units_per_rev, self.velocity_per_turn_s = units_per_rev, velocity_per_turn_s
        self.counter_offset = counter_offset
        self.timer = _Every(period_ms / 1000)

    def _lookup(self, qualified: str) -> tuple[cantools.database.Message, cantools.database.Signal]:
        message_name, _, signal_name = qualified.rpartition(".")
        message = self.db.get_message_by_name(message_name)
        return message, message.get_signal_by_name(signal_name)

    def _encode(self, message: cantools.database.Message, values: dict[str, float]) -> can.Message:
        raw: dict[str, float] = {s.name: 0 for s in message.signals}
        raw.update(values)
        data = message.encode(raw, scaling=False, strict=False)
        return can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=message.is_extended_frame)

    def cyclic(self, t: float, turns: float, speed: float) -> list[can.Message]:
        if not self.timer.due(t):
            return []
        message, signal = self.position
        values: dict[cantools.database.Message, dict[str, float]] = {message: {}}
        if signal.is_float:
            values[message][signal.name] = (turns * self.units_per_rev - signal.offset) / signal.scale
        else:
            count = round(turns * self.units_per_rev / signal.scale) + self.counter_offset
            span = 2**signal.length
            values[message][signal.name] = (count + span // 2) % span - span // 2 if signal.is_signed else count % span
        if self.velocity is not None:
            vmessage, vsignal = self.velocity
            raw = (speed * self.velocity_per_turn_s - vsignal.offset) / vsignal.scale
            values.setdefault(vmessage, {})[vsignal.name] = raw if vsignal.is_float else round(raw)
        return [self._encode(m, v) for m, v in values.items()]


class CanNodeRunner:
    """Drives ``nodes`` on ``bus`` in real time (``tick_s`` steps) with ``motion``; faults:

    - ``drop_probability`` / ``drop_every``: frames lost on the wire (seeded, reproducible);
    - :meth:`error_frames`, :meth:`bus_off`: on an SLCAN ``adapter`` as status flags and a
      bus-off the host must clear with C/O; on a virtual bus as SocketCAN error frames;
    - per node ``silent`` / ``heartbeat_enabled``; counter offsets for wrap tests.
    """

    def __init__(self, bus: can.BusABC, nodes: list[EmulatedNode], motion: WheelMotion, *, tick_s: float = 0.001,
                 adapter: SlcanEmulator | None = None, seed: int = 0) -> None:
        self.bus, self.nodes, self.motion = bus, nodes, motion
        self.tick_s = tick_s
        self.adapter = adapter
        self.drop_probability = 0.0
        self.drop_every = 0
        self.stats: Counter[str] = Counter()
        self._rng = random.Random(seed)
        self._count = 0
        self._paused_until = 0.0
        self._pending_errors: list[can.Message] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.t = 0.0
        self._t0 = 0.0
        for node in nodes:
            if isinstance(node, Cia406Node):
                node.attach(bus)

    def start(self) -> CanNodeRunner:
        self._t0 = time.monotonic()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="can-nodes", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def __enter__(self) -> CanNodeRunner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- faults --------------------------------------------------------------------------------
    def error_frames(self, count: int = 1, passive: bool = False) -> None:
        """Bus errors: error warning (or passive) seen by the host."""
        if self.adapter is not None:
            self.adapter.raise_flags(0x20 if passive else 0x04)
            return
        status = 0x10 if passive else 0x04
        with self._lock:
            self._pending_errors += [can.Message(arbitration_id=CAN_ERR_CRTL | CAN_ERR_PROT, is_error_frame=True,
                                                 is_extended_id=False, data=bytes((0, status, 0, 0, 0, 0, 0, 0)))
                                     for _ in range(count)]

    def bus_off(self, duration_s: float = 0.2) -> None:
        """The controller goes bus-off. SLCAN: until the host closes and reopens the channel;
        virtual: for ``duration_s``, announced and ended by error frames (kernel restart-ms)."""
        if self.adapter is not None:
            self.adapter.bus_off()
            return
        with self._lock:
            self._pending_errors.append(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True,
                                                    is_extended_id=False, dlc=8))
            self._paused_until = self.t + duration_s

    # -- loop ----------------------------------------------------------------------------------
    def _keep(self) -> bool:
        self._count += 1
        if self.drop_every and self._count % self.drop_every == 0:
            return False
        return not (self.drop_probability and self._rng.random() < self.drop_probability)

    def _send(self, frames: list[can.Message]) -> None:
        if self.t < self._paused_until:
            self.stats["dropped_bus_off"] += len(frames)
            return
        kept = [f for f in frames if self._keep()]
        self.stats["dropped"] += len(frames) - len(kept)
        if not kept:
            return
        send_many = getattr(self.bus, "send_many", None)
        if send_many is not None:
            self.stats["sent"] += send_many(kept)
        else:
            for frame in kept:
                self.bus.send(frame)
            self.stats["sent"] += len(kept)

    def step(self, t: float) -> None:
        """One tick at time ``t`` (s): cyclic frames, then answers to what the host sent."""
        self.t = t
        turns, speeds = self.motion.advance(t)
        with self._lock:
            errors, self._pending_errors = self._pending_errors, []
            resumed = self._paused_until and t >= self._paused_until
            if resumed:
                self._paused_until = 0.0
                errors.append(can.Message(arbitration_id=CAN_ERR_RESTARTED, is_error_frame=True,
                                          is_extended_id=False, dlc=8))
        for frame in errors:
            self.bus.send(frame)
        frames = []
        for node in self.nodes:
            if not node.silent:
                frames += node.cyclic(t, float(turns[node.wheel]), float(speeds[node.wheel]))
        self._send(frames)
        while (msg := self.bus.recv(0)) is not None:
            if msg.is_error_frame:
                continue
            self.stats["received"] += 1
            replies = []
            for node in self.nodes:
                if not node.silent:
                    replies += node.on_frame(msg, t, float(turns[node.wheel]), float(speeds[node.wheel]))
            self._send(replies)

    def _run(self) -> None:
        next_tick = time.monotonic()
        while not self._stop.is_set():
            self.step(time.monotonic() - self._t0)
            next_tick += self.tick_s
            delay = next_tick - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_tick = time.monotonic()


def _can_database(dbc: str | Path) -> cantools.database.Database:
    """The CAN database in the DBC file ``dbc``."""
    db = cantools.database.load_file(str(dbc))
    if not isinstance(db, cantools.database.Database):
        raise UserError(f"{dbc} is a diagnostics database, not a CAN one")
    return db


def odrive_nodes(node_ids: Sequence[int], **options: Any) -> list[EmulatedNode]:
    return [OdriveNode(n, w, **options) for w, n in enumerate(node_ids)]


def cia406_nodes(node_ids: Sequence[int], **options: Any) -> list[EmulatedNode]:
    return [Cia406Node(n, w, **options) for w, n in enumerate(node_ids)]


def vesc_nodes(
    dbc: str | Path, controller_ids: Sequence[int], pole_pairs: int = 7, **options: Any
) -> list[EmulatedNode]:
    """VESC controllers per the example DBC: tachometer in STATUS_5, ERPM in STATUS."""
    db = _can_database(dbc)
    return [DbcNode(db, w, f"VESC_Status5_id{c}.Tachometer", velocity_signal=f"VESC_Status1_id{c}.ERPM",
                    units_per_rev=6 * pole_pairs, velocity_per_turn_s=60 * pole_pairs, **options)
            for w, c in enumerate(controller_ids)]

