"""The disk guard: keeps the log folder's file system above a free-space floor.

Below ``[disk] min_free_mb`` it deletes the oldest closed logs this robot's daemon wrote
(``action = "delete_oldest"``) and, when that is not enough (or ``action = "stop"``), stops
recording; recording resumes once the free space is ``resume_margin`` above the floor. The guard
decides; the daemon's logger acts, through the ``stop_recording`` and ``resume_recording`` callbacks.

A log is the daemon's own only when the file says so (header and summary, no message read):
written by trundle's logger, ``command = "daemon"`` and this robot's name in its metadata. Any
other file in the folder (put there by hand, another robot's, damaged, not MCAP) is never deleted.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trundle.logs import messages as m
from trundle.logs.errors import DataError
from trundle.logs.reader import log_origin
from trundle.logs.writer import LIBRARY_PREFIX

if TYPE_CHECKING:
    from trundle.tools.config.robot import DiskConfig, LoggerConfig

DAEMON_COMMAND = "daemon"  # the ``command`` in the metadata of every log the daemon writes


def written_by_daemon(path: Path, robot: str) -> bool:
    """True when ``path`` is a closed log the daemon of ``robot`` wrote (module doc); False for any
    other file, one that cannot be read included."""
    try:
        library, metadata = log_origin(path)
    except DataError:
        return False
    return library.startswith(LIBRARY_PREFIX) and metadata.command == DAEMON_COMMAND and metadata.robot_name == robot


def sort_logs(folder: Path, robot: str, skip: Path | None = None) -> tuple[list[Path], list[Path]]:
    """The closed ``*.mcap`` files in ``folder`` but ``skip``: those the daemon of ``robot`` wrote,
    oldest first, and every other one (by name)."""
    own: list[Path] = []
    others: list[Path] = []
    for path in sorted(folder.glob("*.mcap")):
        if path.is_file() and path != skip:
            (own if written_by_daemon(path, robot) else others).append(path)
    return sorted(own, key=lambda p: (p.stat().st_mtime, p.name)), others


def _files(n: int, what: str) -> str:
    """``n`` files, "what" made plural unless one."""
    return f"{n} {what}" + ("" if n == 1 else "s")


def other_logs_notice(folder: Path, robot: str) -> str:
    """One line when ``folder`` holds ``.mcap`` files the daemon of ``robot`` did not write (the guard
    keeps them: a notice for ``daemon --check``, not an error); "" when it holds none."""
    if not folder.is_dir():
        return ""
    _, others = sort_logs(folder, robot)
    if not others:
        return ""
    names = ", ".join(p.name for p in others[:5]) + (", ..." if len(others) > 5 else "")
    return (f"note: {folder} holds {_files(len(others), '.mcap file')} the daemon of robot {robot!r} did not "
            f"write ({names}): the disk guard never deletes them")


class DiskGuard:
    """Checks the free space of ``logger.folder`` on each ``check``; deletes only the logs the daemon
    of ``robot`` wrote. ``current_log`` names the file being written (never deleted);
    ``stop_recording(reason)`` and ``resume_recording()`` are called once per transition; ``status``
    is the ``disk`` entry of the status answer."""

    def __init__(self, disk: DiskConfig, logger: LoggerConfig, robot: str, *, current_log: Callable[[], Path | None],
                 stop_recording: Callable[[str], None], resume_recording: Callable[[], None]) -> None:
        self.config, self.folder, self.record, self.robot = disk, logger.folder, logger.record, robot
        self._current_log, self._stop_recording, self._resume_recording = current_log, stop_recording, resume_recording
        self.stopped = ""  # why recording is stopped for want of space; "" while it may record
        self.deleted: list[str] = []
        self.status: dict[str, Any] = {}

    def check(self) -> None:
        """Below ``min_free_mb``: delete this robot's oldest closed logs, saying so in one line (or stop
        recording); resume above it."""
        cfg, folder = self.config, self.folder
        assert folder is not None  # check_daemon_config
        floor = cfg.min_free_mb * 1e6
        try:
            usage = shutil.disk_usage(folder)
        except OSError as error:
            self.status = {"folder": str(folder), "error": error.strerror or str(error)}
            return
        free = usage.free
        if free < floor and cfg.action == "delete_oldest":
            own, others = sort_logs(folder, self.robot, self._current_log())
            deleted: list[str] = []
            for path in own:
                try:
                    path.unlink()
                except OSError:
                    continue
                deleted.append(path.name)
                usage = shutil.disk_usage(folder)
                free = usage.free
                if free >= floor:
                    break
            self.deleted += deleted
            if deleted or (others and not self.stopped):  # the files kept: said once while stopped
                print(f"trundle daemon: disk low: deleted {len(deleted)} of this robot's logs"
                      f"{' (' + ', '.join(deleted) + ')' if deleted else ''} in {folder}; "
                      f"{_files(len(others), 'other .mcap file')} kept", file=sys.stderr, flush=True)
        # the status first: whoever sees recording stop or resume (the status socket) sees why
        self.status = {"folder": str(folder), "free_bytes": free, "total_bytes": usage.total,
                       "min_free_bytes": int(floor), "action": cfg.action, "low": free < floor,
                       "deleted": self.deleted[-10:], "deleted_count": len(self.deleted)}
        if free < floor and not self.stopped:
            self.stopped = f"disk low: {free / 1e6:.0f} MB free in {folder}, below {cfg.min_free_mb:.0f} MB"
            self._stop_recording(self.stopped)
            print(f"trundle daemon: recording stopped: {self.stopped}", file=sys.stderr, flush=True)
        elif self.stopped and free >= floor * (1.0 + cfg.resume_margin) and self.record:
            print("trundle daemon: disk space back, recording again", file=sys.stderr, flush=True)
            self.stopped = ""
            self._resume_recording()

    def diagnostics(self, robot: str) -> m.DiagnosticStatus:
        """The ``robot/disk`` entry of ``/diagnostics``: ERROR while low or unreadable."""
        disk = self.status
        level = m.ERROR if disk.get("low") or "error" in disk else m.OK
        return m.DiagnosticStatus(level, f"{robot}/disk",
                                  disk.get("error", f"{disk.get('free_bytes', 0) / 1e9:.2f} GB free"), "",
                                  tuple((k, str(v)) for k, v in disk.items() if k != "deleted"))
