"""The disk guard: keeps the log folder's file system above a free-space floor.

Below ``[disk] min_free_mb`` it deletes the oldest closed logs (``action = "delete_oldest"``) and,
when that is not enough (or ``action = "stop"``), stops recording; recording resumes once the
free space is ``resume_margin`` above the floor. The guard decides; the daemon's logger acts,
through the ``stop_recording`` and ``resume_recording`` callbacks.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trundle.logs import messages as m

if TYPE_CHECKING:
    from trundle.tools.config.robot import DiskConfig, LoggerConfig


class DiskGuard:
    """Checks the free space of ``logger.folder`` on each ``check``. ``current_log`` names the file
    being written (never deleted); ``stop_recording(reason)`` and ``resume_recording()`` are called
    once per transition. ``status`` is the ``disk`` entry of the status answer."""

    def __init__(self, disk: DiskConfig, logger: LoggerConfig, *, current_log: Callable[[], Path | None],
                 stop_recording: Callable[[str], None], resume_recording: Callable[[], None]) -> None:
        self.config, self.folder, self.record = disk, logger.folder, logger.record
        self._current_log, self._stop_recording, self._resume_recording = current_log, stop_recording, resume_recording
        self.stopped = ""  # why recording is stopped for want of space; "" while it may record
        self.deleted: list[str] = []
        self.status: dict[str, Any] = {}

    def check(self) -> None:
        """Below ``min_free_mb``: delete the oldest closed logs (or stop recording); resume above it."""
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
            for path in self._deletable_logs():
                try:
                    path.unlink()
                except OSError:
                    continue
                self.deleted.append(path.name)
                print(f"trundle daemon: disk low, deleted {path}", file=sys.stderr, flush=True)
                usage = shutil.disk_usage(folder)
                free = usage.free
                if free >= floor:
                    break
        if free < floor and not self.stopped:
            self.stopped = f"disk low: {free / 1e6:.0f} MB free in {folder}, below {cfg.min_free_mb:.0f} MB"
            self._stop_recording(self.stopped)
            print(f"trundle daemon: recording stopped: {self.stopped}", file=sys.stderr, flush=True)
        elif self.stopped and free >= floor * (1.0 + cfg.resume_margin) and self.record:
            print("trundle daemon: disk space back, recording again", file=sys.stderr, flush=True)
            self.stopped = ""
            self._resume_recording()
        self.status = {"folder": str(folder), "free_bytes": free, "total_bytes": usage.total,
                       "min_free_bytes": int(floor), "action": cfg.action, "low": free < floor,
                       "deleted": self.deleted[-10:], "deleted_count": len(self.deleted)}

    def _deletable_logs(self) -> list[Path]:
        """Closed ``*.mcap`` files in the log folder, oldest first (never the file being written)."""
        current, folder = self._current_log(), self.folder
        assert folder is not None  # check_daemon_config
        logs = [p for p in folder.glob("*.mcap") if p.is_file() and p != current]
        return sorted(logs, key=lambda p: (p.stat().st_mtime, p.name))

    def diagnostics(self, robot: str) -> m.DiagnosticStatus:
        """The ``robot/disk`` entry of ``/diagnostics``: ERROR while low or unreadable."""
        disk = self.status
        level = m.ERROR if disk.get("low") or "error" in disk else m.OK
        return m.DiagnosticStatus(level, f"{robot}/disk",
                                  disk.get("error", f"{disk.get('free_bytes', 0) / 1e9:.2f} GB free"), "",
                                  tuple((k, str(v)) for k, v in disk.items() if k != "deleted"))
