"""Play a log's messages into callbacks in log-time order, at real time or any rate."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable

from trundle.logs.reader import LogMessage, LogReader, RawMessage


def play(path: str | os.PathLike[str], callback: Callable[[RawMessage], object], rate: float = 1.0,
         topics: Iterable[str] | None = None, start_ns: int | None = None, end_ns: int | None = None,
         loop: bool = False, on_pass: Callable[[int], object] | None = None,
         sleep: Callable[[float], None] = time.sleep, clock: Callable[[], float] = time.monotonic) -> int:
    """Deliver each stored message of ``topics`` (None: all) with ``start_ns <= log time < end_ns`` to
    ``callback`` as it is stored (:class:`RawMessage`); returns how many were delivered.

    ``rate`` scales time: 1.0 keeps the log's spacing, 2.0 plays twice as fast, 0 as fast as
    possible. Pacing is against the first message of each pass, so callback time does not
    accumulate drift. ``loop`` plays the window again and again (until the callback raises, e.g.
    KeyboardInterrupt); ``on_pass(n)`` is called before pass n (0, 1, ...).
    """
    if rate < 0:
        raise ValueError("rate must be >= 0")
    count = 0
    reader = LogReader(path)
    for n in range(1 << 62 if loop else 1):
        if on_pass is not None:
            on_pass(n)
        t0_log: int | None = None
        t0_wall = 0.0
        delivered = count
        for item in reader.raw_messages(topics, start_ns, end_ns):
            if rate > 0:
                if t0_log is None:
                    t0_log, t0_wall = item.log_time_ns, clock()
                delay = t0_wall + (item.log_time_ns - t0_log) * 1e-9 / rate - clock()
                if delay > 0:
                    sleep(delay)
            callback(item)
            count += 1
        if count == delivered:  # an empty window would loop without end
            break
    return count


def replay(path: str | os.PathLike[str], callback: Callable[[LogMessage], object], rate: float = 1.0,
           topics: Iterable[str] | None = None, start_ns: int | None = None, end_ns: int | None = None,
           sleep: Callable[[float], None] = time.sleep, clock: Callable[[], float] = time.monotonic) -> int:
    """:func:`play` with each message decoded (types trundle does not map are skipped, not counted)."""
    from trundle.logs import ros2  # numpy and the rosbags typestore: only to decode

    def decode(raw: RawMessage) -> bool:
        if not ros2.is_supported(raw.ros_type):
            return False
        callback(LogMessage(raw.topic, raw.log_time_ns, ros2.decode(raw.ros_type, raw.data)))
        return True

    delivered = 0

    def counted(raw: RawMessage) -> None:
        nonlocal delivered
        delivered += decode(raw)

    play(path, counted, rate, topics, start_ns, end_ns, sleep=sleep, clock=clock)
    return delivered
