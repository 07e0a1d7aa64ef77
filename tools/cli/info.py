"""`trundle info FILE`: what a log holds, shaped like `ros2 bag info`."""

from __future__ import annotations

import argparse
from datetime import UTC, datetime

from trundle.logs.locks import writer_of
from trundle.logs.outputs import json_text
from trundle.logs.reader import LogReader
from trundle.tools.cli.damage import say_damage
from trundle.tools.jobs.info import as_dict


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="MCAP log (.mcap or .mcap.active)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def _when(ns: int | None) -> str:
    if ns is None:
        return "-"
    t = datetime.fromtimestamp(ns / 1e9, tz=UTC)
    return f"{t:%b %d %Y %H:%M:%S}.{ns % 1_000_000_000:09d} ({ns / 1e9:.9f})"


def _size(n: int) -> str:
    if n < 1024:
        return f"{n} B"
    size = n / 1024
    for unit in ("KiB", "MiB"):
        if size < 1024:
            return f"{size:.1f} {unit}"
        size /= 1024
    return f"{size:.1f} GiB"


def run(args: argparse.Namespace) -> int:
    info = LogReader(args.file).info()
    live = writer_of(info.path)  # a file still being written is not damaged: recover has nothing to do
    if live is None:
        say_damage(args, info.damage)
    ok = 0 if info.message_count or info.complete or live else 1
    if args.json:
        print(json_text({**as_dict(info), "being_written_by": live}, indent=2))
        return ok
    if live is not None:
        state = f"being written by {live} (what it has flushed so far)"
    elif info.complete:
        state = "complete"
    else:
        state = "INCOMPLETE (read what was intact, see stderr; `trundle recover` fixes it)"
    lines = [
        f"Files:             {info.path.name}",
        f"Bag size:          {_size(info.size_bytes)}",
        "Storage id:        mcap",
        f"Profile:           {info.profile or '-'} ({info.library or 'unknown writer'})",
        f"Compression:       {', '.join(sorted(info.compression)) or 'none'} in {info.chunks} chunks",
        f"State:             {state}",
        f"Duration:          {info.duration_s:.3f}s",
        f"Start:             {_when(info.start_ns)}",
        f"End:               {_when(info.end_ns)}",
        f"Messages:          {info.message_count}",
    ]
    width = max((len(t) for t in info.topics), default=0)
    type_width = max((len(t.ros_type) for t in info.topics.values()), default=0)
    for i, (name, t) in enumerate(sorted(info.topics.items())):
        head = "Topic information: " if i == 0 else "                   "
        latched = " | latched" if t.latched else ""
        # a latched topic's few messages (each split repeats them) have no rate: its "rate" was their spacing
        rate = f"{'-':>8}   " if t.latched else f"{t.rate_hz:8.2f} Hz"
        lines.append(f"{head}Topic: {name:<{width}} | Type: {t.ros_type:<{type_width}} | Count: {t.count:>7} | "
                     f"Rate: {rate} | Serialization Format: {t.encoding}{latched}")
    print("\n".join(lines))
    return ok
