"""`trundle recover IN [OUT]`: salvage a truncated or .active log into a complete file."""

from __future__ import annotations

import argparse
from pathlib import Path

from trundle.logs.recover import default_output, recover
from trundle.tools.cli.damage import say_damage


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="damaged MCAP (e.g. run.mcap.active, trundle's crash file: removed once recovered)")
    p.add_argument("output", nargs="?", help="output file (default: IN without .active, or IN.recovered.mcap)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    src = Path(args.input)
    dst = Path(args.output) if args.output else default_output(src)
    result = recover(src, dst)
    say_damage(args, result.damage)
    print(result.line())
    return 0
