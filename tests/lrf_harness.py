"""Test harness for the laser drivers: a recording sink, waiting on conditions, a running pair.

Waits are on counters and message counts with a generous ceiling, never on wall-clock
durations, so a loaded machine only makes the tests slower, not flaky.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from camera_clips import wait_for

from trundle.drivers.lifecycle import Driver
from trundle.logs import messages as m
from trundle.tools.emulators.device_server import DeviceServer

CEILING_S = 60.0


class Recorder:
    """A Sink keeping every message with its log time."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.messages: list[tuple[str, m.Message, int]] = []

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> bool:
        with self.lock:
            self.messages.append((topic, msg, log_time_ns))
        return True

    def topic(self, name: str) -> list[m.Message]:
        with self.lock:
            return [msg for topic, msg, _ in self.messages if topic == name]

    def scans(self) -> list[m.LaserScan]:
        return self.topic("/scan")  # type: ignore[return-value]


def wait_until(predicate: Callable[[], bool], what: str, timeout_s: float = CEILING_S) -> None:
    """Poll until ``predicate`` holds; a hang guard with a generous ceiling, not a timing check."""
    wait_for(predicate, timeout_s, what)


@contextmanager
def running(server: DeviceServer, driver: Driver) -> Iterator[tuple[DeviceServer, Driver]]:
    """Serve the device (unless already served) and run the driver; stop both, driver first,
    letting the device read the driver's last words (stop streaming, stop the motor)."""
    if server._thread is None:
        server.start()
    driver.start()
    try:
        yield server, driver
    finally:
        driver.stop()
        try:
            # nothing left unread, and the last read long enough ago to have been handled (a loaded
            # machine can leave the server thread unscheduled for longer than the driver's pause)
            wait_until(lambda: not server.unread() and time.time_ns() - server.last_input_ns > 300_000_000,
                       "the device to read the rest", timeout_s=10.0)
        finally:
            server.stop()


def inject(server: DeviceServer, kind: str) -> None:
    """Make the device inject ``kind`` into its next scan, exactly once."""
    with server.lock:
        server.device.faults.force(kind)


def replug_delay_ns(server: DeviceServer, driver: Driver, sink: Recorder) -> int:
    """Unplug the device (its plan says for how long), wait for it to come back and for a scan
    measured after that; returns how long after the replug that scan was measured."""
    inject(server, "unplug")
    wait_until(lambda: len(server.replugged_ns) == 1, "the replug")
    wait_until(lambda: any(s.stamp_ns > server.replugged_ns[0] for s in sink.scans()), "a scan after the replug")
    replug = server.replugged_ns[0]
    return min(s.stamp_ns for s in sink.scans() if s.stamp_ns > replug) - replug


MUTATIONS = ("flip", "insert", "delete", "replace")


def mutate(stream: bytearray, how: str, where: int, value: int) -> None:
    """Damage one byte of ``stream`` in place: flip bit ``value % 8``, insert or write ``value``,
    or delete; ``where`` is taken modulo the length (for hypothesis-drawn positions)."""
    i = where % len(stream)
    if how == "flip":
        stream[i] ^= 1 << (value % 8)
    elif how == "insert":
        stream.insert(i, value)
    elif how == "delete":
        del stream[i]
    else:
        stream[i] = value
