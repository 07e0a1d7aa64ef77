"""`trundle recover IN [OUT]`: salvage a truncated or .active log into a complete file."""

from __future__ import annotations

import argparse
from pathlib import Path

from trundle.logs.recover import recover
from trundle.tools.cli.damage import say_damage


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="damaged MCAP (e.g. run.mcap.active)")
    p.add_argument("output", nargs="?", help="output file (default: IN without .active, or IN.recovered.mcap)")
    p.set_defaults(func=run)


def default_output(src: Path) -> Path:
    if src.name.endswith(".mcap.active"):
        candidate = src.with_name(src.name[: -len(".active")])
        if not candidate.exists():
            return candidate
    stem = src.name.split(".mcap")[0]
    return src.with_name(f"{stem}.recovered.mcap")


def run(args: argparse.Namespace) -> int:
    src = Path(args.input)
    dst = Path(args.output) if args.output else default_output(src)
    result = recover(src, dst)
    say_damage(args, result.damage)
    note = f"; stopped by {result.stopped_by}" if result.stopped_by else ""
    corrupt = f"; skipped {result.corrupt_chunks} corrupt chunks" if result.corrupt_chunks else ""
    print(f"recovered {result.messages} messages into {result.output}{corrupt}{note}")
    return 0
