"""The `trundle` command line.

Each sub-command lives in ``tools/commands/<name>.py`` and defines ``register(subparsers)``,
which adds its parser and sets ``func`` to a callable taking the parsed arguments and returning
the exit code. A user's mistake raises ``UserError`` (or an OSError about a path) and ends as one
line on stderr with a non-zero exit code.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from trundle.logs.errors import UserError
from trundle.tools import commands

EXIT_USER_ERROR = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trundle", description="Onboard software of a wheeled mobile robot.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"trundle.tools.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as error:
        print(f"trundle {args.command}: {error}", file=sys.stderr)
        return EXIT_USER_ERROR
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as error:
        where = f": {error.filename}" if error.filename else ""
        print(f"trundle {args.command}: {error.strerror or error}{where}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"trundle {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


def entry() -> None:
    """Console-script entry point."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
