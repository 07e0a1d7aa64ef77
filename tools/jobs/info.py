"""The info job: what a log holds (duration, size, topics, types, counts, rates) as one JSON-able dict.

The same figures ``trundle info --json`` prints, from one pass over the file (exact for damaged
files too, see :class:`trundle.logs.reader.LogReader`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from trundle.logs.reader import LogInfo, LogReader, damage_dict


def as_dict(info: LogInfo) -> dict[str, Any]:
    """``info`` as a JSON-able dict: sizes in bytes, times in ns, duration in s, rates in Hz; ``log_damage``
    what the read skipped (None: intact)."""
    return {
        "file": str(info.path), "size_bytes": info.size_bytes, "profile": info.profile,
        "library": info.library, "compression": sorted(info.compression), "duration_s": info.duration_s,
        "start_ns": info.start_ns, "end_ns": info.end_ns, "messages": info.message_count,
        "chunks": info.chunks, "corrupt_chunks": info.corrupt_chunks, "complete": info.complete,
        "error": info.error, "log_damage": damage_dict(info.damage), "metadata": info.metadata,
        "topics": {name: {"type": t.ros_type, "encoding": t.encoding, "count": t.count, "rate_hz": t.rate_hz,
                          "latched": t.latched}
                   for name, t in sorted(info.topics.items())},
    }


def info_log(log: Path) -> dict[str, Any]:
    """The summary of ``log`` (see :func:`as_dict`); a missing or non-MCAP file is a UserError."""
    return as_dict(LogReader(log).info())
