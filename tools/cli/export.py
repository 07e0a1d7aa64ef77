"""`trundle export FILE --topic T --format csv|ndjson`: a topic's messages as rows."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import sys
from collections.abc import Iterable
from typing import TextIO

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text, writing_file
from trundle.logs.paths import new_file
from trundle.logs.reader import LogMessage, LogReader
from trundle.tools.cli.damage import say_damage


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="MCAP log (trundle info FILE lists its topics)")
    p.add_argument("--topic", required=True, help="the topic to export, e.g. /odom")
    p.add_argument("--format", choices=("csv", "ndjson"), default="csv",
                   help="csv: one row per message, nested fields as columns; ndjson: one JSON object per line "
                        "(default csv)")
    p.add_argument("-o", "--output", help="output file (default: stdout; must not exist)")
    p.set_defaults(func=run)


def _plain(value: object) -> object:
    """JSON-ready value: arrays to lists, NaN and infinities to null (strict JSON has neither), bytes
    to hex, nested messages to dicts."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, m.Message):
        return _plain_message(value)
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def _plain_message(msg: m.Message) -> dict[str, object]:
    """A message as a JSON-ready dict of its fields."""
    return {f.name: _plain(getattr(msg, f.name)) for f in dataclasses.fields(msg)}


def flatten(value: object, prefix: str = "") -> dict[str, object]:
    """One CSV row: every leaf of ``value`` (a message, nested messages, arrays, lists) in its own
    column named by its path, ``status.0.values.1.key`` (as ``ros2 bag`` tools and Foxglove's CSV
    export name them); bytes as hex, non-finite floats as ``nan``/``inf`` text. A diagnostic status's
    ``(key, value)`` pairs are ``values.N.key`` and ``values.N.value``, as ROS's KeyValue names them."""
    if isinstance(value, m.Message):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
        if "values" in value and isinstance(value["values"], tuple):
            value["values"] = [{"key": k, "value": v} for k, v in value["values"]]
    if isinstance(value, np.ndarray):
        value = value.reshape(-1).tolist()
    if isinstance(value, dict):
        items = list(value.items())
    elif isinstance(value, (tuple, list)):
        items = list(enumerate(value))
    else:
        return {prefix: value.hex() if isinstance(value, bytes) else value}
    row: dict[str, object] = {}
    for key, item in items:
        row.update(flatten(item, f"{prefix}.{key}" if prefix else str(key)))
    return row


def write_rows(items: Iterable[LogMessage], out: TextIO, form: str, columns: list[str]) -> int:
    """Each message of ``items`` as one CSV row (``columns``: every flattened field of the topic) or
    NDJSON line on ``out``; returns how many."""
    count = 0
    writer = None
    for item in items:
        if form == "ndjson":
            record = {"topic": item.topic, "log_time_ns": item.log_time_ns, **_plain_message(item.msg)}
            out.write(json_text(record) + "\n")
        else:
            if writer is None:
                writer = csv.DictWriter(out, fieldnames=["log_time_ns", *columns])
                writer.writeheader()
            writer.writerow({"log_time_ns": item.log_time_ns, **flatten(item.msg)})
        count += 1
    return count


def run(args: argparse.Namespace) -> int:
    """Write the topic's rows to ``-o`` (all of them or, on any failure, nothing) or to stdout."""
    reader = LogReader(args.file)
    info = reader.info()
    if args.topic not in info.topics:
        raise UserError(f"{args.file} has no topic {args.topic} (topics: {info.topic_list()})")
    if args.output:
        new_file(args.output, "-o")
    items = reader.messages([args.topic])
    empty = UserError(f"no messages on topic {args.topic} that trundle can decode")
    # CSV: messages whose arrays differ in length have different columns; the header is all of them,
    # in the order first met, from a first pass (a cell a message lacks stays empty)
    columns = [] if args.format == "ndjson" else list(
        {name: None for item in reader.messages([args.topic]) for name in flatten(item.msg)})
    if args.output:
        with writing_file(args.output, "-o") as tmp, open(tmp, "w", newline="") as out:
            count = write_rows(items, out, args.format, columns)
            if count == 0:
                raise empty  # nothing is kept under -o
    else:
        count = write_rows(items, sys.stdout, args.format, columns)
    say_damage(args, reader.last_damage)
    if count == 0:
        raise empty
    return 0
