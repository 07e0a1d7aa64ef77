"""The one line every command that reads a log says on stderr when the log is damaged.

What was skipped is counted and worded by :class:`trundle.logs.reader.LogDamage`; a command passes
the damage of the pass it read (or its report's ``log_damage``) here, and an intact log (None)
says nothing.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from typing import Any

from trundle.logs.reader import LogDamage


def say_damage(args: argparse.Namespace, damage: LogDamage | Mapping[str, Any] | str | None) -> None:
    """Print ``trundle COMMAND: LOG is damaged: skipped ...`` on stderr for ``damage`` (a LogDamage, a
    report's ``log_damage`` dict or a fleet row's ``log_damage`` line); nothing for None."""
    if not damage:
        return
    if isinstance(damage, LogDamage):
        line = damage.line()
    elif isinstance(damage, str):
        line = damage
    else:
        line = damage["said"]
    print(f"trundle {args.command}: {line}", file=sys.stderr)
