"""SLCAN (Lawicel) serial CAN adapters: the frame line codec and the host's bus.

Lines end with CR (OK; BEL is an error). Frames are ``tIIILDD..`` / ``TIIIIIIIILDD..`` (data,
11- or 29-bit id, DLC digit, hex bytes) and ``rIIIL`` / ``RIIIIIIIIL`` (remote); an adapter with
time stamps on (``Z1``) appends four hex digits of ms to the frames it receives. The host sends
``C`` (close), ``Sn`` (bit rate), ``O`` (open), ``F`` (status flags, answered ``Fxx``) and frames
(acknowledged ``z`` / ``Z``). The emulator (``tools/emulators/slcan_emulator.py``) is the other side
of the same codec.

:class:`SlcanBus` owns its serial port and its line reading and hands python-can nothing but its
public plug-in interface (``can.BusABC``: ``_recv_internal``, ``send``, ``shutdown``), so it does
not depend on the internals of python-can's own slcan interface. It reads every byte available
per system call: python-can 4.6.1's slcan reads one byte per call (hardbyte/python-can#2027),
which caps reception near 3 k frames/s on an idle machine and far lower on a loaded one.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import can
import serial

from trundle.drivers.serial_link import SerialLink
from trundle.logs.errors import ProtocolError

OK, ERROR = b"\r", b"\x07"
BITRATE_COMMANDS = {10000: "S0", 20000: "S1", 50000: "S2", 100000: "S3", 125000: "S4", 250000: "S5",
                    500000: "S6", 750000: "S7", 1000000: "S8", 83300: "S9"}  # as python-can and CANable
FRAME_KINDS = b"tTrR"
STAMP_DIGITS = 4  # the ms stamp (0..59999, hex) an adapter appends with Z1
HEX_DIGITS = frozenset(b"0123456789ABCDEFabcdef")
_READ_TIMEOUT_S = 0.005  # longest single wait on the port: bounds how late a deadline is noticed


def format_frame(msg: can.Message, stamp_ms: int | None = None) -> bytes:
    """The SLCAN line (with CR) for ``msg``: what a host transmits, or with ``stamp_ms`` (ms) what
    an adapter with time stamps on sends for a received frame."""
    if msg.is_remote_frame:
        line = (f"R{msg.arbitration_id:08X}{msg.dlc:d}" if msg.is_extended_id
                else f"r{msg.arbitration_id:03X}{msg.dlc:d}")
    else:
        head = f"T{msg.arbitration_id:08X}" if msg.is_extended_id else f"t{msg.arbitration_id:03X}"
        line = f"{head}{len(msg.data):d}{bytes(msg.data).hex().upper()}"
    if stamp_ms is not None:
        line += f"{stamp_ms % 60000:04X}"
    return line.encode() + OK


def parse_frame(line: bytes) -> can.Message | None:
    """A frame line (``t``/``T``/``r``/``R``, no CR, no time stamp) as a message; None if malformed."""
    kind = line[:1]
    extended = kind in (b"T", b"R")
    id_len = 8 if extended else 3
    if not kind or kind not in FRAME_KINDS or len(line) < 2 + id_len:
        return None
    ident, dlc_char = line[1:1 + id_len], line[1 + id_len:2 + id_len]
    if not (set(ident) <= HEX_DIGITS and dlc_char.isdigit()):
        return None
    can_id, dlc = int(ident, 16), int(dlc_char)
    if dlc > 8 or can_id > (0x1FFFFFFF if extended else 0x7FF):
        return None
    payload = line[2 + id_len:]
    if kind in (b"r", b"R"):
        if payload:
            return None
        return can.Message(arbitration_id=can_id, is_extended_id=extended, is_remote_frame=True, dlc=dlc)
    if len(payload) != 2 * dlc or not set(payload) <= HEX_DIGITS:
        return None
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=bytes.fromhex(payload.decode()))


def parse_received(line: bytes) -> can.Message | None:
    """A frame line from an adapter, with or without its ``Z1`` time stamp (dropped: it wraps every
    minute and has ms steps); None if malformed."""
    msg = parse_frame(line)
    stamp = line[-STAMP_DIGITS:]
    if msg is None and len(line) > STAMP_DIGITS and set(stamp) <= HEX_DIGITS:
        msg = parse_frame(line[:-STAMP_DIGITS])
    return msg


class SlcanBus(can.BusABC):
    """A Lawicel/SLCAN adapter on serial port ``channel`` (a path or a pyserial URL) at CAN
    ``bitrate``, as a python-can bus. Opening sends ``C``, the bit rate and ``O``.

    Reading is for one thread; writing (``send``, commands) is safe from any. ``recv`` returns
    frames stamped with host time at receipt; a garbled frame line raises
    ``ProtocolError`` (the caller counts it; the next ``recv`` goes on with the next line). Port
    failures raise ``can.CanOperationError`` (``CanInitializationError`` when opening), as
    python-can's interfaces do, except a port another program holds: ``PortBusyError``.
    :meth:`status_flags` and :meth:`restart` are the ``F`` and ``C``/``O`` commands python-can
    has no call for.
    """

    def __init__(self, channel: str, bitrate: int = 500000, tty_baudrate: int = 115200,
                 sleep_after_open: float = 0.0, **kwargs: Any) -> None:
        if bitrate not in BITRATE_COMMANDS:
            raise ValueError(f"SLCAN bit rate {bitrate} not one of {', '.join(map(str, sorted(BITRATE_COMMANDS)))}")
        try:
            self.link = SerialLink(channel, tty_baudrate, read_timeout_s=_READ_TIMEOUT_S)
        except (serial.SerialException, OSError, ValueError) as error:
            raise can.CanInitializationError(f"cannot open {channel}: {error}") from error
        self.port = self.link.port
        self._pending = bytearray()  # bytes read after the last complete line
        self._lines: deque[bytes] = deque()  # complete lines (without CR/BEL) not handed out yet
        self._write_lock = threading.Lock()  # a command and a frame sent from two threads stay whole
        time.sleep(sleep_after_open)
        try:
            for command in ("C", BITRATE_COMMANDS[bitrate], "O"):
                self.write_command(command)
        except can.CanOperationError as error:
            self.port.close()
            raise can.CanInitializationError(str(error)) from error
        super().__init__(channel, **kwargs)

    # -- the serial line -----------------------------------------------------------------------
    def write_command(self, command: str) -> None:
        """Send one command line (CR added); safe from any thread."""
        self._write(command.encode("ascii") + OK)

    def _write(self, line: bytes) -> None:
        try:
            with self._write_lock:
                self.port.write(line)
        except (serial.SerialException, OSError) as error:
            raise can.CanOperationError("Could not write to serial device") from error

    def read_line(self, timeout_s: float | None) -> bytes | None:
        """The next line the adapter sent (without its CR or BEL), or None once ``timeout_s`` (s;
        None waits for ever) passed. Reads every byte the port holds in one system call
        (:class:`SerialLink`: a select and a read, where pyserial's ``read(in_waiting)`` took two
        reads and three system calls a frame)."""
        if self._lines:   # read before: no deadline to keep (two pyserial Timeouts were a fifth of a frame's recv)
            return self._lines.popleft()
        deadline = serial.Timeout(timeout_s)  # type: ignore[arg-type]  # pyserial's Timeout takes None: no deadline
        while not self._lines:
            try:
                chunk = self.link.read()
            except (serial.SerialException, OSError) as error:
                raise can.CanOperationError("Could not read from serial device") from error
            if chunk:
                self._pending += chunk.replace(ERROR, OK)
                *lines, rest = self._pending.split(OK)
                self._lines.extend(bytes(line) for line in lines)
                self._pending = bytearray(rest)
            elif deadline.expired():
                return None
        return self._lines.popleft()

    # -- python-can's bus interface ------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline: serial.Timeout | None = None   # started once the adapter must be waited for
        while True:
            if deadline is None and not self._lines:
                deadline = serial.Timeout(timeout)  # type: ignore[arg-type]  # pyserial's Timeout takes None: no deadline
            line = self.read_line(None if deadline is None else deadline.time_left())
            if line is None:
                return None, False
            if line[:1] and line[:1] in FRAME_KINDS:
                msg = parse_received(line)
                if msg is None:
                    raise ProtocolError(f"garbled SLCAN frame line {line[:32]!r}")
                msg.timestamp = time.time()
                return msg, False
            if deadline is not None and deadline.expired():  # a reply (OK, z, Fxx, ...) and no time left
                return None, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if timeout != self.port.write_timeout:
            self.port.write_timeout = timeout
        self._write(format_frame(msg))

    def shutdown(self) -> None:
        """Close the CAN channel (``C``) and release the port; a pulled adapter's failing ``C`` is ignored."""
        super().shutdown()
        try:
            self.write_command("C")
        except can.CanOperationError:
            pass
        finally:
            self.port.close()

    # -- SLCAN commands python-can has no call for ---------------------------------------------
    def status_flags(self, timeout_s: float) -> int | None:
        """The adapter's ``F`` status flags, or None without an answer within ``timeout_s`` (s).
        Frames that arrive meanwhile stay queued for ``recv``."""
        self.write_command("F")
        deadline = serial.Timeout(timeout_s)
        held: list[bytes] = []
        try:
            while (line := self.read_line(deadline.time_left())) is not None:
                if line[:1] == b"F" and len(line) >= 3:
                    try:
                        return int(line[1:3], 16)
                    except ValueError:
                        return None
                if line[:1] and line[:1] in FRAME_KINDS:
                    held.append(line)
            return None
        finally:
            self._lines.extendleft(reversed(held))

    def restart(self) -> None:
        """Close and reopen the CAN channel (``C`` then ``O``): how a Lawicel adapter leaves bus-off."""
        self.write_command("C")
        self.write_command("O")
