"""Slamtec RPLIDAR emulator (A1, A2): the device side of the serial protocol.

``RplidarDevice`` is a pure state machine driven by explicit host times: ``receive`` answers
requests (GET_INFO, GET_HEALTH, GET_SAMPLERATE, GET_ACC_BOARD_FLAG, SET_MOTOR_PWM, STOP,
RESET, SCAN, FORCE_SCAN, EXPRESS_SCAN), ``poll`` streams the samples measured by ``now`` as
legacy nodes or express capsules, with faults from a ``FaultPlan`` (corrupt check bits or
capsule checksums, lost bytes, garbage, stalls, unplug; flags ``streaming`` and
``health_error``). Serve it with ``trundle.tools.emulators.device_server.DeviceServer``.

Geometry: sample k of a revolution lies at ``k * 360 / N`` degrees, clockwise seen from above
as the device counts; in the ROS laser frame that is ``pi - angle`` (as rplidar_ros
publishes), which is what ``angles`` gives a range source. Samples are measured
``us_per_sample`` apart; A1's motor follows DTR, which a pty cannot carry, so it always turns.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from trundle.drivers import rplidar as rp
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.scene import RangeSource

KINDS = ("checksum", "truncate", "garbage", "stall", "unplug")
FLAGS = ("streaming", "health_error")
BANNER = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n"
EDGE = 12  # faults stay this many samples away from a revolution's ends


@dataclass(frozen=True)
class RplidarModel:
    """One model: GET_INFO answer, motor control, samples per revolution, timing and range."""

    name: str
    info: rp.DeviceInfo
    motor: str  # "dtr" (A1) or "pwm" (A2/A3 accessory board)
    samples: int  # per revolution in standard mode; express mode has twice as many
    standard_us: int
    express_us: int
    range_min: float
    range_max: float

    @property
    def angles(self) -> np.ndarray:
        """ROS laser-frame angles (rad) of the express-mode samples; standard mode uses every other."""
        n = 2 * self.samples
        return math.pi - 2.0 * math.pi * np.arange(n) / n


MODELS = {
    "a1": RplidarModel("a1", rp.DeviceInfo(0x18, (1, 29), 7, bytes.fromhex("A1000000000000000000000000000001")),
                       "dtr", 360, 500, 250, 0.15, 12.0),
    "a2": RplidarModel("a2", rp.DeviceInfo(0x28, (1, 27), 5, bytes.fromhex("A2000000000000000000000000000002")),
                       "pwm", 180, 500, 250, 0.15, 12.0),
}


def distance_q2(ranges_m: np.ndarray, model: RplidarModel, express: bool) -> np.ndarray:
    """Ranges (m) as distances in 1/4 mm; 0 (the device's 'invalid') outside the model's range."""
    r = np.asarray(ranges_m, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= model.range_min) & (r <= model.range_max)
        mm = np.where(ok, r * 1000.0, 0.0)
    return (np.round(mm) * 4 if express else np.round(mm * 4)).astype(np.int64)


@dataclass
class SentRevolution:
    """A revolution the device measured: ``index`` since the scan started, the true host time of
    its first sample, sample angles (1/64 deg) and distances (1/4 mm), the faults it carries."""

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
    model : ``MODELS["a1"]`` or ``MODELS["a2"]``.
    ranges_at : range source ``ranges_at(t_s)`` in metres for ``model.angles``; all +inf if None.
    faults : fault plan (per-revolution kinds ``KINDS``, flags ``FLAGS``).
    now_ns : power-on time (host wall clock, ns).
    """

    def __init__(self, model: RplidarModel, ranges_at: RangeSource | None = None,
                 faults: FaultPlan | None = None, now_ns: int = 0) -> None:
        self.model = model
        self.ranges_at = ranges_at or (lambda t: np.full(2 * model.samples, np.inf))
        self.faults = faults or FaultPlan()
        self.parser = rp.RequestParser()
        self.requests: list[rp.Request] = []
        self.sent: list[SentRevolution] = []
        self.injected: Counter[str] = Counter()
        self.link_request: tuple[str, float] | None = None
        self.pwm = 0
        self.health = rp.Health(rp.HEALTH_ERROR, 0x0808) if "health_error" in self.faults.flags else rp.Health(0)
        self.power_on(now_ns)
        if "streaming" in self.faults.flags:
            self.pwm = 660
            self._start_scan("standard", now_ns)

    def power_on(self, now_ns: int) -> None:
        self.phase_ns = now_ns
        self.mode: str | None = None
        self.pwm = 0
        self._silent_until = 0
        self.parser = rp.RequestParser()

    @property
    def motor_running(self) -> bool:
        return self.model.motor == "dtr" or self.pwm > 0

    # --- host -> device ----------------------------------------------------------------------

    def receive(self, data: bytes, now_ns: int) -> bytes:
        out = bytearray()
        for req in self.parser.feed(data):
            self.requests.append(req)
            out += self._request(req, now_ns)
        return bytes(out)

    def _request(self, req: rp.Request, now: int) -> bytes:
        cmd = req.command
        if cmd != rp.SET_MOTOR_PWM:
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
        if cmd == rp.GET_SAMPLERATE:
            return rp.SAMPLERATE_DESCRIPTOR.encode() + np.array(
                [self.model.standard_us, self.model.express_us], "<u2").tobytes()
        if cmd == rp.GET_ACC_BOARD_FLAG:
            return rp.ACC_BOARD_DESCRIPTOR.encode() + (1 if self.model.motor == "pwm" else 0).to_bytes(4, "little")
        if cmd == rp.SET_MOTOR_PWM and len(req.payload) == 2:
            self.pwm = int.from_bytes(req.payload, "little") if self.model.motor == "pwm" else 0
            return b""
        if cmd in (rp.SCAN, rp.FORCE_SCAN):
            if self.health.status == rp.HEALTH_ERROR:
                return b""  # protection stop: no answer until RESET
            self._start_scan("force" if cmd == rp.FORCE_SCAN else "standard", now)
            return rp.SCAN_DESCRIPTOR.encode()
        if cmd == rp.EXPRESS_SCAN and len(req.payload) == 5:
            if self.health.status == rp.HEALTH_ERROR:
                return b""
            self._start_scan("express", now)
            return rp.EXPRESS_DESCRIPTOR.encode()
        return b""  # unknown or unsupported requests get no answer, as on the device

    def _start_scan(self, mode: str, now: int) -> None:
        self.mode = mode
        express = mode == "express"
        self.n = self.model.samples * (2 if express else 1)
        self.sample_ns = (self.model.express_us if express else self.model.standard_us) * 1000
        self._next = (now - self.phase_ns) // self.sample_ns + 1  # next sample, counted from power-on
        self._first_capsule = True
        self._capsule = np.zeros(0, np.int64)  # express: samples waiting for a whole capsule
        self._capsule_fault = ""
        self._revolutions: dict[int, SentRevolution] = {}
        self._fault_at: dict[int, str] = {}
        self._held = bytearray()

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
        if self.mode != "force" and not self.motor_running:
            self._next = last + 1
            return b""
        k = self._next
        while k <= last:
            index = k // self.n
            if index not in self._revolutions:
                self._new_revolution(index)
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

    def _new_revolution(self, index: int) -> None:
        """Measure revolution ``index`` (counted from power-on) and plan its fault."""
        n = self.n
        start_ns = self.phase_ns + index * n * self.sample_ns
        express = self.mode == "express"
        ranges = np.asarray(self.ranges_at(start_ns / 1e9), np.float64)[::1 if express else 2]
        dist = distance_q2(ranges, self.model, express)
        rev = SentRevolution(index, start_ns, np.arange(n) * (rp.FULL_CIRCLE_Q6 // n), dist,
                             np.where(dist > 0, 47, 0), [])
        fault = self.faults.draw()
        if fault:
            # keep faults inside the revolution: express capsules hold 32 samples and the
            # decoder holds two capsules back, so a bad capsule spoils up to 96 samples before it
            lo, hi = (4 * rp.CABINS * 2, n - 2 * rp.CABINS * 2) if express else (EDGE, n - EDGE)
            self.injected[fault] += 1
            rev.faults.append(fault)
            self._fault_at[index * n + int(self.faults.rng.integers(lo, hi))] = fault
        self._revolutions = {i: r for i, r in self._revolutions.items() if i >= index - 2}
        self._revolutions[index] = rev
        self.sent.append(rev)

    def _samples(self, a: int, b: int, fault: str = "") -> bytes:
        """Bytes of samples a..b-1 (one revolution), the fault applied to their frame."""
        if b <= a:
            return b""
        index = a // self.n
        rev = self._revolutions[index]
        i = np.arange(a, b) - index * self.n
        if self.mode != "express":
            nodes = rp.encode_nodes(i == 0, rev.quality[i], rev.angle_q6[i], rev.distance_q2[i])
            return self._corrupt(nodes, fault, rp.NODE_SIZE) if fault else nodes
        self._capsule = np.concatenate((self._capsule, np.arange(a, b)))
        self._capsule_fault = self._capsule_fault or fault
        out = bytearray()
        while self._capsule.size >= 2 * rp.CABINS:
            samples, self._capsule = self._capsule[:2 * rp.CABINS], self._capsule[2 * rp.CABINS:]
            dist = [int(self._revolutions[s // self.n].distance_q2[s % self.n]) for s in samples]
            start_q6 = int(samples[0] % self.n) * (rp.FULL_CIRCLE_Q6 // self.n)
            raw = rp.encode_capsule(start_q6, dist, np.zeros(samples.size, np.int64), new_scan=self._first_capsule)
            self._first_capsule = False
            fault, self._capsule_fault = self._capsule_fault, ""
            out += self._corrupt(raw, fault, rp.CAPSULE_SIZE) if fault else raw
        return bytes(out)

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
