"""A pseudo-terminal that stands in for a USB serial device, behind a stable symlink.

The emulator holds the master side; a driver opens the symlink (as it would open
``/dev/serial/by-id/...``) and gets the slave. ``unplug`` closes the pty and removes the
link, as pulling the cable does; ``replug`` makes a new pty behind the same link.

The link never replaces anything but a link of its own kind: a path that exists (a file, a
real device node such as ``/dev/ttyACM0``, a folder, someone's link) is refused, except a stale
link left by a killed emulator (pointing at a pty slave that no longer exists). Only the
emulator's own link is ever removed.
"""

from __future__ import annotations

import contextlib
import os
import select
import termios
import tty
from pathlib import Path

from trundle.logs.errors import UserError

PTY_SLAVES = "/dev/pts/"


def _ours(path: Path, target: str) -> bool:
    """Whether ``path`` is a link to ``target`` (our pty) or a stale link to a pty slave that is gone."""
    try:
        pointed = os.readlink(path)
    except OSError:
        return False
    return pointed == target or (pointed.startswith(PTY_SLAVES) and not os.path.exists(pointed))


def check_link_path(path: Path, own_target: str = "") -> None:
    """Refuse a link path that exists and is not ours (see the module doc): a UserError naming it."""
    if not (path.exists() or path.is_symlink()) or _ours(path, own_target):
        return
    if path.is_symlink():
        raise UserError(f"{path} is a link to {os.readlink(path)}, which is in use (another emulator?); "
                        "remove the link if it is a leftover")
    kind = "a folder" if path.is_dir() else "a device node" if path.is_char_device() or path.is_block_device() \
        else "a file"
    raise UserError(f"{path} exists and is {kind}: the emulator's link replaces nothing; choose a new path")


class PtyLink:
    """One emulated serial device on a pty whose slave is reachable at ``link_path``."""

    def __init__(self, link_path: str | os.PathLike[str]) -> None:
        self.link_path = Path(link_path)
        self._master = -1
        self._slave = -1
        self._target = ""
        self.replug()

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def fileno(self) -> int:
        return self._master

    def replug(self) -> None:
        """(Re)create the pty and point the symlink at its slave."""
        self._close_fds()
        check_link_path(self.link_path, self._target)
        master, slave = os.openpty()
        tty.setraw(slave)
        attrs = termios.tcgetattr(slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        target = os.ttyname(slave)
        tmp = self.link_path.with_name(f".{self.link_path.name}.{os.getpid()}.tmp")  # this process's own name
        tmp.unlink(missing_ok=True)
        os.symlink(target, tmp)
        os.replace(tmp, self.link_path)
        self._target = target

    def unplug(self) -> None:
        """Remove the link and close the pty: the driver's reads fail as on a pulled cable."""
        if self._target and _ours(self.link_path, self._target):
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
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1
