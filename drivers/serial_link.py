"""The pyserial side of a streaming device driver (device path or ``socket://`` URL).

Reads return whatever has arrived (waiting at most ``read_timeout_s`` for the first byte) and
note when data last came, so a driver can tell a silent device from a quiet moment; ``drain``
drops input until the line has been quiet for a while (a device left streaming by a crashed
client); ``close`` sends last words (stop streaming, stop the motor) and never raises.
"""

from __future__ import annotations

import errno
import select
import time
from typing import Callable

import serial

from trundle.drivers.lifecycle import DeviceError


class SerialLink:
    """An open pyserial port plus the receive bookkeeping drivers need."""

    def __init__(self, url: str, baudrate: int, read_timeout_s: float = 0.05) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        # non-blocking reads after a select: pyserial's socket:// reports at most 1 byte waiting,
        # so reading ``in_waiting`` bytes would take a TCP stream one byte per call
        self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, write_timeout=1.0)
        self.last_rx = time.monotonic()

    def read(self) -> bytes:
        """What has arrived, or (after up to ``read_timeout_s``) nothing."""
        ready, _, _ = select.select([self.port.fileno()], [], [], self.read_timeout_s)
        if not ready:
            return b""
        data = self.port.read(1 << 16)
        if data:
            self.last_rx = time.monotonic()
        return data

    def write(self, data: bytes) -> None:
        self.port.write(data)

    @property
    def silent_s(self) -> float:
        """Seconds since data last arrived (or since the port was opened)."""
        return time.monotonic() - self.last_rx

    def drain(self, quiet_s: float, limit_s: float = 2.0) -> int:
        """Read and drop until nothing came for ``quiet_s``; returns the bytes dropped."""
        dropped, start = 0, time.monotonic()
        quiet_since = start
        while time.monotonic() - quiet_since < quiet_s:
            if time.monotonic() - start > limit_s:
                raise DeviceError(f"{self.url} keeps sending after being told to stop")
            data = self.read()
            if data:
                dropped += len(data)
                quiet_since = time.monotonic()
        return dropped

    def close(self, farewell: Callable[[serial.SerialBase], None] | None = None) -> None:
        """Let ``farewell`` write to the port if it is still open, then close; never raises."""
        try:
            if farewell is not None and self.port.is_open:
                farewell(self.port)
                self.port.flush()
        except (OSError, serial.SerialException, ValueError):
            pass
        try:
            self.port.close()
        except (OSError, serial.SerialException):
            pass


def set_modem_line(port: serial.SerialBase, name: str, value: bool) -> bool:
    """Set DTR or RTS; False when the port has no modem lines (a pty: ENOTTY/EINVAL)."""
    try:
        setattr(port, name, value)
        return True
    except OSError as error:
        if error.errno in (errno.ENOTTY, errno.EINVAL):
            return False
        raise
