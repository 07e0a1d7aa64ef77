"""A pseudo-terminal that stands in for a USB serial device, behind a stable symlink.

The emulator holds the master side; a driver opens the symlink (as it would open
``/dev/serial/by-id/...``) and gets the slave. ``unplug`` closes the pty and removes the
link, as pulling the cable does; ``replug`` makes a new pty behind the same link.
"""

from __future__ import annotations

import os
import select
import termios
import tty
from pathlib import Path


class PtyLink:
    """One emulated serial device on a pty whose slave is reachable at ``link_path``."""

    def __init__(self, link_path: str | os.PathLike[str]) -> None:
        self.link_path = Path(link_path)
        self._master = -1
        self._slave = -1
        self.replug()

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def fileno(self) -> int:
        return self._master

    def replug(self) -> None:
        """(Re)create the pty and point the symlink at its slave."""
        self._close_fds()
        master, slave = os.openpty()
        tty.setraw(slave)
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        tmp = self.link_path.with_name(self.link_path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link_path)

    def unplug(self) -> None:
        """Remove the link and close the pty: the driver's reads fail as on a pulled cable."""
        self.link_path.unlink(missing_ok=True)
        self._close_fds()

    def read(self, max_bytes: int = 65536, timeout_s: float = 0.0) -> bytes:
        """Bytes the driver wrote, waiting up to ``timeout_s``; ``b""`` if none or unplugged."""
        if self._master < 0:
            return b""
        ready, _, _ = select.select([self._master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self._master, max_bytes)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:  # EIO: no process has the slave open
            return b""

    def write(self, data: bytes) -> int:
        """Send bytes to the driver; returns how many the pty took (0 when unplugged or full)."""
        if self._master < 0:
            return 0
        total = 0
        view = memoryview(data)
        while total < len(data):
            try:
                total += os.write(self._master, view[total:])
            except BlockingIOError:
                if not select.select([], [self._master], [], 1.0)[1]:
                    break
            except OSError:
                break
        return total

    def close(self) -> None:
        self.unplug()

    def __enter__(self) -> PtyLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1
