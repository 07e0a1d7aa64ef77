"""systemd's notify protocol (``Type=notify``): READY=1, STATUS=, WATCHDOG=1, STOPPING=1.

No libsystemd: one datagram to ``$NOTIFY_SOCKET`` per state, and the watchdog period read from
``$WATCHDOG_USEC``, so the daemon runs the same with or without systemd.
"""

from __future__ import annotations

import os
import socket


def sd_notify(state: str) -> bool:
    """Send ``state`` (e.g. ``READY=1``) to systemd's notify socket; False when not under systemd."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.send(state.encode(), socket.MSG_DONTWAIT)  # never block the main loop on a slow reader
    except OSError:
        return False
    return True


def watchdog_period_s() -> float | None:
    """How often to send WATCHDOG=1 (s): half of systemd's ``WatchdogSec`` (from ``WATCHDOG_USEC``)
    when it is meant for this process, else None."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return max(int(usec) / 2e6, 0.01)
    except ValueError:
        return None
