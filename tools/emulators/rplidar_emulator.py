"""Slamtec RPLIDAR emulator (A1, A2M8, A2M12, A3, S1, S2, S3, C1): the device side of the serial protocol.

``RplidarDevice`` is a pure state machine driven by explicit host times: ``receive`` answers
requests (GET_INFO, GET_HEALTH, GET_SAMPLERATE, GET_LIDAR_CONF, GET_ACC_BOARD_FLAG,
SET_MOTOR_PWM, HQ_MOTOR_SPEED_CTRL, STOP, RESET, SCAN, FORCE_SCAN, EXPRESS_SCAN with a working
mode), ``poll`` streams the samples measured by ``now`` in the format of the running scan mode
(legacy nodes, express, ultra, dense or ultra-dense capsules, HQ frames), with faults from a
``FaultPlan`` (corrupt check bits or checksums, lost bytes, garbage, stalls, unplug; flags
``streaming`` and ``health_error``). Serve it with ``trundle.tools.emulators.device_server.DeviceServer``.

Geometry: in a mode of N samples a revolution, sample k lies at ``k * 360 / N`` degrees of the
turret, clockwise seen from above as the device counts (``pi - angle`` in the ROS laser frame,
as rplidar_ros publishes); N divides 23040 so that every angle is a whole number of 1/64 deg and
each format's interpolation reproduces it exactly. Ultra capsules come from triangulation
models whose measurement angle lags the turret by the optics' parallax; the emulator applies the
SDK's compensation model so that a decoder recovers the angles recorded in ``sent``. Samples are
``us_per_sample`` apart. A1's motor follows DTR, which a pty cannot carry, so it always turns;
the C1's motor follows the scan; A2/A3 need SET_MOTOR_PWM, the S series HQ_MOTOR_SPEED_CTRL.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass
from functools import reduce

import numpy as np

from trundle.drivers import rplidar as rp
from trundle.drivers import rplidar_capsules as rc
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.scene import RangeSource

KINDS = ("checksum", "truncate", "garbage", "stall", "unplug")
FLAGS = ("streaming", "health_error")
BANNER = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n"
EDGE = 12  # faults stay this many samples away from a revolution's ends
QUALITY = 47  # legacy quality of a valid sample (0..63)


@dataclass(frozen=True)
class EmulatedMode:
    """A scan mode as GET_LIDAR_CONF describes it, the samples it takes per revolution, and the
    true sample duration where the firmware reports a wrong one (``true_us``, 0: as reported)."""

    mode: rp.ScanMode
    samples: int
    true_us: float = 0.0

    @property
    def sample_ns(self) -> int:
        return round((self.true_us or self.mode.us_per_sample) * 1000)


def _modes(*rows: tuple[str, float, float, int, int]) -> tuple[EmulatedMode, ...]:
    return tuple(
        EmulatedMode(rp.ScanMode(i, name, us, dist, kind), n) for i, (name, us, dist, kind, n) in enumerate(rows)
    )


@dataclass(frozen=True)
class RplidarModel:
    """One model: GET_INFO answer, motor control (``dtr``, ``pwm``, ``rpm`` or ``none``), its
    scan modes and typical mode, the GET_SAMPLERATE answer (None: not answered), whether it
    answers GET_LIDAR_CONF, its desired motor speed (rpm, PWM) and closest range (m)."""

    name: str
    info: rp.DeviceInfo
    motor: str
    modes: tuple[EmulatedMode, ...]
    typical: int
    samplerate: tuple[int, int] | None
    conf: bool
    range_min: float
    desired: tuple[int, int] = (600, 660)

    @property
    def grid(self) -> int:
        """Samples of the finest grid every mode's samples lie on."""
        return reduce(math.lcm, (m.samples for m in self.modes))

    @property
    def angles(self) -> np.ndarray:
        """ROS laser-frame angles (rad) of the grid; a mode of N samples uses every grid/N-th."""
        return math.pi - 2.0 * math.pi * np.arange(self.grid) / self.grid

    def mode(self, name: str) -> EmulatedMode:
        return next(m for m in self.modes if m.mode.name.lower() == name.lower())

    @property
    def standard(self) -> EmulatedMode:
        """The legacy SCAN mode (answer 0x81)."""
        return next(m for m in self.modes if m.mode.answer_type == rp.ANS_MEASUREMENT)


def _serial(tag: str) -> bytes:
    return bytes.fromhex(tag.ljust(32, "0"))


# Mode tables. A1M8: the GET_LIDAR_CONF answers of an A1M8 (model 0x18, firmware 1.29, hardware 7)
# printed in a public README ("library for working Slamtec RPLIDAR ... tested with A1 and S1"), as
# is the S1 (model 0x61, firmware 1.28, hardware 18). A2M8: the modes rplidar_ros printed for a
# 1.24-firmware A2 at 115200 baud (robopeak/rplidar_ros #68, Slamtec/sllidar_ros2 #42). S3:
# Standard 16 kHz 16 m and DenseBoost 40 m (Slamtec/rplidar_ros #150, #155: firmware 1.02,
# hardware 18). Bauds: sllidar_ros2 launch files. Other rates and ranges from the datasheets
# (A3: 16 kHz Sensitivity 25 m, 10 kHz Stability; S2: 32 kHz, 30 m; C1: 5 kHz, 12 m; A2M12: 16 kHz,
# 12 m); their typical modes are the launch files' defaults. Sample counts per revolution are the
# emulator's choice (a divisor of 23040 near the typical 5.5-10 Hz).
MODELS = {
    "a1": RplidarModel("a1", rp.DeviceInfo(0x18, (1, 29), 7, _serial("A1")), "dtr", _modes(
        ("Standard", 508, 12.0, rp.ANS_MEASUREMENT, 360), ("Express", 254, 12.0, rp.ANS_CAPSULED, 720),
        ("Boost", 127, 12.0, rp.ANS_ULTRA, 1440), ("Sensitivity", 127, 12.0, rp.ANS_ULTRA, 1440),
        ("Stability", 201, 12.0, rp.ANS_ULTRA, 960)), 3, (508, 254), True, 0.15),
    "a2": RplidarModel("a2", rp.DeviceInfo(0x28, (1, 27), 5, _serial("A2")), "pwm", _modes(
        ("Standard", 500, 12.0, rp.ANS_MEASUREMENT, 180), ("Express", 250, 12.0, rp.ANS_CAPSULED, 360),
        ("Boost", 125, 12.0, rp.ANS_ULTRA, 720)), 2, (500, 250), True, 0.15),
    "a2m12": RplidarModel("a2m12", rp.DeviceInfo(0x2C, (1, 32), 6, _serial("A212")), "pwm", _modes(
        ("Standard", 250, 12.0, rp.ANS_MEASUREMENT, 384), ("Express", 125, 12.0, rp.ANS_CAPSULED, 768),
        ("Boost", 62.5, 12.0, rp.ANS_ULTRA, 1536), ("Sensitivity", 62.5, 12.0, rp.ANS_ULTRA, 1536),
        ("Stability", 100, 12.0, rp.ANS_ULTRA, 960)), 3, (250, 125), True, 0.2),
    "a3": RplidarModel("a3", rp.DeviceInfo(0x31, (1, 29), 6, _serial("A3")), "pwm", _modes(
        ("Standard", 250, 25.0, rp.ANS_MEASUREMENT, 384), ("Express", 125, 25.0, rp.ANS_CAPSULED, 768),
        ("Boost", 62.5, 25.0, rp.ANS_ULTRA, 1536), ("Sensitivity", 62.5, 25.0, rp.ANS_ULTRA, 1536),
        ("Stability", 100, 20.0, rp.ANS_ULTRA, 960)), 3, (250, 125), True, 0.2),
    "s1": RplidarModel("s1", rp.DeviceInfo(0x61, (1, 28), 18, _serial("51")), "rpm", _modes(
        ("Standard", 244, 40.0, rp.ANS_MEASUREMENT, 384), ("DenseBoost", 108, 40.0, rp.ANS_DENSE, 960)),
        1, (244, 108), True, 0.1),
    "s2": RplidarModel("s2", rp.DeviceInfo(0x71, (1, 2), 18, _serial("52")), "rpm", _modes(
        ("Standard", 100, 30.0, rp.ANS_MEASUREMENT, 960), ("DenseBoost", 31.25, 30.0, rp.ANS_DENSE, 2880)),
        1, (100, 31), True, 0.05),
    "s3": RplidarModel("s3", rp.DeviceInfo(0x81, (1, 2), 18, _serial("53")), "rpm", _modes(
        ("Standard", 62.5, 16.0, rp.ANS_MEASUREMENT, 1536), ("DenseBoost", 31.25, 40.0, rp.ANS_DENSE, 2880)),
        1, (62, 31), True, 0.05),
    "c1": RplidarModel("c1", rp.DeviceInfo(0x41, (1, 2), 18, _serial("C1")), "none", _modes(
        ("Standard", 200, 12.0, rp.ANS_MEASUREMENT, 480), ("DenseBoost", 200, 12.0, rp.ANS_DENSE, 480)),
        0, (200, 200), True, 0.05),
}


def distance_q2(ranges_m: np.ndarray, model: RplidarModel, mode: EmulatedMode) -> np.ndarray:
    """Ranges (m) as distances in 1/4 mm (legacy nodes) or whole millimetres times 4 (capsules);
    0 (the device's 'invalid') outside the model's closest range and the mode's reach."""
    r = np.asarray(ranges_m, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= model.range_min) & (r <= mode.mode.max_distance)
        mm = np.where(ok, r * 1000.0, 0.0)
    legacy = mode.mode.answer_type == rp.ANS_MEASUREMENT
    return (np.round(mm * 4) if legacy else np.round(mm) * 4).astype(np.int64)


@dataclass
class SentRevolution:
    """A revolution the device measured: ``index`` since power-on, the true host time of its
    first sample, sample angles (1/64 deg: what a decoder of the bytes sent reads), distances
    (1/4 mm, as represented on the wire), quality (0..63) and the faults it carries."""

    index: int
    start_ns: int
    angle_q6: np.ndarray
    distance_q2: np.ndarray
    quality: np.ndarray
    faults: list[str]


class RplidarDevice:
    """One emulated RPLIDAR (see the module docstring).

    Parameters
    ----------
    model : one of ``MODELS``.
    ranges_at : range source ``ranges_at(t_s)`` in metres for ``model.angles``; all +inf if None.
    faults : fault plan (per-revolution kinds ``KINDS``, flags ``FLAGS``).
    now_ns : power-on time (host wall clock, ns).
    """

    def __init__(self, model: RplidarModel, ranges_at: RangeSource | None = None,
                 faults: FaultPlan | None = None, now_ns: int = 0) -> None:
        self.model = model
        self.ranges_at = ranges_at or (lambda t: np.full(model.grid, np.inf))
        self.faults = faults or FaultPlan()
        self.parser = rp.RequestParser()
        self.requests: list[rp.Request] = []
        self.sent: list[SentRevolution] = []
        self.injected: Counter[str] = Counter()
        self.link_request: tuple[str, float] | None = None
        self.health = rp.Health(rp.HEALTH_ERROR, 0x0808) if "health_error" in self.faults.flags else rp.Health(0)
        self.power_on(now_ns)
        if "streaming" in self.faults.flags:
            self.pwm = model.desired[1]
            self._start_scan(model.standard, False, now_ns)

    def power_on(self, now_ns: int) -> None:
        self.phase_ns = now_ns
        self.mode: EmulatedMode | None = None
        self.force = False
        self.pwm = 0
        self.rpm = 0
        self._silent_until = 0
        self.parser = rp.RequestParser()

    @property
    def motor_running(self) -> bool:
        """A pwm motor turns only with a PWM set; DTR (a pty has none), rpm and built-in
        motors turn while the device scans."""
        return self.model.motor != "pwm" or self.pwm > 0

    # --- host -> device ----------------------------------------------------------------------

    def receive(self, data: bytes, now_ns: int) -> bytes:
        out = bytearray()
        for req in self.parser.feed(data):
            self.requests.append(req)
            out += self._request(req, now_ns)
        return bytes(out)

    def _request(self, req: rp.Request, now: int) -> bytes:
        cmd = req.command
        if cmd not in (rp.SET_MOTOR_PWM, rp.HQ_MOTOR_SPEED_CTRL):
            self.mode = None  # any new request ends a scan
        if cmd == rp.STOP:
            return b""
        if cmd == rp.RESET:
            self.health = rp.Health(rp.HEALTH_GOOD)
            self.power_on(now)
            return BANNER
        if cmd == rp.GET_INFO:
            return rp.INFO_DESCRIPTOR.encode() + self.model.info.encode()
        if cmd == rp.GET_HEALTH:
            return rp.HEALTH_DESCRIPTOR.encode() + self.health.encode()
        if cmd == rp.GET_SAMPLERATE and self.model.samplerate is not None:
            return rp.SAMPLERATE_DESCRIPTOR.encode() + struct.pack("<HH", *self.model.samplerate)
        if cmd == rp.GET_LIDAR_CONF and self.model.conf and len(req.payload) >= 4:
            return self._conf(req.payload)
        if cmd == rp.GET_ACC_BOARD_FLAG:
            return rp.ACC_BOARD_DESCRIPTOR.encode() + (1 if self.model.motor == "pwm" else 0).to_bytes(4, "little")
        if cmd == rp.SET_MOTOR_PWM and len(req.payload) == 2:
            self.pwm = int.from_bytes(req.payload, "little") if self.model.motor == "pwm" else 0
            return b""
        if cmd == rp.HQ_MOTOR_SPEED_CTRL and len(req.payload) == 2:
            self.rpm = int.from_bytes(req.payload, "little") if self.model.motor == "rpm" else 0
            return b""
        if self.health.status == rp.HEALTH_ERROR:
            return b""  # protection stop: no scan until RESET
        if cmd in (rp.SCAN, rp.FORCE_SCAN):
            return self._start_scan(self.model.standard, cmd == rp.FORCE_SCAN, now)
        if cmd == rp.EXPRESS_SCAN and len(req.payload) == 5:
            mode = self._working_mode(req.payload[0])
            return b"" if mode is None else self._start_scan(mode, False, now)
        return b""  # unknown or unsupported requests get no answer, as on the device

    def _working_mode(self, working_mode: int) -> EmulatedMode | None:
        """The mode EXPRESS_SCAN asks for: its id, and 0 for the legacy express scan (protocol:
        working_mode 0 before scan modes existed)."""
        if working_mode == 0:
            return next((m for m in self.model.modes if m.mode.answer_type == rp.ANS_CAPSULED), None)
        return self.model.modes[working_mode] if working_mode < len(self.model.modes) else None

    def _conf(self, payload: bytes) -> bytes:
        entry = struct.unpack("<I", payload[:4])[0]
        mode = struct.unpack("<H", payload[4:6])[0] if len(payload) >= 6 else 0
        model = self.model
        if entry == rp.CONF_SCAN_MODE_COUNT:
            value = struct.pack("<H", len(model.modes))
        elif entry == rp.CONF_SCAN_MODE_TYPICAL:
            value = struct.pack("<H", model.typical)
        elif entry == rp.CONF_DESIRED_ROT_FREQ:
            value = struct.pack("<HH", *model.desired)
        elif entry in rp.MODE_ENTRIES and mode < len(model.modes):
            value = model.modes[mode].mode.conf_values()[entry]
        else:
            return b""
        answer = rp.conf_answer(entry, value)
        return rp.Descriptor(len(answer), rp.SINGLE, rp.ANS_CONF).encode() + answer

    def _start_scan(self, mode: EmulatedMode, force: bool, now: int) -> bytes:
        self.mode, self.force = mode, force
        self.n = mode.samples
        self.sample_ns = mode.sample_ns
        self.format = rc.FORMATS.get(mode.mode.answer_type)
        self._next = (now - self.phase_ns) // self.sample_ns + 1  # next sample, counted from power-on
        self._first_capsule = True
        self._pending = np.zeros(0, np.int64)  # capsule formats: samples waiting for a whole capsule
        self._pending_fault = ""
        self._revolutions: dict[int, SentRevolution] = {}
        self._fault_at: dict[int, str] = {}
        self._held = bytearray()
        if self.format is None:
            return rp.SCAN_DESCRIPTOR.encode()
        return self.format.descriptor.encode()

    # --- device -> host ----------------------------------------------------------------------

    def next_event_ns(self) -> int | None:
        if self.mode is None:
            return None
        return max(self.phase_ns + self._next * self.sample_ns, self._silent_until if self._held else 0)

    def poll(self, now: int) -> bytes:
        """The samples measured by ``now``; during a stall they are held back and sent after it.
        SCAN sends nothing while the motor stands (FORCE_SCAN does not wait for it)."""
        if self.mode is None:
            return b""
        last = (now - self.phase_ns) // self.sample_ns  # the last sample measured by now
        if not self.force and not self.motor_running:
            self._next = last + 1
            return b""
        k = self._next
        while k <= last:
            index = k // self.n
            self._revolution(index)
            end = min(last + 1, (index + 1) * self.n)
            at = next((f for f in self._fault_at if k <= f < end), None)
            if at is None:
                self._held += self._samples(k, end)
                k = end
                continue
            self._held += self._samples(k, at)
            fault = self._fault_at.pop(at)
            if fault == "unplug":
                self.link_request = ("unplug", self.faults.unplug_s)
                self.mode = None
                self._held.clear()
                return b""
            if fault == "stall":
                self._silent_until = self.phase_ns + at * self.sample_ns + int(self.faults.stall_s * 1e9)
                fault = ""
            self._held += self._samples(at, at + 1, fault)
            k = at + 1
        self._next = max(self._next, last + 1)
        if now < self._silent_until:
            return b""
        out, self._held = bytes(self._held), bytearray()
        return out

    def _revolution(self, index: int) -> SentRevolution:
        """Revolution ``index`` (counted from power-on), measured and its fault planned on first use."""
        rev = self._revolutions.get(index)
        if rev is not None:
            return rev
        assert self.mode is not None
        n = self.n
        start_ns = self.phase_ns + index * n * self.sample_ns
        grid = self.model.grid
        ranges = np.asarray(self.ranges_at(start_ns / 1e9), np.float64)[::grid // n]
        dist = distance_q2(ranges, self.model, self.mode)
        rev = SentRevolution(index, start_ns, np.arange(n) * (rp.FULL_CIRCLE_Q6 // n), dist,
                             np.where(dist > 0, QUALITY, 0), [])
        fault = self.faults.draw()
        if fault:
            # keep faults inside the revolution: a capsule's samples need the next capsule, and
            # the decoder holds two back, so a bad capsule spoils up to three capsules before it
            spc = self.format.samples if self.format else 1
            lo, hi = (4 * spc, n - 2 * spc) if self.format else (EDGE, n - EDGE)
            self.injected[fault] += 1
            rev.faults.append(fault)
            self._fault_at[index * n + int(self.faults.rng.integers(lo, hi))] = fault
        self._revolutions = {i: r for i, r in self._revolutions.items() if i >= index - 2}
        self._revolutions[index] = rev
        self.sent.append(rev)
        return rev

    def _sample(self, s: int) -> tuple[SentRevolution, int]:
        return self._revolution(s // self.n), s % self.n

    def _samples(self, a: int, b: int, fault: str = "") -> bytes:
        """Bytes of samples a..b-1 (one revolution), the fault applied to their frame."""
        if b <= a:
            return b""
        if self.format is None:
            rev, first = self._sample(a)
            i = np.arange(first, first + b - a)
            nodes = rp.encode_nodes(i == 0, rev.quality[i], rev.angle_q6[i], rev.distance_q2[i])
            return self._corrupt(nodes, fault, rp.NODE_SIZE) if fault else nodes
        self._pending = np.concatenate((self._pending, np.arange(a, b)))
        self._pending_fault = self._pending_fault or fault
        spc = self.format.samples
        lookahead = 1 if self.format is rc.ULTRA else 0  # an ultra capsule predicts from the next one's first sample
        out = bytearray()
        while self._pending.size >= spc + lookahead:
            samples, self._pending = self._pending[:spc], self._pending[spc:]
            raw = self._capsule(samples, int(self._pending[0]) if lookahead else -1)
            self._first_capsule = False
            fault, self._pending_fault = self._pending_fault, ""
            out += self._corrupt(raw, fault, self.format.size) if fault else raw
        return bytes(out)

    def _capsule(self, samples: np.ndarray, following: int) -> bytes:
        """Encode one capsule of the running mode and record what its bytes represent."""
        located = [self._sample(int(s)) for s in samples]
        mm = np.array([rev.distance_q2[i] for rev, i in located]) // 4
        start_q6 = int(located[0][1]) * (rp.FULL_CIRCLE_Q6 // self.n)
        new, fmt = self._first_capsule, self.format
        quality = np.where(mm > 0, QUALITY << 2, 0)
        if fmt is rc.EXPRESS:
            raw, shown = rc.encode_capsule(start_q6, mm * 4, np.zeros(mm.size, np.int64), new), mm
        elif fmt is rc.DENSE:
            raw, shown = rc.encode_dense_capsule(start_q6, mm, new), mm
        elif fmt is rc.ULTRA:
            rev, i = self._sample(following)
            raw, shown = rc.encode_ultra_capsule(start_q6, mm, int(rev.distance_q2[i]) // 4, new)
        elif fmt is rc.ULTRA_DENSE:
            raw, shown, quality = rc.encode_ultra_dense_capsule(start_q6, mm, quality, new)
        else:
            angles = np.array([rev.angle_q6[i] for rev, i in located])
            raw, shown = rc.encode_hq_capsule(angles, mm * 4, quality, angles == 0), mm
        turret = np.array([rev.angle_q6[i] for rev, i in located]) if fmt is rc.ULTRA else None
        for k, (rev, i) in enumerate(located):
            rev.distance_q2[i] = shown[k] * 4
            rev.quality[i] = quality[k] >> 2
        if turret is not None:
            measured = rc.ultra_offset_q6(shown * 4, turret << 10)
            for k, (rev, i) in enumerate(located):
                rev.angle_q6[i] = measured[k]
        return raw

    def _corrupt(self, raw: bytes, fault: str, size: int) -> bytes:
        rng = self.faults.rng
        if fault == "checksum":
            if size == rp.NODE_SIZE:  # a node that fails its check: check bit cleared or start bits equal
                b = bytearray(raw)
                if rng.random() < 0.5:
                    b[1] &= 0xFE
                else:
                    b[0] = (b[0] & 0xFC) | (0x03 if rng.random() < 0.5 else 0x00)
                return bytes(b)
            i = int(rng.integers(2, size))
            return raw[:i] + bytes((raw[i] ^ (1 << int(rng.integers(8))),)) + raw[i + 1:]
        if fault == "truncate":
            return raw[:size - int(rng.integers(1, size))]
        if fault == "garbage":
            return rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8).tobytes() + raw
        return raw
