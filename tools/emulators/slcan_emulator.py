"""An SLCAN (Lawicel) USB-CAN adapter on a pty, as python-can's ``slcan`` interface sees a CANable.
The frame line codec is ``trundle.drivers.slcan``'s (the host's side of the same protocol).

The host opens the pty's stable symlink with ``can.Bus(interface="slcan", channel=LINK)``; the
emulated devices behind the adapter use :attr:`SlcanEmulator.bus`, a python-can bus of their
own (so ``canopen`` nodes, ``cantools`` encoders or plain ``can.Message`` senders work as they
would on a real bus). Protocol (lines end with CR; OK = CR, error = BEL):

``S0``..``S8`` / ``sxxyy`` bit rate, ``O`` open, ``L`` open listen-only, ``C`` close,
``V`` -> ``V1013``, ``N`` -> ``NA123``, ``F`` -> ``Fxx`` status flags, ``Z0``/``Z1`` adapter time
stamps (4 hex digits of ms, 0..59999, appended to frames), ``t``/``T``/``r``/``R`` transmit
(answered ``z`` / ``Z``), ``M``/``m``/``W``/``X``/``U``/``Q`` accepted. Adapter -> host frames are
``tIIILDD..`` / ``TIIIIIIIILDD..`` / ``rIIIL`` / ``RIIIIIIIIL``.

Faults: :meth:`bus_off` (the adapter stops passing frames and reports the bus error flag until
the host sends ``C`` then ``O``, as real Lawicel adapters do), :meth:`raise_flags` (error
warning / passive / overrun bits shown once by ``F``), :meth:`inject_noise` (garbled lines),
:meth:`unplug` / :meth:`replug`.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

import can

from trundle.drivers.slcan import ERROR, HEX_DIGITS, OK, format_frame, parse_frame
from trundle.tools.emulators.pty_link import PtyLink

# Lawicel's own table (S0..S8, S7 = 800 kbit/s); hosts (python-can, drivers.slcan) send S7 for 750 kbit/s
BITRATES = {b"0": 10000, b"1": 20000, b"2": 50000, b"3": 100000, b"4": 125000, b"5": 250000, b"6": 500000,
            b"7": 800000, b"8": 1000000}
FLAG_ERROR_WARNING, FLAG_DATA_OVERRUN, FLAG_ERROR_PASSIVE, FLAG_BUS_ERROR = 0x04, 0x08, 0x20, 0x80


class AdapterBus(can.BusABC):
    """The device side of the emulated adapter, as a python-can bus: ``send`` puts a frame on
    the wire towards the host, ``recv`` returns frames the host transmitted."""

    def __init__(self, emulator: SlcanEmulator, **kwargs: Any) -> None:
        self._emulator = emulator
        self._rx: queue.Queue[can.Message] = queue.Queue()
        super().__init__(channel="slcan-emulator", **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._emulator.to_host([msg])

    def send_many(self, msgs: Iterable[can.Message]) -> int:
        return self._emulator.to_host(msgs)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._rx.get(timeout=timeout) if timeout else self._rx.get_nowait(), False
        except queue.Empty:
            return None, False


class SlcanEmulator:
    """One SLCAN adapter behind the symlink ``link_path``; call :meth:`start`, then use :attr:`bus`."""

    def __init__(self, link_path: str, *, version: str = "1013", serial_number: str = "A123") -> None:
        self.link = PtyLink(link_path)
        self.version, self.serial_number = version, serial_number
        self.bus = AdapterBus(self)
        self.is_open = False
        self.listen_only = False
        self.bitrate: int | None = None
        self.timestamps = False
        self.stats: Counter[str] = Counter()
        self._bus_off = False
        self._flags = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()

    # -- life cycle ----------------------------------------------------------------------------
    def start(self) -> SlcanEmulator:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="slcan-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.bus.shutdown()
        self.link.close()

    def __enter__(self) -> SlcanEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- faults --------------------------------------------------------------------------------
    def unplug(self) -> None:
        """Pull the adapter: the host's reads fail, the link disappears."""
        with self._lock:
            self.is_open = False
            self.link.unplug()

    def replug(self) -> None:
        """Plug it back in (a fresh, closed adapter behind the same link)."""
        with self._lock:
            self.is_open = self._bus_off = False
            self._flags = 0
            self.link.replug()

    def bus_off(self) -> None:
        """The controller goes bus-off: no frames pass until the host sends ``C`` and ``O``."""
        self._bus_off = True

    def inject_noise(self, data: bytes = b"t1X3\rT1234\rtZZZ8\r") -> None:
        """Write garbled bytes to the host, as a noisy serial line would."""
        with self._lock:
            self.link.write(data)

    def raise_flags(self, flags: int) -> None:
        """Set status flag bits reported (once) by the next ``F``."""
        self._flags |= flags

    @property
    def passing(self) -> bool:
        return self.is_open and not self._bus_off and self.link.plugged

    # -- adapter -> host -----------------------------------------------------------------------
    def to_host(self, msgs: Iterable[can.Message]) -> int:
        """Deliver frames to the host (one write); returns how many passed."""
        msgs = list(msgs)
        if not self.passing:
            self.stats["dropped"] += len(msgs)
            return 0
        stamp = int((time.monotonic() - self._t0) * 1000) if self.timestamps else None
        data = b"".join(format_frame(msg, stamp) for msg in msgs if not msg.is_error_frame)
        with self._lock:
            written = self.link.write(data)
        if written < len(data):
            self.stats["dropped"] += len(msgs)
            return 0
        self.stats["to_host"] += len(msgs)
        return len(msgs)

    def _reply(self, data: bytes) -> None:
        with self._lock:
            self.link.write(data)

    # -- host -> adapter -----------------------------------------------------------------------
    def _run(self) -> None:
        pending = b""
        while not self._stop.is_set():
            if not self.link.plugged:
                pending = b""
                self._stop.wait(0.01)
                continue
            chunk = self.link.read(65536, 0.05)
            if not chunk:
                continue
            pending += chunk
            *lines, pending = pending.split(b"\r")
            for line in lines:
                self._command(line)

    def _command(self, line: bytes) -> None:
        self.stats["commands"] += 1
        head, rest = line[:1], line[1:]
        reply = ERROR
        if head in (b"t", b"T", b"r", b"R"):
            msg = parse_frame(line)
            if msg is None:
                self.stats["bad_commands"] += 1
            elif self.is_open and not self.listen_only and not self._bus_off:
                self.stats["from_host"] += 1
                self.bus._rx.put(msg)
                reply = b"Z\r" if msg.is_extended_id else b"z\r"
        elif head == b"S" and rest in BITRATES and not self.is_open:
            self.bitrate, reply = BITRATES[rest], OK
        elif head == b"s" and len(rest) == 4 and set(rest) <= HEX_DIGITS and not self.is_open:
            reply = OK
        elif head in (b"O", b"L") and not rest and not self.is_open:
            self.is_open, self.listen_only, reply = True, head == b"L", OK
        elif head == b"C" and not rest:
            was_open, self.is_open, self._bus_off = self.is_open, False, False
            reply = OK if was_open else ERROR
        elif head == b"F" and not rest and self.is_open:
            flags = self._flags | (FLAG_BUS_ERROR | FLAG_ERROR_PASSIVE if self._bus_off else 0)
            self._flags = 0
            reply = b"F%02X\r" % flags
        elif head == b"V" and not rest:
            reply = f"V{self.version}\r".encode()
        elif head == b"N" and not rest:
            reply = f"N{self.serial_number}\r".encode()
        elif head == b"Z" and rest in (b"0", b"1") and not self.is_open:
            self.timestamps, reply = rest == b"1", OK
        elif head in (b"M", b"m", b"W", b"X", b"U", b"Q") or not line:
            reply = OK
        elif head not in b"SsOLCFVNZ":
            self.stats["bad_commands"] += 1  # unknown; known commands refused in this state are not
        self._reply(reply)
