"""One log's work on a worker: fingerprint the input, skip it if its result is complete, else run
the job in a private folder and install the outputs in one rename.

``OUT/<name>/`` only ever holds a complete result: the job writes into ``OUT/.fleet/work/``, and
the folder replaces the old one once the report and the completion record ``fleet.json`` (input
hash, options key, row) are written. A job's exception fails its row (one-line error, full
traceback in ``OUT/.fleet/errors/<name>.txt``) and never escapes, so Ray retries only tasks whose
worker was lost.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import time
import traceback
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from trundle import __version__
from trundle.logs.errors import OutputError, TrundleError, UserError
from trundle.logs.metadata import read_metadata
from trundle.logs.outputs import write_json, write_text
from trundle.logs.reader import LogReader
from trundle.tools.fleet.inputs import identity, local_copy
from trundle.tools.fleet.jobs import REPORT, run_job
from trundle.tools.fleet.rows import flatten, one_line

MARKER = "fleet.json"
STATE = ".fleet"   # OUT/.fleet: work folders, error texts, the run lock


@dataclass(frozen=True)
class Task:
    """What a worker needs for one log: the job, the log (path or URL), its output folder name
    under ``output``, the job options and their key (:func:`trundle.tools.fleet.jobs.options_key`),
    whether to recompute a complete result, and the driver's trundle version."""

    job: str
    source: str
    name: str
    output: str
    options: dict[str, Any]
    key: str
    force: bool = False
    version: str = __version__

    @property
    def folder(self) -> Path:
        return Path(self.output) / self.name

    @property
    def error_file(self) -> Path:
        return Path(self.output) / STATE / "errors" / f"{self.name}.txt"


def read_marker(folder: Path) -> dict[str, Any] | None:
    """The completion record of a log's output folder (None if absent or unreadable)."""
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None


def sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def robot_name(metadata: dict[str, dict[str, str]]) -> str:
    """The robot a log came from: the robot's name in the log (record, daemon); for an imported
    dataset, which one (``imported carmen``: the host is only the machine that imported it); else
    the recording host ('' if none)."""
    described = read_metadata(metadata)
    if described.robot_name:
        return described.robot_name
    if described.command.startswith("import "):
        return "imported " + described.command.removeprefix("import ")
    return str(described.fields.get("host", ""))


def _log_columns(path: Path, source: str) -> dict[str, Any]:
    """The robot, first message time (UTC ISO 8601), duration (s) and damage (one line naming
    ``source``, None when intact) of the log at ``path`` (the local copy of ``source``)."""
    info = LogReader(path).info()
    start = (datetime.fromtimestamp(info.start_ns / 1e9, tz=UTC).isoformat(timespec="milliseconds")
             if info.start_ns is not None else None)
    return {"robot": robot_name(info.metadata), "log_start": start, "log_duration_s": info.duration_s,
            "log_damage": info.damage.line(source) if info.damage is not None else None}


def _install(work: Path, target: Path) -> None:
    """Put the folder ``work`` at ``target``, replacing what was there (two renames on one filesystem)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    old = work.with_name(work.name + ".old")
    if target.exists():
        target.rename(old)
    work.rename(target)
    shutil.rmtree(old, ignore_errors=True)


def process_log(task: Task) -> dict[str, Any]:
    """Run ``task`` and return its row (status ``ok``, ``skipped`` or ``failed``); see the module doc."""
    started, cpu_started = time.perf_counter(), time.process_time()
    row: dict[str, Any] = {"log": task.source, "name": task.name, "status": "failed", "error": ""}
    work = Path(task.output) / STATE / "work" / f"{task.name}.{uuid.uuid4().hex[:12]}"
    try:
        if task.version != __version__:
            raise UserError(f"this worker has trundle {__version__}, the driver {task.version}: "
                            "install the same version on every node")
        fingerprint = identity(task.source)
        done = read_marker(task.folder)
        if (not task.force and done and done.get("key") == task.key and done.get("identity") == fingerprint):
            return {**done["row"], "status": "skipped"}
        with local_copy(task.source) as path:
            digest = sha256(path)
            if not task.force and done and done.get("key") == task.key and done.get("sha256") == digest:
                write_json(task.folder / MARKER, {**done, "identity": fingerprint}, replace=True)
                return {**done["row"], "status": "skipped"}
            row.update(size_bytes=path.stat().st_size, sha256=digest, **_log_columns(path, task.source))
            report = run_job(task.job, path, work, task.options)
        row.update(seconds=time.perf_counter() - started, cpu_seconds=time.process_time() - cpu_started,
                   **flatten(report))
        ok = {**row, "status": "ok"}  # once its results are in place: a report that cannot be written fails it
        if not (work / REPORT).exists():
            write_json(work / REPORT, report)
        write_json(work / MARKER, {"key": task.key, "identity": fingerprint, "sha256": digest, "job": task.job,
                                   "options": task.options, "version": __version__, "row": ok})
        _install(work, task.folder)
        task.error_file.unlink(missing_ok=True)
        return ok
    except Exception as error:  # a bad log or a job's failure fails this row alone, never the fleet
        row.update(seconds=time.perf_counter() - started, cpu_seconds=time.process_time() - cpu_started,
                   error=one_line(str(error) if isinstance(error, TrundleError)
                                  else f"{type(error).__name__}: {error}"))
        with contextlib.suppress(OSError, OutputError):  # a full disk: the row holds the error all the same
            task.error_file.parent.mkdir(parents=True, exist_ok=True)
            write_text(task.error_file, f"{task.source}\n{traceback.format_exc()}", replace=True)
        return row
    finally:
        shutil.rmtree(work, ignore_errors=True)
