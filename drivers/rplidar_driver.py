"""Slamtec RPLIDAR driver (A1, A2, A3, C1, S1, S2, S3): any scan mode, one LaserScan per revolution.

Start-up stops a scan left running (STOP, wait, flush), checks health (RESET on error, then
give up as a hardware fault), reads GET_INFO, enumerates the scan modes with GET_LIDAR_CONF
(firmware 1.24 and later, and every C/S model; older firmware has Standard and Express, timed
by GET_SAMPLERATE), picks the typical mode unless the config names one, starts the motor the
way the model wants (rpm command on the S series, PWM through the accessory board on A2/A3,
DTR on A1; the C1 turns by itself; a pty's missing modem lines only cost a counter), starts
SCAN or EXPRESS_SCAN with the mode's working mode and checks the descriptor against the
mode's answer type. ``RevolutionAssembler`` (pure) turns the decoded samples into whole
revolutions and refuses any revolution touched by lost or corrupt bytes; ``revolution_scan``
bins one onto a fixed angular grid. Shutdown sends STOP and stops the motor.
"""

from __future__ import annotations

import math
import struct
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
import serial
from pydantic import Field, field_validator

from trundle.drivers import rplidar as rp
from trundle.drivers import rplidar_capsules as rc
from trundle.drivers.laser_mount import laser_transform
from trundle.drivers.lifecycle import Backoff, Driver, Sink, wall_ns
from trundle.drivers.serial_link import STREAM_BATCH_S, SerialLink, set_modem_line
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError
from trundle.logs.schema import Name, Schema
from trundle.logs.topics import SCAN_TOPIC, TF_STATIC_TOPIC


@dataclass(frozen=True)
class ModelSpec:
    """What the device does not report: default ``baud`` (sllidar_ros2 launch files), closest
    range (m) and, for firmware without scan modes, the farthest (datasheets)."""

    model_id: int
    baud: int
    range_min: float
    range_max: float


MODELS = {"a1": ModelSpec(0x18, 115200, 0.15, 12.0), "a2": ModelSpec(0x28, 115200, 0.15, 12.0),
          "a2m12": ModelSpec(0x2C, 256000, 0.2, 12.0), "a3": ModelSpec(0x31, 256000, 0.2, 25.0),
          "s1": ModelSpec(0x61, 256000, 0.1, 40.0), "s2": ModelSpec(0x71, 1000000, 0.05, 30.0),
          "s3": ModelSpec(0x81, 1000000, 0.05, 40.0), "c1": ModelSpec(0x41, 460800, 0.05, 12.0)}
SERIES = {"A": "a2", "C": "c1", "S": "s2"}  # for model ids not in MODELS
LEGACY_SAMPLE_US = 476  # the SDK's sample duration when nothing better is known
BAUDS = (115200, 256000, 460800, 1000000)  # the native rates of the A/S/C series
WRAP_Q6 = 16 * 64  # a clean wrap goes from the last 16 deg of a turn to its first 16 deg
DEFAULT_PWM, DEFAULT_RPM = 660, 600  # the SDK's values when the device does not say


def model_key(info: rp.DeviceInfo) -> str:
    """The ``MODELS`` key of a device, by model id, else by series (A, C, S)."""
    exact = next((k for k, spec in MODELS.items() if spec.model_id == info.model), None)
    return exact or SERIES.get(info.model_name[0], "a2")


class RplidarConfig(Schema):
    """Driver options (the ``[lrf]`` table of a robot config). Angles in radians, times in seconds.

    ``model`` (a key of ``MODELS``) sets the first baud rate tried and is checked against GET_INFO
    (the device's own answer wins); ``mode`` names a scan mode as the device lists it (Standard,
    Express, Boost, Sensitivity, Stability, DenseBoost, ...), "" for the model's typical mode;
    ``beams`` is the size of the published angular grid (0: the samples of the first whole
    revolution); ``motor_pwm`` (A2/A3) and ``motor_rpm`` (S series) set the motor speed (0: the
    device's desired speed). ``range_min``, ``range_max`` and ``baudrate`` default (0) to the
    model's and the mode's. ``error_limit`` bad revolutions in a row or ``timeout_s`` of silence
    force a reconnect (backing off up to ``backoff_max_s``); ``reply_timeout_s`` bounds each
    start-up reply, ``startup_timeout_s`` the scan's first answer.
    """

    port: Name
    model: str = ""
    baudrate: Annotated[int, Field(ge=0)] = 0
    mode: str = ""
    beams: int = 0
    frame_id: Name = "laser"
    parent_frame: Name = "base_link"
    topic: Name = SCAN_TOPIC
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0
    range_min: Annotated[float, Field(ge=0)] = 0.0
    range_max: Annotated[float, Field(ge=0)] = 0.0
    motor_pwm: Annotated[int, Field(ge=0, le=1023)] = 0
    motor_rpm: Annotated[int, Field(ge=0, le=0xFFFF)] = 0
    error_limit: Annotated[int, Field(ge=1)] = 4
    timeout_s: Annotated[float, Field(gt=0)] = 1.0
    startup_timeout_s: Annotated[float, Field(gt=0)] = 3.0
    reply_timeout_s: Annotated[float, Field(gt=0)] = 0.5
    backoff_max_s: Annotated[float, Field(gt=0)] = 0.5

    @field_validator("model")
    @classmethod
    def _model(cls, model: str) -> str:
        if model and model not in MODELS:
            raise ValueError(f"unknown RPLIDAR model (choose {', '.join(MODELS)})")
        return model

    @field_validator("beams")
    @classmethod
    def _beams(cls, beams: int) -> int:
        if beams and not 8 <= beams <= rp.FULL_CIRCLE_Q6:
            raise ValueError(f"expected 0 (one per sample) or 8-{rp.FULL_CIRCLE_Q6}")
        return beams

    @property
    def first_baud(self) -> int:
        return self.baudrate or (MODELS[self.model].baud if self.model else BAUDS[0])


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
    boundaries are clean wraps (no lost bytes there, the turret angle falls from its last 16
    degrees to its first 16), no bytes were lost inside it, and its turret angles (``encoder_q6``)
    advance, never backwards and without a gap wider than five typical steps; its samples keep
    their measurement angles (``angle_q6``) for binning. Counters, for revolutions that
    began with a clean wrap: ``corrupt_revolutions`` (lost or bad bytes inside or at the end),
    ``incomplete_revolutions`` (angle gaps); ``late_data`` counts start samples that arrived
    over 50 ms later than the sample clock predicts.

    Times come from the sample clock (``sample_ns`` apart, lost bytes counted as the samples
    they held), re-anchored on the earliest receive time seen, so data held up by the host or a
    USB hiccup is not stamped late. The newest
    sample of a chunk is taken as measured at its receive time, ``lag_samples`` after the last
    sample the decoder hands over (capsules are held back two at a time).
    """

    sample_ns: int
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
                self._parts.append(nodes.slice(pos, b))
                self._prev_angle = self._last_angle = int(nodes.encoder_q6[b - 1])
                self._since_anchor += b - pos
            if b == n:
                break
            pos = b
            if nodes.broken[b]:
                self._since_anchor += self._lost(int(nodes.encoder_q6[b]))
                self._clean, self._prev_angle = False, None
            if nodes.start[b]:
                wrap = (not nodes.broken[b] and self._prev_angle is not None
                        and self._prev_angle >= rp.FULL_CIRCLE_Q6 - WRAP_Q6 and nodes.encoder_q6[b] < WRAP_Q6)
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
        encoder = np.concatenate([p.encoder_q6 for p in parts])
        step = np.diff(encoder)
        limit = max(5 * float(np.median(step)) if step.size else 0.0, 2.0 * 64)
        if (encoder.size < 8 or step.max() > limit or step.min() < 0 or encoder[0] > limit
                or encoder[-1] < rp.FULL_CIRCLE_Q6 - limit):
            self.counters["incomplete_revolutions"] += 1
            return None
        self._step_q6 = rp.FULL_CIRCLE_Q6 / encoder.size
        return Revolution(np.concatenate([p.angle_q6 for p in parts]), np.concatenate([p.distance_q2 for p in parts]),
                          np.concatenate([p.quality for p in parts]), self._start_ns, encoder.size * self.sample_ns)


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
                "health_warnings", "health_resets", "modem_lines_unsupported", "model_mismatches",
                "conf_unanswered", "sink_drops")

    def __init__(self, config: RplidarConfig, sink: Sink, *, clock: Callable[[], int] = wall_ns,
                 name: str = "lrf") -> None:
        super().__init__(name, sink, hardware_id=config.port, backoff=Backoff(0.1, config.backoff_max_s), clock=clock)
        self.config = config
        self.serial_port = "" if "://" in config.port else config.port
        self.counters.update({k: 0 for k in self.COUNTERS})
        self.info: rp.DeviceInfo | None = None
        self.health: rp.Health | None = None
        self.modes: list[rp.ScanMode] = []
        self.scan_mode: rp.ScanMode | None = None
        self.motor = ""
        self.link: SerialLink | None = None
        self.beams = config.beams
        self._buf = bytearray()
        self._decoder: rp.NodeDecoder | rc.CapsuleNodeDecoder = rp.NodeDecoder()
        self._assembler = RevolutionAssembler(LEGACY_SAMPLE_US * 1000, counters=self.counters)
        self._limits = (0.0, 0.0)
        self._intensities = True
        self._modes_from_conf = False
        self._bad_in_row = 0
        self._static = laser_transform(config, clock())

    def static_messages(self) -> list[tuple[str, m.Message]]:
        return [(TF_STATIC_TOPIC, self._static)]

    # --- transport ---------------------------------------------------------------------------

    def _read(self) -> bytes:
        if self.link is None:
            raise DeviceError("port closed")
        return self.link.read()

    def _send(self, command: int, payload: bytes | None = None) -> None:
        assert self.link is not None
        self.link.write(rp.request(command, payload))

    def _answer(self, answer_type: int, timeout_s: float | None = None, mode: int = rp.SINGLE,
                length: int | None = None) -> bytes:
        """Wait for a descriptor of ``answer_type`` and ``mode`` (skipping and counting other
        bytes); return its payload (single) or the bytes that followed it (multiple). A multiple
        answer must announce ``length`` bytes per packet."""
        deadline = time.monotonic() + (timeout_s or self.config.reply_timeout_s)
        while time.monotonic() < deadline and not self.stopping:
            at = self._buf.find(bytes((rp.SYNC, rp.SYNC2)))
            while 0 <= at <= len(self._buf) - rp.DESCRIPTOR_SIZE:
                head = rp.Descriptor.parse(bytes(self._buf[at:at + rp.DESCRIPTOR_SIZE]))
                if head.type == answer_type and head.mode == mode:
                    if mode == rp.MULTIPLE:
                        if length is not None and head.length != length:
                            raise DeviceError(f"answer {answer_type:#04x} announces {head.length}-byte packets, "
                                              f"not {length}: not a format this driver knows")
                        self.counters["drained_bytes"] += at
                        rest, self._buf = bytes(self._buf[at + rp.DESCRIPTOR_SIZE:]), bytearray()
                        return rest
                    end = at + rp.DESCRIPTOR_SIZE + head.length
                    if len(self._buf) < end:
                        break
                    self.counters["drained_bytes"] += at
                    payload = bytes(self._buf[at + rp.DESCRIPTOR_SIZE:end])
                    del self._buf[:end]
                    return payload
                at = self._buf.find(bytes((rp.SYNC, rp.SYNC2)), at + 1)
            self._buf += self._read()
        raise DeviceError(f"no {answer_type:#04x} answer from {self.config.port} "
                          f"(wrong port or baud rate {self.link.port.baudrate if self.link else '?'}?)")

    def _flush(self, quiet_s: float = 0.02) -> int:
        """Drop input until the line has been quiet for ``quiet_s``; returns how many bytes."""
        assert self.link is not None
        dropped = len(self._buf)
        self._buf.clear()
        return dropped + self.link.drain(quiet_s)

    # --- start-up ----------------------------------------------------------------------------

    def open(self) -> None:
        self.link = SerialLink(self.config.port, self.config.first_baud)
        self._buf = bytearray()
        self._send(rp.STOP)
        time.sleep(0.01)
        drained = self._flush()
        self.counters["drained_bytes"] += drained
        if drained:
            self.counters["stale_streams"] += 1
        self._check_health()
        self._send(rp.GET_INFO)
        self.info = info = rp.DeviceInfo.parse(self._answer(rp.ANS_INFO))
        self.hardware_id = (f"RPLIDAR {info.model_name} (model {info.model:#04x}) fw {info.firmware[0]}."
                            f"{info.firmware[1]:02d} hw {info.hardware} sn {info.serial.hex().upper()}")
        key = model_key(info)
        if self.config.model and self.config.model != key:
            self.counters["model_mismatches"] += 1
        self.modes, typical = self._scan_modes(MODELS[key])
        mode = self._choose(typical)
        self._start_motor()
        self._start_scan(mode, MODELS[key])

    def _health(self) -> rp.Health:
        """GET_HEALTH; with no answer, try the other RPLIDAR bauds (a wrong baud is the usual
        cause of "Descriptor length mismatch") before giving up with one line naming them."""
        assert self.link is not None
        bauds = [self.link.port.baudrate] + [b for b in BAUDS if b != self.link.port.baudrate]
        for baud in bauds if "://" not in self.config.port else bauds[:1]:
            self.link.port.baudrate = baud
            self._send(rp.GET_HEALTH)
            try:
                return rp.Health.parse(self._answer(rp.ANS_HEALTH))
            except DeviceError:
                self._buf.clear()
        raise DeviceError(f"no RPLIDAR answer on {self.config.port} at {', '.join(map(str, bauds))} baud "
                          "(wrong port, not an RPLIDAR, or no permission?)")

    def _check_health(self) -> None:
        for attempt in range(2):
            self.health = health = self._health()
            if health.status == rp.HEALTH_WARNING:
                self.counters["health_warnings"] += 1
            if health.status != rp.HEALTH_ERROR:
                return
            if attempt == 0:
                self.counters["health_resets"] += 1
                self._send(rp.RESET)
                time.sleep(0.02)
                self._flush(quiet_s=0.05)  # the device prints a text banner after a reset
        raise DeviceError(f"RPLIDAR hardware fault: health error code {health.error_code:#06x} after RESET")

    def _conf(self, entry: int, mode: int | None = None) -> bytes:
        """One GET_LIDAR_CONF entry's value."""
        self._send(rp.GET_LIDAR_CONF, rp.conf_request(entry, mode))
        return rp.parse_conf(entry, self._answer(rp.ANS_CONF))

    def _scan_modes(self, spec: ModelSpec) -> tuple[list[rp.ScanMode], int]:
        """The device's scan modes and the id of its typical one; firmware without GET_LIDAR_CONF
        (or not answering it) has Standard and, from 1.17, Express, timed by GET_SAMPLERATE."""
        assert self.info is not None
        if self.info.supports_conf:
            try:
                count = struct.unpack("<H", self._conf(rp.CONF_SCAN_MODE_COUNT)[:2])[0]
                typical = struct.unpack("<H", self._conf(rp.CONF_SCAN_MODE_TYPICAL)[:2])[0]
                modes = [rp.ScanMode.from_conf(i, {e: self._conf(e, i) for e in rp.MODE_ENTRIES}) for i in range(count)]
                self._modes_from_conf = True
                return [self._timed(mode) for mode in modes], min(typical, max(count - 1, 0))
            except (DeviceError, struct.error):
                self.counters["conf_unanswered"] += 1
        self._modes_from_conf = False
        standard, express = self._sample_rates()
        modes = [rp.ScanMode(0, "Standard", standard, spec.range_max, rp.ANS_MEASUREMENT)]
        if self.info.firmware >= (1, 17):
            modes.append(rp.ScanMode(1, "Express", express, spec.range_max, rp.ANS_CAPSULED))
        return modes, len(modes) - 1

    def _sample_rates(self) -> tuple[float, float]:
        """GET_SAMPLERATE (firmware 1.17 and later): microseconds a sample in SCAN and EXPRESS_SCAN."""
        assert self.info is not None
        if self.info.firmware >= (1, 17) or self.info.major_model >= 4:
            self._send(rp.GET_SAMPLERATE)
            try:
                standard, express = struct.unpack("<HH", self._answer(rp.ANS_SAMPLERATE))
                return float(standard or LEGACY_SAMPLE_US), float(express or LEGACY_SAMPLE_US)
            except (DeviceError, struct.error):
                pass
        return float(LEGACY_SAMPLE_US), float(LEGACY_SAMPLE_US)

    def _timed(self, mode: rp.ScanMode) -> rp.ScanMode:
        """A mode whose sample duration the device reported as 0 (seen on S3 firmware 1.02,
        Slamtec/rplidar_ros #155) gets GET_SAMPLERATE's figure instead."""
        if mode.us_per_sample > 0:
            return mode
        standard, express = self._sample_rates()
        us = standard if mode.answer_type == rp.ANS_MEASUREMENT else express
        return rp.ScanMode(mode.id, mode.name, us, mode.max_distance, mode.answer_type)

    def _choose(self, typical: int) -> rp.ScanMode:
        """The configured mode (by name, any case) or the typical one."""
        wanted = self.config.mode.strip().lower()
        if not wanted:
            return self.modes[typical]
        for mode in self.modes:
            if mode.name.lower() == wanted:
                return mode
        assert self.info is not None
        raise DeviceError(f"RPLIDAR {self.info.model_name} has no scan mode {self.config.mode!r}; "
                          f"it offers {', '.join(mode.name for mode in self.modes)}")

    def _start_motor(self) -> None:
        """S series: rpm command; A2/A3: PWM if the accessory board says so, else DTR (A1);
        C series without the accessory flag: the motor follows the scan, nothing to do."""
        assert self.info is not None and self.link is not None
        major = self.info.major_model
        if major >= 6:
            self.motor = "rpm"
            self._send(rp.HQ_MOTOR_SPEED_CTRL, struct.pack("<H", self.config.motor_rpm or self._desired()[0]))
            return
        flags = 0
        if major >= 2:
            self._send(rp.GET_ACC_BOARD_FLAG, bytes(4))
            try:
                flags = int.from_bytes(self._answer(rp.ANS_ACC_BOARD_FLAG, 0.2), "little")
            except DeviceError:
                flags = 0
        if flags & 1:
            self.motor = "pwm"
            self._send(rp.SET_MOTOR_PWM, struct.pack("<H", self.config.motor_pwm or self._desired()[1]))
        elif major >= 4:
            self.motor = "none"
        else:
            self.motor = "dtr"
            if not set_modem_line(self.link.port, "dtr", False):  # SDK: DTR cleared = motor runs
                self.counters["modem_lines_unsupported"] += 1

    def _desired(self) -> tuple[int, int]:
        """The device's desired (rpm, PWM) from GET_LIDAR_CONF, else the SDK's defaults."""
        assert self.info is not None
        if self.info.supports_conf:
            try:
                rpm, pwm = struct.unpack("<HH", self._conf(rp.CONF_DESIRED_ROT_FREQ)[:4])
                return rpm or DEFAULT_RPM, pwm or DEFAULT_PWM
            except (DeviceError, struct.error):
                pass
        return DEFAULT_RPM, DEFAULT_PWM

    def _start_scan(self, mode: rp.ScanMode, spec: ModelSpec) -> None:
        """SCAN for the standard answer type, else EXPRESS_SCAN with the mode's working mode
        (0, the legacy express scan, without scan modes); the descriptor must match."""
        assert self.info is not None
        fmt = rc.FORMATS.get(mode.answer_type)
        if mode.answer_type == rp.ANS_MEASUREMENT:
            self._send(rp.SCAN)
        elif fmt is None:
            raise DeviceError(f"scan mode {mode.name} answers {mode.answer_type:#04x}, a format this driver "
                              "does not know")
        else:
            working_mode = mode.id if self._modes_from_conf else 0
            self._send(rp.EXPRESS_SCAN, struct.pack("<BHH", working_mode, 0, 0))
        rest = self._answer(mode.answer_type, self.config.startup_timeout_s, rp.MULTIPLE,
                            fmt.size if fmt else rp.NODE_SIZE)
        self.scan_mode = mode
        self._decoder = rc.CapsuleNodeDecoder(fmt) if fmt else rp.NodeDecoder()
        self._assembler = RevolutionAssembler(round(mode.us_per_sample * 1000),
                                              lag_samples=fmt.hold * fmt.samples if fmt else 0, counters=self.counters)
        self._intensities = fmt is None or fmt.quality
        self._limits = (self.config.range_min or spec.range_min,
                        self.config.range_max or mode.max_distance or spec.range_max)
        self._bad_in_row = 0
        assert self.link is not None
        self.link.batch_s = STREAM_BATCH_S
        if rest:
            self._process(rest, self.clock())

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
        if isinstance(d, rc.CapsuleNodeDecoder):
            return d.framer.bad_capsules, d.framer.resyncs, d.framer.skipped_bytes
        return d.bad_nodes, d.resyncs, d.skipped_bytes

    def _process(self, data: bytes, rx_ns: int) -> None:
        decoder = self._decoder
        before = self._decoder_stats()
        bad_before = self.counters["corrupt_revolutions"] + self.counters["incomplete_revolutions"]
        nodes = decoder.feed(data)
        bad, resyncs, skipped = (a - b for a, b in zip(self._decoder_stats(), before, strict=True))
        self.counters["bad_capsules" if isinstance(decoder, rc.CapsuleNodeDecoder) else "bad_nodes"] += bad
        self.counters["resyncs"] += resyncs
        self.counters["skipped_bytes"] += skipped
        range_min, range_max = self._limits
        for rev in self._assembler.feed(nodes, rx_ns):
            self._bad_in_row = 0
            self.counters["scans"] += 1
            self.beams = self.beams or int(rev.angle_q6.size)
            scan = revolution_scan(rev, self.beams, range_min, range_max, self.config.frame_id,
                                   intensities=self._intensities)
            if self.sink(self.config.topic, scan, rx_ns) is False:
                self.counters["sink_drops"] += 1
        self._bad_in_row += self.counters["corrupt_revolutions"] + self.counters["incomplete_revolutions"] - bad_before

    def silence_reason(self) -> str:
        bad = self.counted(("corrupt_revolutions", "incomplete_revolutions", "bad_capsules", "bad_nodes",
                            "skipped_bytes", "timeouts"))
        return f"data, but no whole revolution ({bad})" if bad else "no scan data arrives"

    def diagnostics(self) -> m.DiagnosticStatus:
        base = super().diagnostics()
        mode = self.scan_mode
        extra = [("motor", self.motor), ("health", str(self.health.status) if self.health else ""),
                 ("scan_mode", mode.name if mode else ""),
                 ("answer_type", f"{mode.answer_type:#04x}" if mode else ""),
                 ("us_per_sample", f"{mode.us_per_sample:g}" if mode else ""),
                 ("scan_modes", ", ".join(f"{x.name} ({x.answer_type:#04x}, {x.us_per_sample:g} us, "
                                          f"{x.max_distance:g} m)" for x in self.modes)),
                 ("beams", str(self.beams))]
        return m.DiagnosticStatus(base.level, base.name, base.message, self.hardware_id, base.values + tuple(extra))
