"""Play a log's messages into callbacks in log-time order, at real time or any rate."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable

from trundle.logs.reader import LogMessage, LogReader


def replay(path: str | os.PathLike[str], callback: Callable[[LogMessage], object], rate: float = 1.0,
           topics: Iterable[str] | None = None, start_ns: int | None = None, end_ns: int | None = None,
           sleep: Callable[[float], None] = time.sleep, clock: Callable[[], float] = time.monotonic) -> int:
    """Deliver each decoded message to ``callback``; returns how many were delivered.

    ``rate`` scales time: 1.0 keeps the log's spacing, 2.0 plays twice as fast, 0 as fast as
    possible. Pacing is against the first message, so callback time does not accumulate drift.
    """
    if rate < 0:
        raise ValueError("rate must be >= 0")
    count = 0
    t0_log: int | None = None
    t0_wall = 0.0
    for item in LogReader(path).messages(topics, start_ns, end_ns):
        if rate > 0:
            if t0_log is None:
                t0_log, t0_wall = item.log_time_ns, clock()
            due = t0_wall + (item.log_time_ns - t0_log) * 1e-9 / rate
            delay = due - clock()
            if delay > 0:
                sleep(delay)
        callback(item)
        count += 1
    return count
