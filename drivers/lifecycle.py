"""The life cycle every device driver shares: open, handshake, stream, detect faults,
reconnect with capped exponential back-off, count errors, publish health.

A concrete driver implements ``open`` (transport + handshake), ``read_once`` (read and publish
what is available, raising ``DeviceError``/``OSError`` on a fault that needs a reconnect) and
``close``. ``run`` drives them until ``stop()``; ``start()`` does it on a thread.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from typing import Callable, Protocol

from trundle.logs import messages as m


class Sink(Protocol):
    """Where a driver sends messages: ``sink(topic, msg, log_time_ns)`` (log time = receive time)."""

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> object: ...


class DeviceError(Exception):
    """A device fault that calls for closing and reopening the transport."""


def wall_ns() -> int:
    """Host wall-clock time in nanoseconds (the time base of every stamp)."""
    return time.time_ns()


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
    ``checksum_errors``, ``frames``, ...). ``state`` is one of connecting, streaming, waiting, stopped.
    """

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
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected_once = False

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
        """Open, stream and reconnect until ``stop()``; never raises for device faults."""
        while not self._stop.is_set():
            self.state = "connecting"
            try:
                self.open()
                if self._connected_once:
                    self.counters["reconnects"] += 1
                self._connected_once = True
                self.backoff.reset()
                self.state = "streaming"
                while not self._stop.is_set():
                    self.read_once()
            except (DeviceError, OSError, ValueError) as error:
                self.counters["errors"] += 1
                self.last_error = f"{type(error).__name__}: {error}"
            finally:
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

    def diagnostics(self) -> m.DiagnosticStatus:
        level = m.OK if self.state == "streaming" else m.WARN if self.state != "stopped" else m.STALE
        values = [("state", self.state), *sorted((k, str(v)) for k, v in self.counters.items())]
        if self.last_error:
            values.append(("last_error", self.last_error))
        return m.DiagnosticStatus(level, self.name, self.state, self.hardware_id, tuple(values))
