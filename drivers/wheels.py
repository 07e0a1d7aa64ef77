"""Wheel-encoder driver on a CAN bus: raw frames on ``/can/rx``, wheel angles on ``/wheels``.
Odometry is ``trundle.fusion.odometry.diff_drive.OdometrySink`` wrapped around the driver's sink (live) or run over
a log's ``/wheels`` (replay): the same code either way.

Configuration (the ``[can]`` table of the robot TOML; ``encoders`` also from ``--encoders``)::

    url = "slcan:///dev/ttyACM0@1000000"
    encoders = "odrive:0,1"          # or "cia406:5,6", "dbc:/path/robot.dbc", or groups joined by "+"
    wheels = ["left", "right"]       # joint names, one per encoder in order
    direction = [1, -1]              # +1 / -1 per wheel (or one number): forward = positive
    gear_ratio = 1.0                 # motor turns per wheel turn (per wheel or one number)
    counts_per_rev = 8192            # override the device's counts per motor turn (optional)
    wheel_radius_m = 0.08            # with track_m: odometry (trundle.fusion.odometry.diff_drive.OdometrySink)
    track_m = 0.35
    [can.odrive]   firmware = "auto", source = "estimates", poll_hz = 0, heartbeat_timeout_s = 0.35
    [can.cia406]   eds = "...", counts_per_rev = 4096, tpdo_period_ms = 10, heartbeat_ms = 100
    [can.dbc]      signals = ["Msg.Signal", ...], units_per_rev = 42, velocity_signals = [...]

A wheel whose node stops its heartbeat or its positions is published as NaN (stale); so is
every wheel when the bus is lost. Odometry stops there and restarts from the next good reading
without a jump.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Annotated, Any

import numpy as np
from pydantic import BeforeValidator

from trundle.drivers.can_bus import CanBus, Received, parse_url
from trundle.drivers.cia406 import Cia406Encoders
from trundle.drivers.counter_unwrap import CounterUnwrapper
from trundle.drivers.dbc_wheels import DbcWheels
from trundle.drivers.encoder_protocol import EncoderProtocol, WheelReading, per_wheel
from trundle.drivers.lifecycle import Driver, Sink
from trundle.drivers.odrive_encoders import OdriveEncoders
from trundle.logs import messages as m
from trundle.logs.errors import ConfigError, UserError
from trundle.logs.schema import Name, Schema, parse
from trundle.logs.topics import CAN_RX_TOPIC, WHEELS_TOPIC

PROTOCOLS = ("odrive", "cia406", "dbc")
VELOCITY_WINDOW_S = 0.05  # shortest span for a velocity from two positions
MAX_SEEN_IDS = 256  # arbitration ids remembered for the "which nodes are there" hint
MAX_CARRY_S = 0.05  # a reading older than this at the publish instant is not carried forward:
# that much lag is a receive stall (stamps of a burst), not the phase between two nodes


def _per_wheel(value: float | list[float], key: str, n: int) -> list[float]:
    """A per-wheel setting (one number, or one per wheel) as one number per wheel."""
    try:
        return per_wheel(value, n, key)
    except ValueError as error:
        raise ConfigError(f"can.{error}") from None


def _node_ids(protocol: str, text: str) -> tuple[int, ...]:
    try:
        ids = tuple(int(t, 0) for t in text.split(",") if t.strip())
    except ValueError:
        raise UserError(f"{protocol} node ids must be integers, got {text!r}") from None
    if not ids:
        raise UserError(f"no node ids after {protocol}:")
    return ids


def build_protocols(spec: str, config: Mapping[str, Any]) -> list[EncoderProtocol]:
    """Encoder protocols from an ``--encoders`` spec such as ``odrive:0,1`` or
    ``cia406:5+dbc:robot.dbc``; wheels are numbered in the order they appear."""
    protocols: list[EncoderProtocol] = []
    first = 0
    for group in spec.split("+"):
        kind, sep, arg = group.strip().partition(":")
        kind = kind.lower()
        if not sep or kind not in PROTOCOLS:
            raise UserError(f"bad encoder spec {group!r}: use odrive:0,1, cia406:5,6 or dbc:/path/file.dbc")
        options = dict(config.get(kind, {}))
        try:
            if kind == "odrive":
                ids = _node_ids(kind, arg)
                protocol: EncoderProtocol = OdriveEncoders(ids, tuple(range(first, first + len(ids))), **options)
            elif kind == "cia406":
                ids = _node_ids(kind, arg)
                protocol = Cia406Encoders(ids, tuple(range(first, first + len(ids))), **options)
            else:
                signals = options.pop("signals", None)
                if not signals:
                    raise UserError("dbc encoders need [can.dbc] signals = [\"Message.Signal\", ...], one per wheel")
                protocol = DbcWheels(arg, list(signals), tuple(range(first, first + len(signals))), **options)
        except TypeError as error:
            raise UserError(f"bad [can.{kind}] option: {error}") from None
        except ValueError as error:
            raise UserError(f"{kind} encoders: {error}") from None
        protocols.append(protocol)
        first += len(protocol.wheels)
    return protocols


class WheelsDriver(Driver):
    """Reads a CAN bus, decodes wheel encoders, publishes raw frames and wheel states.

    ``wheel_readings`` counts the wheel states with a position of every wheel (the usable
    output); ``seen_ids`` holds the arbitration ids heard (up to ``MAX_SEEN_IDS``), so a bus
    whose frames give no readings can say what is on it.
    """

    usable = "wheel_readings"

    def __init__(self, bus: CanBus, protocols: list[EncoderProtocol], sink: Sink, *, names: tuple[str, ...],
                 direction: list[float], gear_ratio: list[float], counts_per_rev: list[float | None],
                 publish_frames: bool = True, name: str = "can",
                 poll_period_s: float = 0.005) -> None:
        super().__init__(name, sink, hardware_id=bus.spec.url)
        self.bus = bus
        self.serial_port = bus.spec.channel if bus.spec.interface == "slcan" else ""
        self.protocols = protocols
        self.names = names
        n = len(names)
        if sum(len(p.wheels) for p in protocols) != n:
            raise UserError(f"{n} wheel names for {sum(len(p.wheels) for p in protocols)} encoders")
        # Python floats: a frame's scaling is a few scalar operations, which numpy's scalars made slower
        self.direction = [float(v) for v in direction]
        self.gear_ratio = [float(v) for v in gear_ratio]
        self.counts_override = counts_per_rev
        self.publish_frames = publish_frames
        self.poll_period_ns = int(poll_period_s * 1e9)
        self.frame_id = bus.spec.channel.rsplit("/", 1)[-1]
        self._unwrap: list[CounterUnwrapper | None] = [None] * n
        self._position = np.full(n, math.nan)  # rad, at _sampled_ns
        self._velocity = np.full(n, math.nan)  # rad/s: the device's, else from positions >= 50 ms apart
        self._sampled_ns = np.zeros(n, dtype=np.int64)
        self._ref_angle = np.full(n, math.nan)  # reference for the position-difference velocity
        self._ref_ns = np.zeros(n, dtype=np.int64)
        self._fresh: set[int] = set()   # wheels with a reading since the last publish
        self._healthy: set[int] = set()
        self._next_poll = 0
        self._published_finite = False
        self.seen_ids: set[int] = set()

    # -- life cycle ----------------------------------------------------------------------------
    def open(self) -> None:
        self.bus.open()
        now = time.monotonic_ns()
        for protocol in self.protocols:
            protocol.start(self.bus, now)
        self._unwrap = [None] * len(self.names)
        self._fresh.clear()
        self._healthy = set()

    def close(self) -> None:
        for protocol in self.protocols:
            protocol.stop()
        if self._published_finite:  # whatever happens while disconnected is not integrated
            self._publish_stale(set(range(len(self.names))), self.bus.host_ns() if self.bus.bus else self.clock())
        self.bus.close()

    def read_once(self) -> None:
        received = self.bus.recv(0.01)
        now = time.monotonic_ns()
        if received is not None:
            self.handle(received, now)
        if now >= self._next_poll:
            self._next_poll = now + self.poll_period_ns
            self.poll(now)

    # -- processing (also used directly by tests and replays) ----------------------------------
    def handle(self, received: Received, now_ns: int) -> None:
        msg = received.msg
        self.counters["frames"] += 1
        if len(self.seen_ids) < MAX_SEEN_IDS and not msg.is_error_frame:
            self.seen_ids.add(msg.arbitration_id)
        if self.publish_frames:
            self.publish(CAN_RX_TOPIC, m.CanFrame(received.stamp_ns, self.frame_id, msg.arbitration_id, bytes(msg.data),
                                               msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame),
                         received.host_ns)
        if msg.is_error_frame:
            return
        readings: list[WheelReading] = []
        for protocol in self.protocols:
            try:
                readings += protocol.handle(msg, now_ns)
            except ValueError:
                self.counters["decode_errors"] += 1
        if not readings:
            return
        healthy = self._healthy_now(now_ns)
        for reading in readings:
            self._apply(reading, healthy, received.stamp_ns)
        if healthy and healthy <= self._fresh:
            self._publish(healthy, received.stamp_ns, received.host_ns)

    def poll(self, now_ns: int) -> None:
        for protocol in self.protocols:
            protocol.poll(now_ns)
        healthy = self._healthy_now(now_ns)
        lost = self._healthy - healthy
        self._healthy = healthy
        if lost:
            self.counters["stale_events"] += len(lost)
            for w in lost:
                self._unwrap[w] = None
            self._publish_stale(lost, self.bus.host_ns())

    def _healthy_now(self, now_ns: int) -> set[int]:
        healthy: set[int] = set()
        for protocol in self.protocols:
            healthy |= protocol.healthy_wheels(now_ns)
        return healthy

    def _apply(self, reading: WheelReading, healthy: set[int], stamp_ns: int) -> None:
        w = reading.wheel
        if w not in healthy:
            self._unwrap[w] = None
            self._position[w] = math.nan
            return
        position = reading.position
        if reading.modulus is not None:
            unwrapper = self._unwrap[w]
            if unwrapper is None or unwrapper.modulus != reading.modulus:
                unwrapper = self._unwrap[w] = CounterUnwrapper(reading.modulus)
            position = unwrapper.update(int(position))
        counts = self.counts_override[w] or self._counts_per_rev(w)
        scale = 2.0 * math.pi * self.direction[w] / (counts * self.gear_ratio[w])
        angle = position * scale
        velocity = reading.velocity * scale
        if math.isnan(velocity):
            velocity = self._difference_velocity(w, angle, stamp_ns)
        self._position[w], self._velocity[w], self._sampled_ns[w] = angle, velocity, stamp_ns
        self._fresh.add(w)

    def _difference_velocity(self, w: int, angle: float, stamp_ns: int) -> float:
        """Velocity from positions at least ``VELOCITY_WINDOW_S`` apart: receive stamps of frames
        read in a burst are nearly equal, and a difference over them would be wild."""
        if math.isnan(self._ref_angle[w]) or math.isnan(self._position[w]):
            self._ref_angle[w], self._ref_ns[w] = angle, stamp_ns
            return math.nan
        dt = (stamp_ns - self._ref_ns[w]) * 1e-9
        if dt < VELOCITY_WINDOW_S:
            return float(self._velocity[w])
        velocity = (angle - self._ref_angle[w]) / dt
        self._ref_angle[w], self._ref_ns[w] = angle, stamp_ns
        return velocity

    def _counts_per_rev(self, wheel: int) -> float:
        for protocol in self.protocols:
            if wheel in protocol.counts_per_rev:
                return protocol.counts_per_rev[wheel]
        raise UserError(f"counts per revolution of wheel {self.names[wheel]} unknown: set counts_per_rev")

    def _publish(self, healthy: set[int], stamp_ns: int, log_ns: int) -> None:
        """Publish every wheel at ``stamp_ns``: wheels sampled earlier (each axis sends on its
        own clock) are carried forward by their velocity, so the pair describes one instant."""
        positions: list[float] = []
        velocities: list[float] = []
        # Python floats for a few wheels (numpy's dozen calls on 4-element arrays were most of a publish)
        for w, (angle, velocity, sampled_ns) in enumerate(zip(self._position.tolist(), self._velocity.tolist(),
                                                             self._sampled_ns.tolist(), strict=True)):
            if w not in healthy:
                positions.append(math.nan)
                velocities.append(math.nan)
                continue
            lag_s = (stamp_ns - sampled_ns) * 1e-9
            carry_s = lag_s if 0.0 < lag_s <= MAX_CARRY_S else 0.0
            positions.append(angle + (velocity if math.isfinite(velocity) else 0.0) * carry_s)
            velocities.append(velocity)
        self._fresh.clear()
        finite = [math.isfinite(p) for p in positions]
        self._published_finite = any(finite)
        if all(finite):
            self.counters["wheel_readings"] += 1
        self._emit(m.JointState(stamp_ns, "base_link", self.names, np.array(positions),
                                np.array(velocities) if any(map(math.isfinite, velocities)) else np.empty(0)), log_ns)

    def _publish_stale(self, lost: set[int], now_ns: int) -> None:
        positions = self._position.copy()
        positions[list(lost)] = math.nan
        self._position[list(lost)] = math.nan
        self._published_finite = bool(np.isfinite(positions).any())
        self._emit(m.JointState(now_ns, "base_link", self.names, positions), now_ns)

    def _emit(self, state: m.JointState, log_ns: int) -> None:
        self.counters["joint_states"] += 1
        self.publish(WHEELS_TOPIC, state, log_ns)

    # -- health --------------------------------------------------------------------------------
    def silence_reason(self) -> str:
        """What the bus carries instead of wheel readings: nothing, corrupt frames, or other nodes; and the
        wheels not trusted (an axis's error flag, no heartbeat), which is why the others alone are no reading."""
        if not self.counters["frames"]:
            return "no CAN frames at all (bus not connected or not terminated, wrong bit rate, nodes off?)"
        if self.counters["decode_errors"] and self.counters["decode_errors"] * 2 >= self.counters["frames"]:
            return f"{self.counters['decode_errors']} of {self.counters['frames']} frames could not be decoded"
        reasons = [hint for protocol in self.protocols if (hint := protocol.silence_hint(self.seen_ids))]
        if stale := self._stale_wheels():
            reasons.append(f"stale wheels: {', '.join(stale)}")
        return "; ".join(reasons) or f"{self.counters['frames']} frames, none a reading of every wheel"

    def _stale_wheels(self) -> list[str]:
        """The names of the wheels not trusted now."""
        return [self.names[w] for w in range(len(self.names)) if w not in self._healthy]

    def diagnostics(self) -> m.DiagnosticStatus:
        status = super().diagnostics()
        stale = self._stale_wheels()
        values = [*status.values, ("bus_state", self.bus.state),
                  *sorted((f"bus.{k}", str(v)) for k, v in self.bus.counters.items()),
                  ("stale_wheels", ",".join(stale) or "none")]
        for protocol in self.protocols:
            values += protocol.diagnostics()
        level, message = status.level, status.message
        if status.level == m.OK and (stale or self.bus.state != "active"):
            level = m.WARN
            message = f"stale wheels: {', '.join(stale)}" if stale else f"bus {self.bus.state}"
        return m.DiagnosticStatus(level, status.name, message, status.hardware_id, tuple(values))


def _per_wheel_shape(value: Any) -> Any:
    """A per-wheel setting is one finite number or an array of them (their count is checked
    against the wheels once the encoders are known)."""
    numbers = value if isinstance(value, list) else [value]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in numbers):
        raise ValueError("expected a number or an array of numbers, one per wheel")
    return value


PerWheel = Annotated[float | list[float], BeforeValidator(_per_wheel_shape)]


class CanOptions(Schema):
    """The ``[can]`` table (see the module docstring): the driver's options, the protocols'
    subtables (``[can.odrive]`` ...: keyword arguments of the protocol's class) and the wheel
    model beside them, which the driver does not use: it is read and checked by the odometry
    (:class:`trundle.fusion.odometry.diff_drive.WheelModel`)."""

    url: str = ""
    name: Name = "can"
    encoders: Name | None = None
    wheels: list[Name] | None = None
    direction: PerWheel = 1.0
    gear_ratio: PerWheel = 1.0
    counts_per_rev: PerWheel | None = None
    publish_frames: bool = True
    odrive: dict[str, Any] = {}
    cia406: dict[str, Any] = {}
    dbc: dict[str, Any] = {}
    wheel_radius_m: Any = None
    track_m: Any = None
    odometry_wheels: Any = None
    wheel_variance_per_m: Any = None


def driver_from_url(url: str, sink: Sink, config: Mapping[str, Any]) -> WheelsDriver:
    """The wheels driver for CAN ``url`` with ``config`` (the ``[can]`` table, ``encoders`` set)."""
    spec = parse_url(url)
    options = parse(CanOptions, config, "can")
    if not options.encoders:
        raise ConfigError("no wheel encoders given: use --encoders odrive:0,1 (or encoders in [can])")
    protocols = build_protocols(options.encoders, options.model_dump())
    n = sum(len(p.wheels) for p in protocols)
    names = tuple(options.wheels or (("left", "right") if n == 2 else tuple(f"wheel{i}" for i in range(n))))
    if len(names) != n:
        raise ConfigError(f"can.wheels: {len(names)} wheel names for {n} encoders in {options.encoders!r}")
    direction = _per_wheel(options.direction, "direction", n)
    if any(d not in (1.0, -1.0) for d in direction):
        raise ConfigError(f"can.direction = {options.direction!r}: expected 1 or -1 per wheel")
    gear = _per_wheel(options.gear_ratio, "gear_ratio", n)
    if any(g <= 0 for g in gear):
        raise ConfigError(f"can.gear_ratio = {options.gear_ratio!r}: expected numbers > 0")
    counts = ([0.0] * n if options.counts_per_rev is None
              else _per_wheel(options.counts_per_rev, "counts_per_rev", n))
    if any(c < 0 for c in counts):
        raise ConfigError(f"can.counts_per_rev = {options.counts_per_rev!r}: expected numbers >= 0 (0: the device's)")
    return WheelsDriver(CanBus(spec), protocols, sink, names=names, direction=direction, gear_ratio=gear,
                        counts_per_rev=[c or None for c in counts], publish_frames=options.publish_frames,
                        name=options.name)
