"""Hokuyo SCIP 2.0 laser driver (URG-04LX, UTM-30LX on USB; UST/UTM-EW over TCP via ``socket://``).

Start-up stops whatever the sensor was doing (QT and drain; TM2 in time-adjust mode; SCIP2.0
after a SCIP 1.1 answer; RB twice in the abnormal state), reads PP/VV/II, synchronises the
clock with TM0/TM1/TM2 round trips, then streams MD (ME with intensities). Each scan becomes a
``LaserScan`` on ``/scan`` stamped with the host time of its first beam; corrupt replies are
counted and dropped, never published. ``ScipScanStream`` is the pure part (bytes in, scans
out) so it can be tested without a device.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from trundle.drivers import scip2
from trundle.drivers.laser_mount import laser_transform
from trundle.drivers.lifecycle import Backoff, Driver, Sink, wall_ns
from trundle.drivers.scip2 import Measure, Reply, ScipError, ScipFramer, SensorParams
from trundle.drivers.sensor_clock import SensorClock
from trundle.drivers.serial_link import STREAM_BATCH_S, SerialLink
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError
from trundle.logs.schema import Name, Schema
from trundle.logs.topics import SCAN_TIMING_TOPIC, SCAN_TOPIC, TF_STATIC_TOPIC

ABNORMAL = {"0L"} | {f"{n:02d}" for n in range(21, 98)}  # stop, reboot with RB (notes 1.6.5)
RESUMED = "98"
UNSTABLE = "0M"


class ScipConfig(Schema):
    """Driver options (the ``[lrf]`` table of a robot config). Angles in radians, times in seconds.

    ``port`` is a device path or a pyserial URL (``socket://host:10940``). ``angle_min``/``angle_max``
    narrow the scan (default: the sensor's whole range), ``cluster`` merges steps, ``skip`` drops
    scans between two sent, ``intensity`` asks for ME. ``x, y, z, yaw`` place ``frame_id`` in
    ``parent_frame``. ``error_limit`` consecutive bad scans force a reconnect (urg_node uses 4);
    ``timeout_s`` of silence too (default 16 scan periods, at least 0.5 s, as urg_c).
    ``timing_topic`` ("" for none) carries raw and derived times of every scan. ``tm_samples``
    TM1 round trips set the clock (0: anchor on receive times); ``reply_timeout_s`` bounds each
    start-up reply; reconnects back off up to ``backoff_max_s``.
    """

    port: Name
    baudrate: Annotated[int, Field(gt=0)] = 115200
    frame_id: Name = "laser"
    parent_frame: Name = "base_link"
    topic: Name = SCAN_TOPIC
    timing_topic: Name = SCAN_TIMING_TOPIC
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw: float = 0.0
    angle_min: float | None = None
    angle_max: float | None = None
    cluster: Annotated[int, Field(ge=1, le=99)] = 1
    skip: Annotated[int, Field(ge=0, le=9)] = 0
    intensity: bool = False
    error_limit: Annotated[int, Field(ge=1)] = 4
    timeout_s: Annotated[float, Field(gt=0)] | None = None
    tm_samples: Annotated[int, Field(ge=0)] = 10
    reply_timeout_s: Annotated[float, Field(gt=0)] = 0.5
    backoff_max_s: Annotated[float, Field(gt=0)] = 0.5

    @model_validator(mode="after")
    def _angles(self) -> ScipConfig:
        if self.angle_min is not None and self.angle_max is not None and self.angle_min >= self.angle_max:
            raise ValueError(f"angle_min {self.angle_min} must be below angle_max {self.angle_max}")
        return self


def error_code_ranges(model: str, dmin: int) -> np.ndarray:
    """REP 117 value (m) of each code below DMIN for a model: +inf no echo, -inf too near, NaN error.

    URG-04LX: 0 = nothing within 22 m, 1-19 errors. UTM/UST: 1 = no object, 2 = too near,
    3 = interference, 4-5 other errors (lrf-protocols.md 1.5).
    """
    table = np.full(max(dmin, 1), np.nan, np.float32)
    if "URG-04LX" in model.upper():
        table[0] = np.inf
    else:
        table[1:2] = np.inf
        table[2:3] = -np.inf
    return table


@dataclass
class Timing:
    """Raw and derived times of one scan, for the timing topic and offline re-computation."""

    raw: int
    unwrapped: int
    host_rx_ns: int
    offset_ns: int
    drift_ppm: float
    event: str


@dataclass
class ScipScanStream:
    """Replies of an MD/ME stream -> LaserScans, counting and dropping every defect.

    ``counters``: scans, checksum_errors, truncated, format_errors, unstable, status_errors,
    abnormal, stalls and missed_scans (gaps in the sensor's timestamps not explained by a
    dropped reply), resyncs and garbage_bytes (bytes skipped between replies), clock_wraps,
    clock_resets, clock_resyncs. ``consecutive_errors`` resets on a good scan only.
    ``fault_status`` is set to the first abnormal status seen (the driver must reboot the sensor).
    After a clock reset the offset can only be re-anchored on receive times; with
    ``hold_after_reset`` the stream stops returning scans from then on (counting them as
    ``unsynced_scans``) and sets ``unsynced`` so the driver can synchronise the clock again.
    """

    params: SensorParams
    measure: Measure
    clock: SensorClock
    frame_id: str = "laser"
    framer: ScipFramer = field(default_factory=ScipFramer)
    counters: Counter = field(default_factory=Counter)
    consecutive_errors: int = 0
    fault_status: str | None = None
    hold_after_reset: bool = False
    unsynced: bool = False

    def __post_init__(self) -> None:
        p, ms = self.params, self.measure
        self.framer.expect(*{ms.echo(k) for k in ([0] if ms.scans == 0 else range(ms.scans))})
        self.codes = error_code_ranges(p.model, p.dmin)
        self.period_ns = int(round(p.scan_period_s * 1e9))
        self.slot_ms = p.scan_period_s * 1000.0 * (ms.skip + 1)
        rear_step = p.afrt - p.ares / 2.0
        self.first_beam_ns = int(round((ms.start - rear_step) / p.ares * self.period_ns))
        cluster = max(ms.cluster, 1)
        self.scan = partial(m.LaserScan, frame_id=self.frame_id, angle_min=float(p.step_angle(ms.start)),
                            angle_max=float(p.step_angle(ms.start + (ms.beams - 1) * cluster)),
                            angle_increment=2.0 * np.pi * cluster / p.ares,
                            time_increment=cluster * p.scan_period_s / p.ares,
                            scan_time=p.scan_period_s * (ms.skip + 1),
                            range_min=p.dmin / 1000.0, range_max=p.dmax / 1000.0)
        self._last_ts: int | None = None
        self._unreadable = 0

    def ranges(self, distances: np.ndarray) -> np.ndarray:
        """Millimetres and error codes -> metres with REP 117 invalid values."""
        out = (distances / 1000.0).astype(np.float32)  # the float32 nearest each millimetre value
        low = distances < self.params.dmin
        if low.any():
            out[low] = self.codes[np.minimum(distances[low], self.codes.size - 1)]
        high = distances > self.params.dmax
        if high.any():
            out[high] = np.inf
        return out

    def feed(self, data: bytes, host_rx_ns: int) -> list[tuple[m.LaserScan, Timing]]:
        """Add bytes received at ``host_rx_ns``; return the good scans they complete."""
        before = self.framer.resyncs, self.framer.garbage_bytes
        out = [scan for reply in self.framer.feed(data) if (scan := self._reply(reply, host_rx_ns)) is not None]
        self.counters["resyncs"] += self.framer.resyncs - before[0]
        self.counters["garbage_bytes"] += self.framer.garbage_bytes - before[1]
        return out

    def _bad(self, kind: str) -> None:
        self.counters[kind] += 1
        self.consecutive_errors += 1

    def _reply(self, reply: Reply, host_rx_ns: int) -> tuple[m.LaserScan, Timing] | None:
        try:
            status = reply.status
        except ScipError as error:
            self._unreadable += 1
            self._bad("checksum_errors" if error.kind == "checksum" else "truncated")
            return None
        if status == UNSTABLE:
            self.counters["unstable"] += 1
            self._unreadable += 1
            return None
        if status in ABNORMAL:
            self.counters["abnormal"] += 1
            self.fault_status = self.fault_status or status
            return None
        if status == RESUMED:
            self.counters["resumed"] += 1
            return None
        if status not in ("99", "00"):
            self._unreadable += 1
            self._bad("status_errors")
            return None
        timing = self._timestamp(reply, host_rx_ns)
        if timing is None:
            return None
        try:  # status and timestamp are checked: only the data lines are left
            distances, intensity = scip2.decode_measurement(reply.body, self.measure)
        except ScipError as error:
            self._bad({"checksum": "checksum_errors", "format": "format_errors"}.get(error.kind, "truncated"))
            return None
        self.consecutive_errors = 0
        if self.unsynced:
            self.counters["unsynced_scans"] += 1
            return None
        self.counters["scans"] += 1
        stamp = self.clock.host_ns(timing.unwrapped) + self.first_beam_ns
        intensities = intensity.astype(np.float32) if intensity is not None else np.zeros(0, np.float32)
        return self.scan(stamp, ranges=self.ranges(distances), intensities=intensities), timing

    def _timestamp(self, reply: Reply, host_rx_ns: int) -> Timing | None:
        """Read the timestamp line, feed the clock, account for scans that never came."""
        line = reply.body[4:10]
        try:
            if len(line) != 6 or line[-1] != scip2.LF:
                raise ScipError("truncated", "timestamp line")
            raw = scip2.decode_value(scip2.verify_line(line[:-1]))
        except ScipError as error:
            self._unreadable += 1
            self._bad({"checksum": "checksum_errors", "format": "format_errors"}.get(error.kind, "truncated"))
            return None
        reading = self.clock.update(raw, host_rx_ns)
        if reading.event:
            self.counters[
                {"wrap": "clock_wraps", "reset": "clock_resets", "resync": "clock_resyncs"}[reading.event]
            ] += 1
        if reading.event == "reset" and self.hold_after_reset:
            self.unsynced = True
        if self._last_ts is not None and reading.event != "reset":
            missing = round((reading.unwrapped - self._last_ts) / self.slot_ms) - 1 - self._unreadable
            if missing > 0:
                self.counters["stalls"] += 1
                self.counters["missed_scans"] += missing
        self._last_ts, self._unreadable = reading.unwrapped, 0
        return Timing(raw, reading.unwrapped, host_rx_ns, reading.offset_ns, self.clock.drift_ppm, reading.event)


class ScipDriver(Driver):
    """The SCIP 2.0 life cycle on a pyserial port (see the module docstring)."""

    COUNTERS = ("scans", "checksum_errors", "truncated", "format_errors", "unstable", "status_errors", "abnormal",
                "stalls", "missed_scans", "resyncs", "garbage_bytes", "timeouts", "reboots", "drained_bytes",
                "stale_streams", "clock_wraps", "clock_resets", "clock_resyncs", "tm_syncs", "unsynced_scans",
                "sink_drops")

    def __init__(self, config: ScipConfig, sink: Sink, *, clock: Callable[[], int] = wall_ns,
                 name: str = "lrf") -> None:
        super().__init__(name, sink, hardware_id=config.port, backoff=Backoff(0.1, config.backoff_max_s), clock=clock)
        self.config = config
        self.serial_port = "" if "://" in config.port else config.port
        self.counters.update({k: 0 for k in self.COUNTERS})
        self.sensor_clock = SensorClock()
        self.params: SensorParams | None = None
        self.version: dict[str, str] = {}
        self.state_info: dict[str, str] = {}
        self.stream: ScipScanStream | None = None
        self.link: SerialLink | None = None
        self._framer = ScipFramer()
        self._session = 0
        self._static = laser_transform(config, clock())

    def static_messages(self) -> list[tuple[str, m.Message]]:
        return [(TF_STATIC_TOPIC, self._static)]

    # --- transport ---------------------------------------------------------------------------

    def open(self) -> None:
        self.link = SerialLink(self.config.port, self.config.baudrate)
        self._framer = ScipFramer()
        self._handshake()

    def close(self) -> None:
        link, self.link = self.link, None
        if link is not None:
            link.close(lambda port: port.write(b"QT\n"))

    def _read(self) -> bytes:
        if self.link is None:
            raise DeviceError("port closed")
        return self.link.read()

    def _request(self, command: bytes, timeout_s: float | None = None) -> Reply:
        """Send one command and return its reply (other bytes are skipped and counted)."""
        echo = command.rstrip(b"\n")
        self._framer.expect(echo)
        assert self.link is not None
        self.link.write(command)
        deadline = time.monotonic() + (timeout_s or self.config.reply_timeout_s)
        while time.monotonic() < deadline and not self.stopping:
            replies = self._framer.feed(self._read())
            if replies:
                return replies[0]
        raise DeviceError(f"no reply to {echo.decode('latin-1')} from {self.config.port}")

    # --- start-up ----------------------------------------------------------------------------

    def _handshake(self) -> None:
        garbage = self._framer.garbage_bytes
        self._stop_sensor()
        self._framer.clear()
        assert self.link is not None
        drained = self._framer.garbage_bytes - garbage + self.link.drain(0.05)
        self.counters["drained_bytes"] += drained
        if drained:
            self.counters["stale_streams"] += 1
        self.params = self._params()
        self.version = self._info(b"VV\n")
        self.state_info = self._info(b"II\n")
        self.hardware_id = " ".join(v for v in (self.params.model, self.version.get("SERI", ""),
                                                self.version.get("FIRM", "")) if v)
        self._sync_clock()
        self._start_stream()

    def _stop_sensor(self) -> None:
        """QT until the sensor answers 00: TM2 out of time-adjust, SCIP2.0 out of SCIP 1.1, RB if abnormal."""
        for _ in range(4):
            reply = self._request_any_baud(b"QT\n")
            try:
                status = self._status(reply)
            except DeviceError:   # a stale stream's data line can end in "QT": the next QT's echo is the real one
                status = "unreadable"
                continue
            if status == "00":
                return
            if status == "0E":
                self._request(b"TM2\n")
            elif status == "E":
                self._request(b"SCIP2.0\n")
            elif status in ABNORMAL:
                self.counters["abnormal"] += 1
                self._reboot(status)
        raise DeviceError(f"sensor on {self.config.port} does not stop (QT status {status})")

    def _request_any_baud(self, command: bytes) -> Reply:
        """Send ``command``; with no answer try the other SCIP bauds (urg_c), except over TCP."""
        assert self.link is not None
        bauds = [self.config.baudrate] + [b for b in (19200, 38400, 115200) if b != self.config.baudrate]
        if "://" in self.config.port:
            bauds = bauds[:1]
        for baud in bauds:
            if self.link.port.baudrate != baud:
                self.link.port.baudrate = baud
            try:
                return self._request(command)
            except DeviceError:
                continue
        raise DeviceError(f"no SCIP answer on {self.config.port} at {', '.join(map(str, bauds))} baud "
                          "(wrong port, not a Hokuyo, or no permission?)")

    def _status(self, reply: Reply) -> str:
        try:
            return reply.status
        except ScipError as error:
            raise DeviceError(f"bad reply to {reply.echo!r}: {error}") from None

    def _info(self, command: bytes) -> dict[str, str]:
        reply = self._request(command)
        if self._status(reply) != "00":
            raise DeviceError(f"{command.strip().decode()} refused with status {self._status(reply)}")
        try:
            return scip2.parse_info(reply)
        except ScipError as error:
            raise DeviceError(f"bad {command.strip().decode()} reply: {error}") from None

    def _params(self) -> SensorParams:
        try:
            return SensorParams.from_info(self._info(b"PP\n"))
        except ScipError as error:
            raise DeviceError(str(error)) from None

    def _reboot(self, status: str) -> None:
        """RB twice within a second; the sensor then drops the link and restarts."""
        first = self._status(self._request(b"RB\n"))
        try:
            second = self._status(self._request(b"RB\n"))
        except (DeviceError, OSError):  # the sensor restarts at once: the link can drop before its reply is read
            second = "none, the link dropped"
        self.counters["reboots"] += 1
        raise DeviceError(
            f"sensor in abnormal state (status {status}); rebooted it with RB (replies {first}, {second})"
        )

    def _sync_clock(self) -> None:
        """TM0, N x TM1 round trips (median offset), TM2; without TM, anchor on the first scan."""
        self.sensor_clock = SensorClock()
        if not self.config.tm_samples or self._status(self._request(b"TM0\n")) not in ("00", "02"):
            return
        samples = []
        try:
            for _ in range(self.config.tm_samples):
                sent = self.clock()
                reply = self._request(b"TM1\n")
                received = self.clock()
                if self._status(reply) != "00" or len(reply.lines()) != 1:
                    continue
                try:
                    raw = scip2.decode_value(scip2.verify_line(reply.lines()[0]))
                except ScipError:
                    continue
                samples.append((sent, raw, received))
        finally:
            self._request(b"TM2\n")
        if samples:
            self.sensor_clock.synchronise(samples)
            self.counters["tm_syncs"] += 1

    def _start_stream(self) -> None:
        assert self.params is not None
        p, c = self.params, self.config
        start = p.amin if c.angle_min is None else p.angle_step(c.angle_min)
        end = p.amax if c.angle_max is None else p.angle_step(c.angle_max)
        self._session += 1
        measure = Measure("ME" if c.intensity else "MD", start, max(end, start), c.cluster, c.skip, 0,
                          f"trundle{self._session % 1000}")
        status = self._status(self._request(measure.encode()))
        if status in ABNORMAL:
            self.counters["abnormal"] += 1
            self._reboot(status)
        if status != "00":
            what = "intensities (ME)" if c.intensity else "MD streaming"
            raise DeviceError(f"{p.model} refused {what} {measure.encode().strip().decode()} with status {status}")
        self.stream = ScipScanStream(p, measure, self.sensor_clock, c.frame_id, self._framer, self.counters,
                                     hold_after_reset=self.sensor_clock.synced)
        assert self.link is not None
        self.link.batch_s = STREAM_BATCH_S  # a scan's halves in one read; 0 again for the next TM sync

    # --- streaming ---------------------------------------------------------------------------

    def read_once(self) -> None:
        stream = self.stream
        assert stream is not None and self.params is not None
        data = self._read()
        host_rx = self.clock()
        for scan, timing in stream.feed(data, host_rx) if data else ():
            if self.sink(self.config.topic, scan, host_rx) is False:
                self.counters["sink_drops"] += 1
            if self.config.timing_topic:
                self._publish_timing(scan.stamp_ns, timing)
        if stream.fault_status is not None:
            self._reboot(stream.fault_status)
        if stream.unsynced:
            self._resync_clock()
        if stream.consecutive_errors >= self.config.error_limit:
            stream.consecutive_errors = 0
            raise DeviceError(f"{self.config.error_limit} bad scans in a row")
        timeout = self.config.timeout_s or max(0.5, 16 * self.params.scan_period_s)
        if self.link is not None and self.link.silent_s > timeout:
            self.counters["timeouts"] += 1
            raise DeviceError(f"no data from {self.config.port} for {timeout:.2f} s")

    def _resync_clock(self) -> None:
        """The sensor clock restarted under a running stream: stop it, TM-synchronise, restart."""
        assert self.link is not None
        self.link.batch_s = 0.0  # round trips timed as they come
        self._request(b"QT\n")
        self._framer.clear()
        self.link.drain(0.05)
        self._sync_clock()
        self._start_stream()

    def _publish_timing(self, stamp_ns: int, t: Timing) -> None:
        status = m.DiagnosticStatus(m.OK, f"{self.name} timing", t.event, self.hardware_id, (
            ("raw_ms", str(t.raw)), ("unwrapped_ms", str(t.unwrapped)), ("host_rx_ns", str(t.host_rx_ns)),
            ("host_rx_monotonic_ns", str(time.monotonic_ns())), ("offset_ns", str(t.offset_ns)),
            ("drift_ppm", f"{t.drift_ppm:.3f}")))
        self.sink(self.config.timing_topic, m.DiagnosticArray(stamp_ns, (status,)), t.host_rx_ns)

    def silence_reason(self) -> str:
        bad = self.counted(("checksum_errors", "truncated", "format_errors", "status_errors", "unstable", "abnormal",
                            "timeouts", "garbage_bytes"))
        return f"replies, but no valid scans ({bad})" if bad else "no scan data arrives"

    def diagnostics(self) -> m.DiagnosticStatus:
        base = super().diagnostics()
        extra = [("model", self.params.model if self.params else ""), ("serial", self.version.get("SERI", "")),
                 ("firmware", self.version.get("FIRM", "")), ("clock_offset_ns", str(self.sensor_clock.offset_ns)),
                 ("clock_drift_ppm", f"{self.sensor_clock.drift_ppm:.2f}")]
        return m.DiagnosticStatus(base.level, base.name, base.message, self.hardware_id, base.values + tuple(extra))
