"""The life cycle every device driver shares: open, handshake, stream, detect faults,
reconnect with capped exponential back-off, count errors, publish health.

A concrete driver implements ``open`` (transport + handshake), ``read_once`` (read and publish
what is available, raising ``DeviceError``/``OSError`` on a fault that needs a reconnect) and
``close``. ``run`` drives them until ``stop()``; ``start()`` does it on a thread.

Only device faults reconnect: ``DeviceError`` (``trundle.logs.errors``; a codec's ``ProtocolError``
or a ``TransportError``) and ``OSError`` (pyserial's ``SerialException`` is one; ``CanBus`` turns
python-can's ``CanError`` into ``DeviceError``). Any other exception is a bug: ``run`` marks the
driver ``crashed`` (ERROR in its diagnostics) and lets the exception out with its traceback, so
the daemon's supervisor logs and restarts it instead of the driver reconnecting forever.

No device is silent: ``diagnostics`` is ERROR while the device cannot be opened (naming the
error and its likely cause) and WARN while it is connected but its ``usable`` counter (scans,
wheel readings, frames) has not moved for ``silence_s``, with the driver's own guess why
(``silence_reason``: corrupt replies, node ids never seen, ...).

A port held by another program (``PortBusyError``) is retried like any open failure, since the
other program may let go (the daemon), and kept in ``port_busy`` so a command can end on it
instead of reconnecting in silence (``trundle record``).
"""

from __future__ import annotations

import contextlib
import errno
import signal
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Protocol

from trundle.logs import messages as m
from trundle.logs.errors import DeviceError, PortBusyError


class Sink(Protocol):
    """Where a driver sends messages: ``sink(topic, msg, log_time_ns)`` (log time = receive time)."""

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> object: ...


SILENCE_S = 3.0  # connected, but no usable data for this long: a WARN naming the likely cause

# what an open failure most likely means, by errno
OPEN_HINTS = {
    errno.ENOENT: "not plugged in, or a wrong path",
    errno.ENXIO: "no device behind the path (unplugged?)",
    errno.ENODEV: "no such device (unplugged, or a wrong interface name)",
    errno.EACCES: "no permission: add the user to the dialout (serial) or video (camera) group",
    errno.EPERM: "no permission",
    errno.EBUSY: "in use by another program",
    errno.ECONNREFUSED: "nothing listens at that address and port",
    errno.EHOSTUNREACH: "the host cannot be reached (network, address?)",
    errno.ETIMEDOUT: "no answer from the host (network, address?)",
    errno.ENOTTY: "not a serial port",
    errno.EAFNOSUPPORT: "this machine has no such network family (no SocketCAN here?)",
}


def open_hint(error: BaseException) -> str:
    """The likely cause of an open failure (from its errno, or that of its cause), "" if unknown."""
    seen: set[int] = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        code = getattr(error, "errno", None)
        if code is None and error.args and isinstance(error.args[0], int):  # termios.error and the like
            code = error.args[0]
        hint = OPEN_HINTS.get(code if isinstance(code, int) else -1)
        if hint:
            return hint
        error = error.__cause__ or error.__context__  # type: ignore[assignment]
    return ""


def wall_ns() -> int:
    """Host wall-clock time in nanoseconds (the time base of every stamp)."""
    return time.time_ns()


class SignalFlag:
    """A request (stop, split) raised by a signal handler and polled by the main loop.

    Raising it takes no lock: ``threading.Event.set`` in a handler deadlocks when a second signal
    lands while the first handler holds the event's lock (seen: SIGTERM twice froze the daemon).
    ``wait`` sleeps in short steps of ``poll_s`` so the request is acted on at once.
    """

    def __init__(self, poll_s: float = 0.1) -> None:
        self.raised = False
        self.poll_s = poll_s

    def raise_(self, *_: object) -> None:
        """Raise the flag (the signature of a signal handler)."""
        self.raised = True

    def wait(self, timeout_s: float) -> bool:
        """Sleep until the flag is raised or ``timeout_s`` passed; True if raised."""
        deadline = time.monotonic() + timeout_s
        while not self.raised and (left := deadline - time.monotonic()) > 0:
            time.sleep(min(self.poll_s, left))
        return self.raised


@contextlib.contextmanager
def stop_signals() -> Iterator[SignalFlag]:
    """A :class:`SignalFlag` that Ctrl-C (SIGINT) and SIGTERM raise while the block runs, the previous
    handlers back after it. Enter it before making anything the stop must clean up (a link, a file):
    a signal that lands earlier would end the program without the cleanup."""
    flag = SignalFlag()
    previous = {sig: signal.signal(sig, flag.raise_) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class Backoff:
    """Capped exponential back-off: ``initial_s``, times ``factor`` per failure, at most ``max_s``."""

    def __init__(self, initial_s: float = 0.1, max_s: float = 2.0, factor: float = 2.0) -> None:
        self.initial_s, self.max_s, self.factor = initial_s, max_s, factor
        self._next = initial_s

    def next_delay(self) -> float:
        delay = self._next
        self._next = min(self._next * self.factor, self.max_s)
        return delay

    def reset(self) -> None:
        self._next = self.initial_s


class Driver(ABC):
    """Supervised device loop with counters and a diagnostics status.

    ``counters`` always has ``reconnects`` and ``errors``; drivers add their own (``scans``,
    ``checksum_errors``, ``frames``, ...). ``state`` is one of connecting, streaming, waiting, stopped
    and crashed (a bug escaped ``run``; ``last_error`` names it).
    ``usable`` names the counter of good output (what a silent device does not increase);
    ``open_error`` holds why the last open failed ("" once the device opened), ``port_busy`` the
    error if that was another program holding the port. ``serial_port`` is the local serial port
    the driver opens ("" for none), checked free by a command before it creates its output.
    """

    usable = "scans"
    silence_s = SILENCE_S
    serial_port = ""

    def __init__(self, name: str, sink: Sink, *, hardware_id: str = "", backoff: Backoff | None = None,
                 clock: Callable[[], int] = wall_ns) -> None:
        self.name = name
        self.sink = sink
        self.hardware_id = hardware_id
        self.backoff = backoff or Backoff()
        self.clock = clock
        self.counters: Counter[str] = Counter(reconnects=0, errors=0)
        self.state = "stopped"
        self.last_error = ""
        self.open_error = ""
        self.port_busy: PortBusyError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected_once = False
        self._connected_at: float | None = None  # monotonic s of the last successful open
        self._usable_count = 0
        self._usable_at = 0.0  # monotonic s when the usable counter last moved (or the device first opened)
        self._answered = False  # the last error came from a device that opened and answered (bad data)

    @abstractmethod
    def open(self) -> None:
        """Open the transport and bring the device to streaming (handshake)."""

    @abstractmethod
    def read_once(self) -> None:
        """Read what the device has sent and publish it; raise on a fault that needs a reconnect."""

    @abstractmethod
    def close(self) -> None:
        """Release the transport; must not raise."""

    def static_messages(self) -> list[tuple[str, m.Message]]:
        """Latched messages (static transforms, calibration) to log once per file."""
        return []

    def publish(self, topic: str, msg: m.Message, log_time_ns: int | None = None) -> None:
        self.sink(topic, msg, self.clock() if log_time_ns is None else log_time_ns)

    def run(self) -> None:
        """Open, stream and reconnect until ``stop()``; never raises for device faults
        (``DeviceError``, ``OSError``). Anything else is a bug: the driver is ``crashed`` and the
        exception propagates."""
        while not self._stop.is_set():
            self.state = "connecting"
            opened = False
            try:
                self.open()
                opened = True
                if self._connected_once:
                    self.counters["reconnects"] += 1
                self._connected_once = True
                self.open_error = ""
                self.port_busy = None
                self._connected_at = time.monotonic()
                if not self._usable_at:  # silence is counted from the first connection, across reconnects
                    self._usable_at = self._connected_at
                    self._usable_count = self.counters[self.usable]
                self.backoff.reset()
                self.state = "streaming"
                while not self._stop.is_set():
                    self.read_once()
            except (DeviceError, OSError) as error:
                self.counters["errors"] += 1
                self.last_error = f"{type(error).__name__}: {error}"
                self._answered = opened and isinstance(error, DeviceError)
                if not opened:
                    hint = open_hint(error)
                    self.open_error = f"{error}" + (f" ({hint})" if hint else "")
                    self.port_busy = error if isinstance(error, PortBusyError) else None
            except Exception as error:
                self.state = "crashed"
                self.last_error = f"{type(error).__name__}: {error}"
                raise
            finally:
                self._connected_at = None
                self.close()
            if not self._stop.is_set():
                self.state = "waiting"
                self._stop.wait(self.backoff.next_delay())
        self.state = "stopped"

    def start(self) -> threading.Thread:
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name=f"driver-{self.name}", daemon=True)
        self._thread.start()
        return self._thread

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def finish(self) -> None:
        """End the run loop from inside the driver (e.g. a file source reached its end)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def silence_reason(self) -> str:
        """Why a connected device gives no usable data, as far as the driver can tell ("" if it cannot)."""
        return ""

    def counted(self, names: tuple[str, ...]) -> str:
        """The counters ``names`` that are not zero, as ``"12 checksum errors, 3 truncated"``."""
        return ", ".join(f"{self.counters[n]} {n.replace('_', ' ')}" for n in names if self.counters[n])

    def health_status(self, now: float | None = None) -> tuple[int, str]:
        """``(level, message)``: ERROR while the device cannot be opened, WARN while it is connected
        but silent for ``silence_s`` (or reconnecting), OK while streaming, STALE once stopped.
        ``now`` is monotonic seconds (default: now)."""
        now = time.monotonic() if now is None else now
        if self.state == "stopped":
            return m.STALE, "stopped"
        if self.state == "crashed":
            return m.ERROR, f"driver crashed: {self.last_error}"
        if self.state != "streaming" and self.open_error:
            named = self.hardware_id and self.hardware_id in self.open_error
            return m.ERROR, self.open_error if named else f"cannot open {self.hardware_id}: {self.open_error}"
        silent_s = self._silent_s(now)
        if silent_s >= self.silence_s and (self.state == "streaming" or self._answered):
            # a device that opens but never gives usable data also cycles through reconnects: the
            # silence and its reason are the news, whichever phase of the cycle this call lands in
            reason = self.silence_reason()
            again = "" if self.state == "streaming" else f"; {self.state} after {self.last_error}"
            return m.WARN, (f"connected, but no {self.usable.replace('_', ' ')} for {silent_s:.0f} s"
                            + (f": {reason}" if reason else "") + again)
        if self.state != "streaming" or self._connected_at is None:
            return m.WARN, f"{self.state}" + (f" after {self.last_error}" if self.last_error else "")
        return m.OK, "streaming"

    def _silent_s(self, now: float) -> float:
        """Seconds since the usable counter last moved (0 before the first connection)."""
        if not self._usable_at:
            return 0.0
        count = self.counters[self.usable]
        if count != self._usable_count:
            self._usable_count, self._usable_at = count, now
        return now - self._usable_at

    def diagnostics(self) -> m.DiagnosticStatus:
        level, message = self.health_status()
        values = [("state", self.state), *sorted((k, str(v)) for k, v in self.counters.items())]
        if self.last_error:
            values.append(("last_error", self.last_error))
        return m.DiagnosticStatus(level, self.name, message, self.hardware_id, tuple(values))
