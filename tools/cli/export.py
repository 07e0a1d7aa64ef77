"""`trundle export FILE --topic T --format csv|ndjson`: a topic's messages as rows."""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import json
import sys

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.paths import new_file
from trundle.logs.reader import LogReader


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="MCAP log (trundle info FILE lists its topics)")
    p.add_argument("--topic", required=True, help="the topic to export, e.g. /odom")
    p.add_argument("--format", choices=("csv", "ndjson"), default="csv",
                   help="csv: one row per message, nested fields as columns; ndjson: one JSON object per line "
                        "(default csv)")
    p.add_argument("-o", "--output", help="output file (default: stdout; must not exist)")
    p.set_defaults(func=run)


def _plain(value: object) -> object:
    """JSON-ready value: arrays to lists (NaN/inf as strings), nested messages to dicts."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            return [v if np.isfinite(v) else str(v) for v in value.tolist()]
        return value.tolist()
    if isinstance(value, bytes):
        return value.hex()
    if isinstance(value, float) and not np.isfinite(value):
        return str(value)
    if isinstance(value, m.Message):
        return _plain_message(value)
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def _plain_message(msg: m.Message) -> dict[str, object]:
    """A message as a JSON-ready dict of its fields."""
    return {f.name: _plain(getattr(msg, f.name)) for f in dataclasses.fields(msg)}


def flatten(msg: m.Message) -> dict[str, object]:
    """One row: scalars as they are, arrays expanded to ``name.i`` columns (CSV)."""
    row: dict[str, object] = {}
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        if isinstance(value, np.ndarray):
            for i, v in enumerate(value.reshape(-1).tolist()):
                row[f"{f.name}.{i}"] = v
        elif isinstance(value, tuple) and all(isinstance(v, str) for v in value):
            for i, v in enumerate(value):
                row[f"{f.name}.{i}"] = v
        else:
            row[f.name] = _plain(value) if not isinstance(value, (int, float, str, bool)) else value
    return row


def run(args: argparse.Namespace) -> int:
    reader = LogReader(args.file)
    if args.output:
        new_file(args.output, "-o")
    items = reader.messages([args.topic])
    count = 0
    with open(args.output, "w", newline="") if args.output else contextlib.nullcontext(sys.stdout) as out:
        writer = None
        for item in items:
            if args.format == "ndjson":
                record = {"topic": item.topic, "log_time_ns": item.log_time_ns, **_plain_message(item.msg)}
                out.write(json.dumps(record) + "\n")
            else:
                row = {"log_time_ns": item.log_time_ns, **flatten(item.msg)}
                if writer is None:
                    writer = csv.DictWriter(out, fieldnames=list(row), extrasaction="ignore")
                    writer.writeheader()
                writer.writerow(row)
            count += 1
    if count == 0:
        raise UserError(f"no messages on topic {args.topic} that trundle can decode")
    return 0
