"""Hokuyo SCIP 2.0 sensor emulator (URG-04LX, UTM-30LX, UST-10LX): the device side of the protocol.

``ScipDevice`` is a pure state machine driven by explicit host times: ``receive`` answers the
host's command lines, ``poll`` emits the scans that are due while MD/MS/ME streaming runs, with
faults injected from a ``FaultPlan`` (checksum flips, truncated lines, garbage between replies,
``0M`` unstable scans, stalls, abnormal status, clock reset, unplug) modelled on SCIP's ``DB``
malfunction simulation and seqsense/urg_stamped's simulator. Serve it with
``trundle.tools.emulators.device_server.DeviceServer`` on a pty or TCP port.

Timing: the motor turns from power-on; scan k passes the rear (angle pi, where the 24-bit
millisecond timestamp refers, as urg_node assumes) at ``boot + k * period`` and is sent one
period later. ``sent`` records every scan the device meant to send, with its true time.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from trundle.drivers import scip2
from trundle.drivers.scip2 import Measure, ScipError, SensorParams
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.scene import RangeSource

KINDS = ("checksum", "truncate", "garbage", "unstable", "stall", "abnormal", "reboot", "unplug")
FLAGS = ("streaming",)
MASK = 0xFFFFFF
ABNORMAL_STATUSES = ("0L", "33", "52")


@dataclass(frozen=True)
class ScipModel:
    """What one sensor model answers: PP parameters, VV lines, capabilities and error codes.

    ``no_return``, ``too_near`` and ``error`` are the codes (below DMIN) the model sends for no
    echo, an object closer than DMIN and a failed measurement.
    """

    name: str
    params: SensorParams
    version: dict[str, str]
    intensity: bool
    ethernet: bool
    no_return: int
    too_near: int
    error: int

    @property
    def steps(self) -> np.ndarray:
        return np.arange(self.params.amin, self.params.amax + 1)

    @property
    def angles(self) -> np.ndarray:
        """Angles (rad, laser frame) of steps AMIN..AMAX: the beams a range source must cover."""
        return np.asarray(self.params.step_angle(self.steps))


def _version(product: str, firmware: str, serial: str) -> dict[str, str]:
    return {"VEND": "Hokuyo Automatic Co.,Ltd.", "PROD": product, "FIRM": firmware, "PROT": "SCIP 2.0",
            "SERI": serial}


MODELS = {
    "urg-04lx": ScipModel("urg-04lx", SensorParams("URG-04LX(Hokuyo Automatic Co.,Ltd.)", 20, 5600, 1024, 44, 725,
                                                   384, 600),
                          _version("SOKUIKI Sensor URG-04LX", "3.1.00(18/Jan./2007)", "H0614967"),
                          intensity=False, ethernet=False, no_return=0, too_near=19, error=6),
    "utm-30lx": ScipModel("utm-30lx", SensorParams("UTM-30LX", 23, 60000, 1440, 0, 1080, 540, 2400),
                          _version("SOKUIKI Sensor TOP-URG UTM-30LX", "1.1.3(19/Dec./2008)", "H0900001"),
                          intensity=True, ethernet=False, no_return=1, too_near=2, error=3),
    "ust-10lx": ScipModel("ust-10lx", SensorParams("UST-10LX", 20, 30000, 1440, 0, 1080, 540, 2400),
                          _version("SOKUIKI Sensor UST-10LX", "1.0.5", "H1400001"),
                          intensity=True, ethernet=True, no_return=1, too_near=2, error=3),
}


def to_millimetres(ranges_m: np.ndarray, model: ScipModel) -> np.ndarray:
    """Ranges (m; +inf nothing, -inf too near, NaN failed) as the model's values in mm or codes."""
    r = np.asarray(ranges_m, np.float64)
    p = model.params
    with np.errstate(invalid="ignore"):
        mm = np.where(np.isfinite(r), np.round(r * 1000.0), 0.0)
        out = np.clip(mm, 0, p.dmax).astype(np.int64)
        out[np.isnan(r)] = model.error
        out[(r > 0) & (mm > p.dmax)] = model.no_return
        out[r == np.inf] = model.no_return
        out[(r == -np.inf) | (np.isfinite(r) & (mm < p.dmin))] = model.too_near
    return out


def intensity_of(ranges_m: np.ndarray) -> np.ndarray:
    """A plausible return strength for each beam (falls with distance; 0 without a return)."""
    r = np.asarray(ranges_m, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        value = np.where(np.isfinite(r) & (r > 0), 12000.0 / (1.0 + r), 0.0)
    return np.clip(value, 0, (1 << 18) - 1).astype(np.int64)


def cluster_values(values: np.ndarray, cluster: int, dmin: int) -> np.ndarray:
    """Merge ``cluster`` steps: the minimum over valid (>= DMIN) values, else the first code."""
    cluster = max(cluster, 1)
    if cluster == 1:
        return values
    n = math.ceil(values.size / cluster)
    padded = np.full(n * cluster, -1, np.int64)
    padded[:values.size] = values
    groups = padded.reshape(n, cluster)
    valid = np.where(groups >= dmin, groups, np.iinfo(np.int64).max)
    best = valid.min(axis=1)
    return np.where(best == np.iinfo(np.int64).max, groups[:, 0], best)


@dataclass
class SentScan:
    """A scan the device meant to send: raw ``timestamp``, true host time ``rear_ns`` of the rear
    direction, the values, the ``fault`` injected into it ("" none), the streaming ``session``
    and which line a checksum or truncate fault ``damaged`` (status, timestamp or data)."""

    timestamp: int
    rear_ns: int
    distances: np.ndarray
    intensities: np.ndarray | None
    fault: str
    measure: Measure
    session: int
    damaged: str = ""


class ScipDevice:
    """One emulated SCIP 2.0 sensor (see the module docstring).

    Parameters
    ----------
    model : what the sensor answers (``MODELS``).
    ranges_at : range source ``ranges_at(t_s)`` giving metres for ``model.angles``; all +inf if None.
    faults : fault plan; flags: ``streaming`` starts streaming at power-on (as after a crashed
        client), ``wrap`` starts the clock that many seconds before its 24-bit wrap.
    now_ns : power-on time (host wall clock, ns).
    drift_ppm : the sensor clock runs this much slower than the host's.
    """

    def __init__(self, model: ScipModel, ranges_at: RangeSource | None = None, faults: FaultPlan | None = None,
                 now_ns: int = 0, drift_ppm: float = 0.0) -> None:
        self.model = model
        self.params = model.params
        self.period_ns = int(round(60e9 / self.params.rpm))
        self.ranges_at = ranges_at or (lambda t: np.full(model.steps.size, np.inf))
        self.faults = faults or FaultPlan()
        self.drift_ppm = drift_ppm
        self.sent: list[SentScan] = []
        self.injected: Counter[str] = Counter()
        self.commands: list[bytes] = []
        self.link_request: tuple[str, float] | None = None
        self.session = 0
        self._line = bytearray()
        self.scip1 = False
        start = MASK + 1 - int(self.faults.wrap_s * 1000) if self.faults.wrap_s is not None else 0
        self.power_on(now_ns, clock_ms=start)
        if "streaming" in self.faults.flags:
            self._start_stream(Measure("MD", self.params.amin, self.params.amax, string="OLD"), now_ns)

    # --- clock and state ---------------------------------------------------------------------

    def power_on(self, now_ns: int, clock_ms: int = 0) -> None:
        """Boot: laser off, idle, clock from ``clock_ms``, motor phase from now."""
        self.phase_ns = now_ns
        self.clock_origin_ns = now_ns
        self.clock_ms = clock_ms
        self.laser = False
        self.tm = False
        self.abnormal = False
        self.stream: Measure | None = None
        self._rb_ns: int | None = None
        self._silent_until = 0
        self._held = bytearray()
        self._unplug_at: int | None = None
        self._line.clear()

    def sensor_ms(self, t_ns: int) -> int:
        """The raw 24-bit timestamp at host time ``t_ns``."""
        elapsed_ms = (t_ns - self.clock_origin_ns) / 1e6 / (1 + self.drift_ppm * 1e-6)
        return (self.clock_ms + math.floor(elapsed_ms)) & MASK

    def _reset_clock(self, now_ns: int) -> None:
        """Timer to zero (RS, RT, a firmware restart); the motor keeps turning."""
        self.clock_origin_ns, self.clock_ms = now_ns, 0

    def _rear(self, now_ns: int, rotations: int = 0) -> int:
        """When the rear direction was passed last before ``now_ns``, plus ``rotations``."""
        return self.phase_ns + ((now_ns - self.phase_ns) // self.period_ns + rotations) * self.period_ns

    # --- host -> device ----------------------------------------------------------------------

    def receive(self, data: bytes, now_ns: int) -> bytes:
        """Answer every complete command line in ``data`` (LF, CR or CR LF terminated).

        During a stall the device answers nothing; what arrived is answered when it ends.
        """
        self._held += data
        if now_ns < self._silent_until:
            return b""
        data, self._held = bytes(self._held), bytearray()
        out = bytearray()
        for byte in data:
            if byte in (0x0A, 0x0D):
                if self._line:
                    line = bytes(self._line)
                    self._line.clear()
                    self.commands.append(line)
                    out += self._command(line, now_ns)
            elif len(self._line) < 64:
                self._line.append(byte)
        return bytes(out)

    def _command(self, line: bytes, now: int) -> bytes:
        name = b"SCIP2.0" if line.startswith(b"SCIP2.0") else line[:3] if line[:1] == b"%" else line[:2]
        text = line.decode("latin-1")

        def reply(status: str, data: bytes = b"") -> bytes:
            return scip2.encode_reply(line, status, (), data)

        if self.scip1:
            if name == b"SCIP2.0":
                self.scip1 = False
                return reply("00")
            return line + b"\nE\n\n"
        if self.abnormal and name != b"RB":
            return reply("0L")
        if b";" in line:
            string = line.split(b";", 1)[1]
            if len(string) > 16:
                return reply("0G")
            if not scip2.STRING_CHARS.fullmatch(string):
                return reply("0H")
        if name == b"QT":
            if self.tm:
                return reply("0E")
            self.stream = None
            self.laser = False
            return reply("00")
        if name == b"SCIP2.0":
            return reply("0E")
        if name == b"RB":
            if self._rb_ns is not None and now - self._rb_ns <= 1_000_000_000:
                self._rb_ns = None
                self._unplug_at = now + 50_000_000
                return reply("00")
            self._rb_ns = now
            return reply("01")
        if name in (b"VV", b"PP", b"II"):
            if name == b"PP" and self.tm:
                return reply("0E")
            info = {b"VV": self.model.version, b"PP": self.params.info(), b"II": self._state_info(now)}[name]
            return reply("00", scip2.encode_info(info))
        if name == b"%ST":
            state = (
                "900"
                if self.abnormal
                else "002"
                if self.tm
                else "004"
                if self.stream
                else "003"
                if self.laser
                else "000"
            )
            return reply("00", scip2.with_checksum(state.encode()) + b"\n")
        if name == b"TM":
            code = text[2:3]
            if code == "0":
                if self.tm:
                    return reply("02")
                self.tm, self.stream, self.laser = True, None, False
                return reply("00")
            if code == "1":
                if not self.tm:
                    return reply("04")
                return reply("00", scip2.with_checksum(scip2.encode_values([self.sensor_ms(now)], 4)) + b"\n")
            if code == "2":
                if not self.tm:
                    return reply("03")
                self.tm = False
                return reply("00")
            return reply("01")
        if self.tm:
            return reply("10")
        if name == b"BM":
            if self.laser:
                return reply("02")
            self.laser = True
            return reply("00")
        if name in (b"RS", b"RT"):
            self.stream, self.laser = None, False
            self._reset_clock(now)
            return reply("00")
        if name == b"SS":
            return reply("0F" if self.model.ethernet else "00")
        if name[:1] in (b"G", b"M") and name.decode("latin-1") in scip2.MEASURE_COMMANDS:
            return self._measure(line, now)
        return reply("0E")

    def _state_info(self, now: int) -> dict[str, str]:
        p = self.params
        return {"MODL": p.model, "LASR": "ON" if self.laser else "OFF", "SCSP": f"Initial({p.rpm}[rpm])",
                "MESM": "Measuring by Normal Mode" if self.stream else "IDLE",
                "SBPS": "Ethernet 100 [Mbps]" if self.model.ethernet else "USB only",
                "TIME": f"{self.sensor_ms(now):06X}",
                "STAT": "Stop 000 Abnormal" if self.abnormal else "Stable 000 no error."}

    def _measure(self, line: bytes, now: int) -> bytes:
        try:
            measure = Measure.from_echo(line)
        except ScipError:
            return scip2.encode_reply(line, "0C")
        p = self.params
        status = ("01" if not p.amin <= measure.start <= p.amax else "02" if not measure.start <= measure.end <= p.amax
                  else "0E" if measure.intensity and not self.model.intensity else "")
        if status:
            return scip2.encode_reply(line, status)
        if not measure.continuous:
            if not self.laser:
                return scip2.encode_reply(line, "10")
            rear = self._rear(now, -1)
            distances, intensities = self._values(measure, rear)
            return scip2.encode_scan(measure, self.sensor_ms(rear), distances, intensities, status="00")
        self._start_stream(measure, now)
        return scip2.encode_reply(line, "00")

    def _start_stream(self, measure: Measure, now: int) -> None:
        self.laser = True
        self.stream = measure
        self.session += 1
        self._remaining = measure.scans
        self._skip_left = 0
        self._next_rear = self._rear(now, 1)

    # --- device -> host ----------------------------------------------------------------------

    def next_event_ns(self) -> int | None:
        times = [t for t in (self._unplug_at, self._next_rear + self.period_ns if self.stream else None,
                             self._silent_until if self._held else None) if t]
        return min(times) if times else None

    def poll(self, now: int) -> bytes:
        """The scan replies due by ``now`` (a scan is sent one period after it passed the rear)."""
        if self._unplug_at is not None and now >= self._unplug_at:
            self._unplug_at = None
            self.link_request = ("unplug", self.faults.reboot_s)
            self.stream = None
            return b""
        out = bytearray(self.receive(b"", now) if self._held else b"")
        while self.stream is not None and self._next_rear + self.period_ns <= now and self.link_request is None:
            rear = self._next_rear
            self._next_rear += self.period_ns
            if self._skip_left:
                self._skip_left -= 1
                continue
            self._skip_left = self.stream.skip
            out += self._emit(self.stream, rear, rear + self.period_ns)
        return bytes(out)

    def _values(self, measure: Measure, rear_ns: int) -> tuple[np.ndarray, np.ndarray | None]:
        ranges = np.asarray(self.ranges_at(rear_ns / 1e9), np.float64)
        lo, hi = measure.start - self.params.amin, measure.end - self.params.amin + 1
        distances = cluster_values(to_millimetres(ranges, self.model)[lo:hi], measure.cluster, self.params.dmin)
        if not measure.intensity:
            return distances, None
        return distances, cluster_values(intensity_of(ranges)[lo:hi], measure.cluster, 0)

    def _emit(self, measure: Measure, rear: int, sent_at: int) -> bytes:
        fault = self.faults.draw() if sent_at >= self._silent_until else "stalled"
        if fault == "reboot":
            self._reset_clock(rear)
        if fault == "unplug":
            self.link_request = ("unplug", self.faults.unplug_s)
        if measure.scans:
            self._remaining -= 1
        distances, intensities = self._values(measure, rear)
        self.sent.append(SentScan(self.sensor_ms(rear), rear, distances, intensities, fault, measure, self.session))
        if fault and fault != "stalled":
            self.injected[fault] += 1
        if measure.scans and self._remaining <= 0:
            self.stream = None
        if fault in ("stalled", "unplug"):
            return b""
        if fault == "stall":
            self._silent_until = sent_at + int(self.faults.stall_s * 1e9)
            return b""
        remaining = max(self._remaining, 0) if measure.scans else 0
        if fault == "unstable":
            return scip2.encode_reply(measure.echo(remaining), "0M")
        if fault == "abnormal":
            self.abnormal, self.stream, self.laser = True, None, False
            status = ABNORMAL_STATUSES[int(self.faults.rng.integers(len(ABNORMAL_STATUSES)))]
            return scip2.encode_reply(measure.echo(remaining), status)
        raw = scip2.encode_scan(measure, self.sensor_ms(rear), distances, intensities, remaining)
        if fault == "checksum":
            return self._flip(raw, self.sent[-1])
        if fault == "truncate":
            return self._truncate(raw, self.sent[-1])
        if fault == "garbage":
            rng = self.faults.rng
            return rng.integers(0, 256, int(rng.integers(1, 48)), dtype=np.uint8).tobytes() + raw
        return raw

    def _lines(self, raw: bytes) -> list[tuple[int, int]]:
        """(start, end) of every line after the echo, end at its LF."""
        spans: list[tuple[int, int]] = []
        start = raw.index(b"\n") + 1
        while True:
            end = raw.index(b"\n", start)
            if end == start:
                return spans
            spans.append((start, end))
            start = end + 1

    def _flip(self, raw: bytes, record: SentScan) -> bytes:
        """Replace one character of a line after the echo by another valid SCIP character."""
        rng = self.faults.rng
        spans = self._lines(raw)
        line = int(rng.integers(len(spans)))
        record.damaged = ("status", "timestamp")[line] if line < 2 else "data"
        start, end = spans[line]
        i = int(rng.integers(start, end))
        new = (raw[i] - 0x30 + int(rng.integers(1, 64))) % 64 + 0x30
        return raw[:i] + bytes((new,)) + raw[i + 1:]

    def _truncate(self, raw: bytes, record: SentScan) -> bytes:
        """Cut the tail off the timestamp line or a data line (its LF stays)."""
        rng = self.faults.rng
        spans = self._lines(raw)[1:]
        line = int(rng.integers(len(spans)))
        record.damaged = "timestamp" if line == 0 else "data"
        start, end = spans[line]
        cut = int(rng.integers(1, end - start))
        return raw[:end - cut] + raw[end:]
