"""Driver supervision: each driver on its own thread, restarted with a back-off when it crashes.

A crash is an exception escaping ``Driver.run`` (a bug: anything but ``DeviceError``/``OSError``);
device faults are the drivers' own business (they reconnect themselves). A crash is logged on
stderr (the journal) with its traceback and shown in the status and ``/diagnostics``. Each
supervised driver counts its messages per topic, so its status and ``/diagnostics`` entry show
rates next to the driver's own counters.
"""

from __future__ import annotations

import collections
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trundle.logs import messages as m

if TYPE_CHECKING:
    from trundle.drivers.lifecycle import Driver
    from trundle.tools.config.robot import Device

STABLE_RUN_S = 60.0  # a driver that ran this long before crashing starts its back-off afresh


class TopicRates:
    """Message counts per topic and the rates (Hz) over the last measuring period."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.rates: dict[str, float] = {}
        self._last: dict[str, int] = {}
        self._last_t = time.monotonic()

    def count(self, topic: str) -> None:
        """One more message on ``topic`` (called on the driver's thread)."""
        self.counts[topic] += 1

    def update(self, now: float) -> None:
        """Rates since the previous update, ``now`` on the ``time.monotonic`` clock (s)."""
        dt = now - self._last_t
        if dt <= 0:
            return
        counts = dict(self.counts)
        self.rates = {t: (n - self._last.get(t, 0)) / dt for t, n in sorted(counts.items())}
        self._last, self._last_t = counts, now


class Supervised:
    """One driver on a daemon thread; an exception escaping ``Driver.run`` is a crash, reported
    through ``on_crash`` and restarted by ``restart_if_due`` after a doubling delay (s)."""

    def __init__(self, device: Device, driver: Driver, rates: TopicRates, restart_delay_s: float,
                 max_delay_s: float, on_crash: Callable[[Supervised], None] = lambda s: None) -> None:
        self.device, self.driver, self.rates, self.on_crash = device, driver, rates, on_crash
        self.initial_delay_s, self.max_delay_s = restart_delay_s, max_delay_s
        self.delay_s = restart_delay_s
        self.crashes = 0
        self.last_crash = ""
        self.restart_at: float | None = None
        self.started_at = 0.0
        self.thread: threading.Thread | None = None

    def start(self) -> None:
        """Run the driver on a new thread."""
        self.restart_at = None
        self.started_at = time.monotonic()
        self.thread = threading.Thread(target=self._run, name=f"driver-{self.device.name}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.driver.run()
        except BaseException as error:  # noqa: BLE001 -- a driver bug must not take the daemon down
            frame = traceback.extract_tb(error.__traceback__)[-1] if error.__traceback__ else None
            where = f" at {Path(frame.filename).name}:{frame.lineno}" if frame else ""
            self.last_crash = f"{type(error).__name__}: {error}{where}"
            self.crashes += 1
            now = time.monotonic()
            if now - self.started_at > STABLE_RUN_S:
                self.delay_s = self.initial_delay_s
            self.restart_at = now + self.delay_s
            self.delay_s = min(self.delay_s * 2.0, self.max_delay_s)
            trace = "".join(traceback.format_exception(type(error), error, error.__traceback__))
            print(f"trundle daemon: driver {self.device.name} crashed ({self.last_crash}); "
                  f"restarting in {self.restart_at - now:.1f} s\n{trace}", end="", file=sys.stderr, flush=True)
            self.on_crash(self)

    @property
    def crashed(self) -> bool:
        """True from a crash until the restart."""
        return self.restart_at is not None

    @property
    def state(self) -> str:
        """``crashed``, else the driver's own state (``streaming``, ``connecting``, ...)."""
        return "crashed" if self.crashed else self.driver.state

    def restart_if_due(self, now: float) -> None:
        """Restart a crashed driver once its delay is over (``now`` on the ``time.monotonic`` clock, s)."""
        if self.restart_at is not None and now >= self.restart_at:
            print(f"trundle daemon: restarting driver {self.device.name}", file=sys.stderr, flush=True)
            self.start()

    def stop(self, timeout_s: float) -> None:
        """Stop the driver and wait up to ``timeout_s`` (s) for its thread; no restart after this."""
        self.restart_at = None
        self.driver.stop(timeout_s)
        if self.thread is not None:
            self.thread.join(timeout_s)

    def status(self) -> dict[str, Any]:
        """This device's entry in the status answer (JSON-able)."""
        driver, rates = self.driver, self.rates
        return {"name": self.device.name, "family": self.device.family, "url": self.device.url, "state": self.state,
                "rates_hz": {t: round(r, 2) for t, r in rates.rates.items()},
                "messages": dict(rates.counts), "errors": int(driver.counters.get("errors", 0)),
                "reconnects": int(driver.counters.get("reconnects", 0)), "crashes": self.crashes,
                "last_error": driver.last_error, "last_crash": self.last_crash,
                "counters": {k: int(v) for k, v in sorted(driver.counters.items())}}

    def diagnostics(self, robot: str) -> m.DiagnosticStatus:
        """The driver's diagnostics plus rates and crashes, named ``robot/device``; ERROR while crashed."""
        status = self.driver.diagnostics()
        values = (*status.values, *((f"rate {t}", f"{r:.2f} Hz") for t, r in self.rates.rates.items()),
                  ("crashes", str(self.crashes)))
        level, message = status.level, status.message
        if self.crashed:
            level, message = m.ERROR, f"driver crashed: {self.last_crash}"
            values = (*values, ("last_crash", self.last_crash))
        return m.DiagnosticStatus(level, f"{robot}/{self.device.name}", message, status.hardware_id, values)
