"""Saying when a device goes bad and when it recovers: one line each, never a flood.

``HealthReporter.update`` takes the devices' diagnostics (as often as they are published) and
calls ``say`` once when a device has been WARN or ERROR for ``grace_s`` (so a device that is
still starting up is not reported), again only if it gets worse (WARN -> ERROR), and once when it
is OK again. ``trundle record`` says it on stderr, the daemon on stderr too (the journal).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from trundle.logs import messages as m

LEVEL_NAMES = {m.OK: "OK", m.WARN: "WARN", m.ERROR: "ERROR", m.STALE: "STALE"}
GRACE_S = 2.0


@dataclass
class _Watch:
    bad_since: float | None = None
    said: int = m.OK  # the level last said (OK: nothing said, or the recovery)


class HealthReporter:
    """One line through ``say`` per device turning bad (after ``grace_s`` s), worse, or well again."""

    def __init__(self, say: Callable[[str], None], grace_s: float = GRACE_S) -> None:
        self.say, self.grace_s = say, grace_s
        self._watch: dict[str, _Watch] = {}

    def update(self, statuses: Iterable[m.DiagnosticStatus], now: float | None = None) -> None:
        """Look at each status (``now``: monotonic s); stopped (STALE) devices are left alone."""
        now = time.monotonic() if now is None else now
        for status in statuses:
            watch = self._watch.setdefault(status.name, _Watch())
            if status.level in (m.WARN, m.ERROR):
                if watch.bad_since is None:
                    watch.bad_since = now
                if now - watch.bad_since >= self.grace_s and status.level > watch.said:
                    watch.said = status.level
                    self.say(f"{status.name}: {LEVEL_NAMES[status.level]}: {status.message}")
            elif status.level == m.OK:
                if watch.said != m.OK:
                    self.say(f"{status.name}: recovered: {status.message}")
                watch.bad_since, watch.said = None, m.OK

    @property
    def reported(self) -> dict[str, int]:
        """Devices whose trouble was said and not yet recovered: name -> level."""
        return {name: w.said for name, w in self._watch.items() if w.said != m.OK}
