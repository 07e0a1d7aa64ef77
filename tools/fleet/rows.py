"""One row per log of a fleet run: the bookkeeping columns and the job's figures, flattened.

A report is a nested dict; its figures become columns named by their path (``match_score.mean``),
so a figure a job adds to its report is a column with no change here. Lists become JSON text.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from trundle.logs.outputs import json_text

STATUSES = ("ok", "failed", "skipped", "cancelled")
COLUMNS = ("log", "name", "status", "error", "seconds", "cpu_seconds", "size_bytes", "sha256", "robot",
           "log_start", "log_duration_s", "log_damage", "node")
"""The columns every row has, in this order: the log as given, its output folder (relative to
OUT), the status, a one-line error, the wall and CPU seconds of the job on its worker, the
input's size (bytes) and SHA-256, the robot (the log's ``robot`` or ``host`` metadata), the log's
first message time (UTC, ISO 8601) and duration (s), what its damage skipped (the one line of
:meth:`trundle.logs.reader.LogDamage.line`; empty for an intact log), and the Ray node that ran it."""
DROPPED = {"log", "log_damage"}   # report keys that repeat a column (the log's path, its damage)


def one_line(text: str, limit: int = 300) -> str:
    """``text`` as one line of at most ``limit`` characters (whitespace runs become one space)."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[:limit - 3] + "..."


def _scalar(value: Any) -> Any:
    """A CSV/Parquet cell: numbers, text and booleans stay, non-finite floats and None become
    None, lists and other values become JSON text."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return json_text(value)


def flatten(report: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """The figures of ``report`` as one flat dict: nested keys joined with ``.``; a key that
    would clash with a bookkeeping column gets a ``report.`` prefix."""
    flat: dict[str, Any] = {}
    for key, value in report.items():
        name = f"{prefix}{key}"
        if not prefix and key in DROPPED:
            continue
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, f"{name}."))
        else:
            flat[f"report.{name}" if name in COLUMNS else name] = _scalar(value)
    return flat


def columns(rows: list[Mapping[str, Any]]) -> list[str]:
    """The bookkeeping columns, then every figure column in the order the rows first name it."""
    seen = dict.fromkeys(COLUMNS)
    for row in rows:
        seen.update(dict.fromkeys(row))
    return list(seen)
