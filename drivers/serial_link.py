"""The pyserial side of a streaming device driver (device path or ``socket://`` URL).

Reads return whatever has arrived (waiting at most ``read_timeout_s`` for the first byte) and
note when data last came, so a driver can tell a silent device from a quiet moment. A streaming
driver sets ``batch_s``: reads then come at most that often, each taking everything that arrived
meanwhile, so a device trickling small packets (a 1 Mbaud RPLIDAR sends a capsule every ~1 ms)
costs one decode per batch instead of one per packet, and a read that filled the tty layer's
buffer waits up to ``batch_s`` for the rest of the burst behind it. ``drain`` drops input until
the line has been quiet for a while (a device left streaming by a crashed client); ``close``
sends last words (stop streaming, stop the motor) and never raises.

Every serial port trundle opens goes through :func:`open_port`, which takes the port's lock
(pyserial's ``exclusive``: a ``flock`` on the device node), so a second program on the same port
fails at once with ``PortBusyError`` naming the port and the lock's holder, instead of both
programs reading half the data.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import termios
import time
from collections.abc import Callable
from typing import Any

import serial

from trundle.logs.errors import DeviceError, PortBusyError
from trundle.logs.locks import holder_name, lock_holder

STREAM_BATCH_S = 0.05  # the ``batch_s`` of a streaming laser: 20 reads a second, scans up to 50 ms late
TTY_BUFFER = 4095  # the most the Linux tty layer hands over at once (N_TTY_BUF_SIZE - 1): more may be behind
EMPTY_READS_S = 0.5  # how long a tty that says it is ready may read nothing before it counts as gone


def busy_error(port: str, holder: int | None) -> PortBusyError:
    """The one line for ``port`` held by another program (pid ``holder`` and its command name if known)."""
    return PortBusyError(f"{port} is in use by {holder_name(holder)}: stop it, or use another port")


def check_free(port: str) -> None:
    """Raise ``PortBusyError`` if another program holds the lock on serial port ``port`` (how a
    command refuses a busy port before it creates its output)."""
    holder = lock_holder(port)
    if holder is not None:
        raise busy_error(port, holder)


def open_port(url: str, **settings: Any) -> serial.Serial:
    """``url`` (a device path or pyserial URL) opened by pyserial with the port's lock taken;
    ``PortBusyError`` if another program holds it. ``settings`` are pyserial's (baudrate, timeout...)."""
    try:
        return serial.serial_for_url(url, exclusive=True, **settings)
    except serial.SerialException as error:
        if error.errno in (errno.EAGAIN, errno.EWOULDBLOCK):  # pyserial's flock(LOCK_EX | LOCK_NB) failed
            raise busy_error(url, lock_holder(url)) from None
        raise


class SerialLink:
    """An open pyserial port plus the receive bookkeeping drivers need."""

    def __init__(self, url: str, baudrate: int, read_timeout_s: float = 0.05, batch_s: float = 0.0) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.batch_s = batch_s
        # non-blocking reads after a select: pyserial's socket:// reports at most 1 byte waiting,
        # so reading ``in_waiting`` bytes would take a TCP stream one byte per call
        self.port = open_port(url, baudrate=baudrate, timeout=0, write_timeout=1.0)
        self._fd: int | None = getattr(self.port, "fd", None)  # a tty: read directly (pyserial selects again)
        self._last_read = 0.0
        self._empty_since: float | None = None
        self.last_rx = time.monotonic()

    def read(self) -> bytes:
        """What has arrived, or (after up to ``read_timeout_s``) nothing."""
        ready, _, _ = select.select([self.port.fileno()], [], [], self.read_timeout_s)
        if not ready:
            return b""
        wait = self._last_read + self.batch_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        data = self._rest_of_burst(self._available())
        self._last_read = time.monotonic()
        if data:
            self.last_rx = self._last_read
        return data

    def _rest_of_burst(self, first: bytes) -> bytes:
        """The tty layer hands a burst over in pieces (at most 4095 bytes, and a busy host's pty
        less): take what is already behind the first, and after a full piece wait up to
        ``batch_s`` for the rest (a 6.5 kB SCIP scan comes in two), so one read gets the burst."""
        parts = [first]
        while parts[-1] and len(parts) < 64:
            wait = (self.batch_s or self.read_timeout_s) if len(parts[-1]) >= TTY_BUFFER else 0.0
            if not select.select([self.port.fileno()], [], [], wait)[0]:
                break
            parts.append(self._available())
        return b"".join(parts)

    def _available(self) -> bytes:
        """One read of what is there. A tty that says it is ready and then reads nothing is
        either gone (its device node with it: raised at once, in pyserial's words) or, on a busy
        host, a pty whose input is not there yet: nothing read, unless that lasts."""
        if self._fd is None:
            return self.port.read(1 << 16)
        try:
            data = os.read(self._fd, 1 << 16)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as error:
            raise serial.SerialException(f"read failed: {error}") from None
        if data:
            self._empty_since = None
            return data
        now = time.monotonic()
        self._empty_since = self._empty_since or now
        if not os.path.exists(self.url) or now - self._empty_since > EMPTY_READS_S:
            raise serial.SerialException("device reports readiness to read but returned no data "
                                         "(device disconnected or multiple access on port?)")
        return b""

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

    def close(self, farewell: Callable[[serial.SerialBase], object] | None = None) -> None:
        """Let ``farewell`` write to the port if it is still open, then close; never raises."""
        try:
            if farewell is not None and self.port.is_open:
                farewell(self.port)
                self.port.flush()
        except (OSError, serial.SerialException, ValueError, termios.error):  # tcdrain on a line that died: EIO
            pass
        with contextlib.suppress(OSError, serial.SerialException, termios.error):
            self.port.close()


def set_modem_line(port: serial.SerialBase, name: str, value: bool) -> bool:
    """Set DTR or RTS; False when the port has no modem lines (a pty: ENOTTY/EINVAL)."""
    try:
        setattr(port, name, value)
        return True
    except OSError as error:
        if error.errno in (errno.ENOTTY, errno.EINVAL):
            return False
        raise
