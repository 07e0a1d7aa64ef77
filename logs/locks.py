"""Advisory file locks: whether a live process holds one, and who (the one reader of /proc/locks).

trundle marks what a process is using with a ``flock``: a serial port it opened (pyserial's
``exclusive``) and a log it is writing (the logger's ``NAME.mcap.active``). The kernel drops the
lock when its process ends, however it ends (also ``kill -9``), so a held lock means a live
writer for sure, where a file's age could only guess.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

PROC_LOCKS = Path("/proc/locks")


def lock_holder(path: str | os.PathLike[str]) -> int | None:
    """The pid holding a ``flock`` on ``path`` (as listed in /proc/locks), or None if none is held,
    the path is not a file (a ``socket://`` URL) or the kernel does not say."""
    try:
        st = os.stat(path)
        locks = PROC_LOCKS.read_text().splitlines()
    except (OSError, ValueError):
        return None
    inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in locks:
        fields = line.split()  # "1: FLOCK  ADVISORY  WRITE 1234 00:19:3 0 EOF"; waiters have "->" after "1:"
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[5] == inode and fields[4].isdigit():
            return int(fields[4])
    return None


def holder_name(pid: int | None) -> str:
    """``pid N (command)`` for a lock's holder as far as /proc tells, else ``another program``."""
    if pid is None:
        return "another program"
    try:
        return f"pid {pid} ({Path(f'/proc/{pid}/comm').read_text().strip()})"
    except OSError:
        return f"pid {pid}"


def is_locked(path: str | os.PathLike[str]) -> bool:
    """True while any open file (this process's too) holds a ``flock`` on ``path``: a live writer;
    False when the file is free or cannot be opened."""
    try:
        with open(path, "rb") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


def writer_of(path: str | os.PathLike[str]) -> str | None:
    """Who is still writing ``path`` (``pid N (command)``, see :func:`holder_name`), or None when no
    live process holds its lock."""
    return holder_name(lock_holder(path)) if is_locked(path) else None
