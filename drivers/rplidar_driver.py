"""Slamtec RPLIDAR driver (A1/A2/A3/S1): legacy or express scans, one LaserScan per revolution.

Start-up stops a scan left running (STOP, wait, flush), checks health (RESET on error, then
give up as a hardware fault), reads GET_INFO and GET_SAMPLERATE, starts the motor the way the
model wants (DTR on A1, PWM through the accessory board on A2/A3, rpm on S1; a pty's missing
modem lines only cost a counter), starts SCAN or EXPRESS_SCAN and checks the descriptor.
``RevolutionAssembler`` (pure) turns the decoded samples into whole revolutions and refuses
any revolution touched by lost or corrupt bytes; ``revolution_scan`` bins one onto a fixed
angular grid. Shutdown sends STOP and stops the motor.
"""

from __future__ import annotations

import math
import struct
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import serial

from trundle.drivers import rplidar as rp
from trundle.drivers.laser_mount import laser_transform
from trundle.drivers.lifecycle import Backoff, DeviceError, Driver, Sink, wall_ns
from trundle.drivers.serial_link import SerialLink, set_modem_line
from trundle.logs import messages as m
from trundle.logs.errors import UserError

# model: (default baud, range_min m, range_max m)
MODELS = {"a1": (115200, 0.15, 12.0), "a2": (115200, 0.15, 12.0), "a3": (256000, 0.2, 25.0), "s1": (256000, 0.1, 40.0)}
LEGACY_SAMPLE_US = 476  # the SDK's default when GET_SAMPLERATE is not answered
BAUDS = (115200, 256000, 460800, 1000000)  # the native rates of the A/S/C series
WRAP_Q6 = 16 * 64  # a clean wrap goes from the last 16 deg of a turn to its first 16 deg


@dataclass(frozen=True)
class RplidarConfig:
    """Driver options (the ``[lrf]`` table of a robot config). Angles in radians, times in seconds.

    ``model`` picks the default baud and range limits; ``mode`` is ``standard`` (SCAN) or
    ``express`` (EXPRESS_SCAN); ``beams`` is the size of the published angular grid;
    ``motor_pwm`` (A2/A3) and ``motor_rpm`` (S series) set the motor speed. ``range_min``,
    ``range_max`` and ``baudrate`` default (0) to the model's. ``error_limit`` bad revolutions
    in a row or ``timeout_s`` of silence force a reconnect (backing off up to ``backoff_max_s``);
    ``reply_timeout_s`` bounds each start-up reply, ``startup_timeout_s`` the scan's first answer.
    """

    port: str
    model: str = "a1"
    baudrate: int = 0
    mode: str = "standard"
    beams: int = 360
    frame_id: str = "laser"
    parent_frame: str = "base_link"
    topic: str = "/scan"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0
    range_min: float = 0.0
    range_max: float = 0.0
    motor_pwm: int = 660
    motor_rpm: int = 600
    error_limit: int = 4
    timeout_s: float = 1.0
    startup_timeout_s: float = 3.0
    reply_timeout_s: float = 0.5
    backoff_max_s: float = 0.5

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise UserError(f"lrf: unknown RPLIDAR model {self.model!r} (choose {', '.join(MODELS)})")
        if self.mode not in ("standard", "express"):
            raise UserError(f"lrf: mode must be standard or express, not {self.mode!r}")
        if not 8 <= self.beams <= 8192 or not 0 <= self.motor_pwm <= 1023:
            raise UserError("lrf: beams must be 8-8192 and motor_pwm 0-1023")

    @property
    def limits(self) -> tuple[int, float, float]:
        baud, lo, hi = MODELS[self.model]
        return self.baudrate or baud, self.range_min or lo, self.range_max or hi


@dataclass
class Revolution:
    """One whole turn: sample angles (1/64 deg), distances (1/4 mm), quality, host time of its
    first sample and its duration (ns)."""

    angle_q6: np.ndarray
    distance_q2: np.ndarray
    quality: np.ndarray
    start_ns: int
    duration_ns: int


@dataclass
class RevolutionAssembler:
    """Decoded samples -> whole revolutions, dropping every revolution touched by a fault.

    A revolution runs from a start sample to the next; it is kept only if both of its
    boundaries are clean wraps (no lost bytes there, the angle falls from its last 16 degrees to
    its first 16), no
    bytes were lost inside it, and its angles advance without a gap wider than five typical
    steps (``monotonic``: never backwards, as legacy scans are). Counters, for revolutions that
    began with a clean wrap: ``corrupt_revolutions`` (lost or bad bytes inside or at the end),
    ``incomplete_revolutions`` (angle gaps); ``late_data`` counts start samples that arrived
    over 50 ms later than the sample clock predicts.

    Times come from the sample clock (``sample_ns`` apart, lost bytes counted as the samples
    they held), re-anchored on the earliest receive time seen, so data held up by the host or a
    USB hiccup is not stamped late. The newest
    sample of a chunk is taken as measured at its receive time, ``lag_samples`` after the last
    sample the decoder hands over (express capsules are held back two at a time).
    """

    sample_ns: int
    monotonic: bool = True
    lag_samples: int = 0
    counters: Counter = field(default_factory=Counter)
    _parts: list[rp.Nodes] = field(default_factory=list)
    _start_ns: int = 0
    _started: bool = False
    _clean: bool = True
    _prev_angle: int | None = None
    _last_angle: int | None = None  # kept across breaks, to count the samples they swallowed
    _step_q6: float = 0.0  # typical angle between samples
    _pending_lost: int = 0
    _anchor_ns: int | None = None
    _since_anchor: int = 0

    def reset(self) -> None:
        self._parts.clear()
        self._started, self._clean, self._prev_angle, self._anchor_ns = False, True, None, None
        self._last_angle, self._pending_lost = None, 0

    def feed(self, nodes: rp.Nodes, rx_ns: int) -> list[Revolution]:
        n = len(nodes)
        out: list[Revolution] = []
        self._pending_lost += nodes.lost
        if not n:
            return out
        marks = np.flatnonzero(nodes.start | nodes.broken).tolist()
        pos = 0
        for b in marks + [n]:
            if b > pos:
                self._parts.append(_slice(nodes, pos, b))
                self._prev_angle = self._last_angle = int(nodes.angle_q6[b - 1])
                self._since_anchor += b - pos
            if b == n:
                break
            pos = b
            if nodes.broken[b]:
                self._since_anchor += self._lost(int(nodes.angle_q6[b]))
                self._clean, self._prev_angle = False, None
            if nodes.start[b]:
                wrap = (not nodes.broken[b] and self._prev_angle is not None
                        and self._prev_angle >= rp.FULL_CIRCLE_Q6 - WRAP_Q6 and nodes.angle_q6[b] < WRAP_Q6)
                revolution = self._close(wrap)
                if revolution is not None:
                    out.append(revolution)
                self._started, self._clean = wrap, True
                self._start_ns = self._clock(rx_ns - (n - 1 - b + self.lag_samples) * self.sample_ns)
        return out

    def _lost(self, angle_q6: int) -> int:
        """Samples swallowed by a break: the angle gap before ``angle_q6`` in sample steps,
        plus the whole turns the decoder's count of lost bytes implies."""
        estimate, self._pending_lost = self._pending_lost, 0
        if self._last_angle is None or self._step_q6 <= 0:
            return estimate
        per_turn = rp.FULL_CIRCLE_Q6 / self._step_q6
        gap = ((angle_q6 - self._last_angle) % rp.FULL_CIRCLE_Q6) / self._step_q6 - 1
        return max(0, round(gap + per_turn * round((estimate - gap) / per_turn)))

    def _clock(self, observed_ns: int) -> int:
        """Time of a start sample: the sample clock's prediction unless the receive time is earlier."""
        if self._anchor_ns is None:
            t = observed_ns
        else:
            predicted = self._anchor_ns + self._since_anchor * self.sample_ns
            late = observed_ns - predicted
            if late > 50_000_000:
                self.counters["late_data"] += 1
            t = observed_ns if late > 1_000_000_000 else min(observed_ns, predicted + late // 100)
        self._anchor_ns, self._since_anchor = t, 0
        return t

    def _close(self, wrap: bool) -> Revolution | None:
        parts, self._parts = self._parts, []
        if not parts:
            return None
        if not (self._started and self._clean and wrap):
            if self._started:
                self.counters["corrupt_revolutions"] += 1
            return None
        angle = np.concatenate([p.angle_q6 for p in parts])
        step = np.diff(angle)
        limit = max(5 * float(np.median(np.abs(step))) if step.size else 0.0, 2.0 * 64)
        if (angle.size < 8 or step.max() > limit or angle[0] > limit or angle[-1] < rp.FULL_CIRCLE_Q6 - limit
                or (self.monotonic and step.min() < 0) or step.min() < -limit):
            self.counters["incomplete_revolutions"] += 1
            return None
        self._step_q6 = rp.FULL_CIRCLE_Q6 / angle.size
        return Revolution(angle, np.concatenate([p.distance_q2 for p in parts]),
                          np.concatenate([p.quality for p in parts]), self._start_ns, angle.size * self.sample_ns)


def _slice(nodes: rp.Nodes, a: int, b: int) -> rp.Nodes:
    return rp.Nodes(nodes.start[a:b], nodes.quality[a:b], nodes.angle_q6[a:b], nodes.distance_q2[a:b],
                    nodes.broken[a:b])


def revolution_scan(rev: Revolution, beams: int, range_min: float, range_max: float, frame_id: str = "laser",
                    intensities: bool = True) -> m.LaserScan:
    """Bin a revolution onto ``beams`` equal sectors as a LaserScan (REP 103/117).

    The device counts angles clockwise from its own zero; the laser frame angle is
    ``pi - angle`` as rplidar_ros publishes, so beam i (ascending angle) holds the sector at
    device angle ``(beams - 1 - i) * 360 / beams``. The device turns clockwise, so beams in
    index order were measured backwards in time: ``stamp_ns`` is the time of beam 0 and
    ``time_increment`` is negative. Per sector the sample nearest its centre wins; distance 0
    (the device's "no measurement") is +inf, an empty sector NaN.
    """
    sector = rp.FULL_CIRCLE_Q6 / beams
    position = rev.angle_q6 / sector
    j = np.rint(position).astype(np.int64) % beams
    off = np.abs(position - np.rint(position))
    order = np.lexsort((off, j))
    j_sorted = j[order]
    first = order[np.concatenate(([True], j_sorted[1:] != j_sorted[:-1]))]
    dist = rev.distance_q2[first] / 4000.0
    with np.errstate(invalid="ignore"):
        value = np.where(rev.distance_q2[first] == 0, np.inf,
                         np.where(dist < range_min, -np.inf, np.where(dist > range_max, np.inf, dist)))
    ranges = np.full(beams, np.nan, np.float32)
    ranges[beams - 1 - j[first]] = value
    quality = np.zeros(beams if intensities else 0, np.float32)
    if intensities:
        quality[beams - 1 - j[first]] = rev.quality[first]
    period_s = rev.duration_ns / 1e9
    increment = 2.0 * math.pi / beams
    stamp = rev.start_ns + int(rev.duration_ns * (beams - 1) / beams)
    return m.LaserScan(stamp, frame_id, math.pi - (beams - 1) * increment, math.pi, increment, -period_s / beams,
                       period_s, range_min, range_max, ranges, quality)


class RplidarDriver(Driver):
    """The RPLIDAR life cycle on a pyserial port (see the module docstring)."""

    COUNTERS = ("scans", "bad_nodes", "bad_capsules", "resyncs", "skipped_bytes", "corrupt_revolutions",
                "incomplete_revolutions", "late_data", "timeouts", "drained_bytes", "stale_streams",
                "health_warnings", "health_resets", "modem_lines_unsupported", "sink_drops")

    def __init__(self, config: RplidarConfig, sink: Sink, *, clock: Callable[[], int] = wall_ns,
                 name: str = "lrf") -> None:
        super().__init__(name, sink, hardware_id=config.port, backoff=Backoff(0.1, config.backoff_max_s), clock=clock)
        self.config = config
        self.counters.update({k: 0 for k in self.COUNTERS})
        self.info: rp.DeviceInfo | None = None
        self.health: rp.Health | None = None
        self.motor = ""
        self.link: SerialLink | None = None
        self._buf = bytearray()
        self._decoder: rp.NodeDecoder | rp.ExpressNodeDecoder = rp.NodeDecoder()
        self._assembler = RevolutionAssembler(LEGACY_SAMPLE_US * 1000, counters=self.counters)
        self._bad_in_row = 0
        self._static = laser_transform(config, clock())

    def static_messages(self) -> list[tuple[str, m.Message]]:
        return [("/tf_static", self._static)]

    # --- transport ---------------------------------------------------------------------------

    def _read(self) -> bytes:
        if self.link is None:
            raise DeviceError("port closed")
        return self.link.read()

    def _send(self, command: int, payload: bytes | None = None) -> None:
        assert self.link is not None
        self.link.write(rp.request(command, payload))

    def _response(self, expected: rp.Descriptor, timeout_s: float | None = None) -> bytes:
        """Wait for ``expected``'s descriptor (skipping and counting other bytes); return its
        payload (single) or the bytes that followed it (multiple)."""
        deadline = time.monotonic() + (timeout_s or self.config.reply_timeout_s)
        head = expected.encode()
        while time.monotonic() < deadline and not self.stopping:
            at = self._buf.find(head)
            need = at + rp.DESCRIPTOR_SIZE + (0 if expected.mode == rp.MULTIPLE else expected.length)
            if at >= 0 and len(self._buf) >= need:
                self.counters["drained_bytes"] += at
                if expected.mode == rp.MULTIPLE:
                    rest, self._buf = bytes(self._buf[need:]), bytearray()
                    return rest
                payload = bytes(self._buf[need - expected.length:need])
                del self._buf[:need]
                return payload
            self._buf += self._read()
        raise DeviceError(f"no {expected.type:#04x} response from {self.config.port} "
                          f"(wrong port or baud rate {self.link.port.baudrate if self.link else '?'}?)")

    def _flush(self, quiet_s: float = 0.02) -> int:
        """Drop input until the line has been quiet for ``quiet_s``; returns how many bytes."""
        assert self.link is not None
        dropped = len(self._buf)
        self._buf.clear()
        return dropped + self.link.drain(quiet_s)

    # --- start-up ----------------------------------------------------------------------------

    def open(self) -> None:
        baud, range_min, range_max = self.config.limits
        self.link = SerialLink(self.config.port, baud)
        self._buf = bytearray()
        self._send(rp.STOP)
        time.sleep(0.01)
        drained = self._flush()
        self.counters["drained_bytes"] += drained
        if drained:
            self.counters["stale_streams"] += 1
        self._check_health()
        self._send(rp.GET_INFO)
        self.info = rp.DeviceInfo.parse(self._response(rp.INFO_DESCRIPTOR))
        self.hardware_id = (f"RPLIDAR model {self.info.model:#04x} fw {self.info.firmware[0]}.{self.info.firmware[1]:02d}"
                            f" hw {self.info.hardware} sn {self.info.serial.hex().upper()}")
        sample_us = self._sample_us()
        self._start_motor()
        express = self.config.mode == "express"
        if express:
            self._send(rp.EXPRESS_SCAN, bytes(5))
        else:
            self._send(rp.SCAN)
        rest = self._response(rp.EXPRESS_DESCRIPTOR if express else rp.SCAN_DESCRIPTOR, self.config.startup_timeout_s)
        self._decoder = rp.ExpressNodeDecoder() if express else rp.NodeDecoder()
        self._assembler = RevolutionAssembler(sample_us * 1000, monotonic=not express,
                                              lag_samples=4 * rp.CABINS if express else 0, counters=self.counters)
        self._bad_in_row = 0
        if rest:
            self._process(rest, self.clock())

    def _health(self) -> rp.Health:
        """GET_HEALTH; with no answer, try the other RPLIDAR bauds (a wrong baud is the usual
        cause of "Descriptor length mismatch") before giving up with one line naming them."""
        assert self.link is not None
        bauds = [self.link.port.baudrate] + [b for b in BAUDS if b != self.link.port.baudrate]
        for baud in bauds if "://" not in self.config.port else bauds[:1]:
            self.link.port.baudrate = baud
            self._send(rp.GET_HEALTH)
            try:
                return rp.Health.parse(self._response(rp.HEALTH_DESCRIPTOR))
            except DeviceError:
                self._buf.clear()
        raise DeviceError(f"no RPLIDAR answer on {self.config.port} at {', '.join(map(str, bauds))} baud "
                          "(wrong port, not an RPLIDAR, or no permission?)")

    def _check_health(self) -> None:
        for attempt in range(2):
            self.health = self._health()
            if self.health.status == rp.HEALTH_WARNING:
                self.counters["health_warnings"] += 1
            if self.health.status != rp.HEALTH_ERROR:
                return
            if attempt == 0:
                self.counters["health_resets"] += 1
                self._send(rp.RESET)
                time.sleep(0.02)
                self._flush(quiet_s=0.05)  # the device prints a text banner after a reset
        raise DeviceError(f"RPLIDAR hardware fault: health error code {self.health.error_code:#06x} after RESET")

    def _sample_us(self) -> int:
        """Microseconds between samples in the chosen mode (GET_SAMPLERATE, firmware >= 1.17)."""
        assert self.info is not None
        if self.info.firmware >= (1, 17):
            self._send(rp.GET_SAMPLERATE)
            try:
                standard, express = struct.unpack("<HH", self._response(rp.SAMPLERATE_DESCRIPTOR))
                return max(1, express if self.config.mode == "express" else standard)
            except DeviceError:
                pass
        return LEGACY_SAMPLE_US

    def _start_motor(self) -> None:
        """S series: rpm command; A series: PWM if the accessory board says so, else DTR."""
        assert self.info is not None and self.link is not None
        if self.info.major_model >= 6:
            self.motor = "rpm"
            self._send(rp.HQ_MOTOR_SPEED_CTRL, struct.pack("<H", self.config.motor_rpm))
            return
        self._send(rp.GET_ACC_BOARD_FLAG, bytes(4))
        try:
            flags = int.from_bytes(self._response(rp.ACC_BOARD_DESCRIPTOR, 0.2), "little")
        except DeviceError:
            flags = 0
        if flags & 1:
            self.motor = "pwm"
            self._send(rp.SET_MOTOR_PWM, struct.pack("<H", self.config.motor_pwm))
        else:
            self.motor = "dtr"
            if not set_modem_line(self.link.port, "dtr", False):  # SDK: DTR cleared = motor runs
                self.counters["modem_lines_unsupported"] += 1

    def close(self) -> None:
        """STOP, then stop the motor, then close; never raises."""
        link, self.link = self.link, None
        if link is None:
            return

        def farewell(port: serial.SerialBase) -> None:
            port.write(rp.request(rp.STOP))
            port.flush()
            time.sleep(0.002)
            if self.motor == "pwm":
                port.write(rp.request(rp.SET_MOTOR_PWM, struct.pack("<H", 0)))
            elif self.motor == "rpm":
                port.write(rp.request(rp.HQ_MOTOR_SPEED_CTRL, struct.pack("<H", 0)))
            elif self.motor == "dtr" and not set_modem_line(port, "dtr", True):
                self.counters["modem_lines_unsupported"] += 1

        link.close(farewell)

    # --- streaming ---------------------------------------------------------------------------

    def read_once(self) -> None:
        data = self._read()
        if data:
            self._process(data, self.clock())
        if self._bad_in_row >= self.config.error_limit:
            self._bad_in_row = 0
            raise DeviceError(f"{self.config.error_limit} bad revolutions in a row")
        if self.link is not None and self.link.silent_s > self.config.timeout_s:
            self.counters["timeouts"] += 1
            raise DeviceError(f"no data from {self.config.port} for {self.config.timeout_s:.2f} s")

    def _decoder_stats(self) -> tuple[int, int, int]:
        """(bad frames, resyncs, skipped bytes) of the current decoder."""
        d = self._decoder
        if isinstance(d, rp.ExpressNodeDecoder):
            return d.capsules.bad_capsules, d.capsules.resyncs, d.capsules.skipped_bytes
        return d.bad_nodes, d.resyncs, d.skipped_bytes

    def _process(self, data: bytes, rx_ns: int) -> None:
        decoder = self._decoder
        express = isinstance(decoder, rp.ExpressNodeDecoder)
        before = self._decoder_stats()
        bad_before = self.counters["corrupt_revolutions"] + self.counters["incomplete_revolutions"]
        nodes = decoder.feed(data)
        bad, resyncs, skipped = (a - b for a, b in zip(self._decoder_stats(), before))
        self.counters["bad_capsules" if express else "bad_nodes"] += bad
        self.counters["resyncs"] += resyncs
        self.counters["skipped_bytes"] += skipped
        _, range_min, range_max = self.config.limits
        for rev in self._assembler.feed(nodes, rx_ns):
            self._bad_in_row = 0
            self.counters["scans"] += 1
            scan = revolution_scan(rev, self.config.beams, range_min, range_max, self.config.frame_id,
                                   intensities=not express)
            if self.sink(self.config.topic, scan, rx_ns) is False:
                self.counters["sink_drops"] += 1
        self._bad_in_row += self.counters["corrupt_revolutions"] + self.counters["incomplete_revolutions"] - bad_before

    def silence_reason(self) -> str:
        bad = self.counted(("corrupt_revolutions", "incomplete_revolutions", "bad_capsules", "bad_nodes",
                            "skipped_bytes", "timeouts"))
        return f"data, but no whole revolution ({bad})" if bad else "no scan data arrives"

    def diagnostics(self) -> m.DiagnosticStatus:
        base = super().diagnostics()
        extra = [("motor", self.motor), ("health", str(self.health.status) if self.health else "")]
        return m.DiagnosticStatus(base.level, base.name, base.message, self.hardware_id, base.values + tuple(extra))
