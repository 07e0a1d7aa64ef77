"""The `trundle` command line.

Each command lives in ``tools/cli/<name>.py`` (``-`` in the name as ``_``; ``import`` in
``import_data.py``) and defines ``register(parser)``, which adds the command's arguments and sets
``func`` to a callable taking the parsed arguments and returning the exit code. Only the module of
the command being run is imported: ``trundle --help`` and ``trundle --version`` import none, so
the command line starts at once. A user's mistake raises ``UserError`` (or an OSError about a
path) and ends as one line on stderr with exit code 2; an output the disk refused (read-only,
full: ``OutputError``) ends as one line with exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from typing import Any, NoReturn

from trundle import __version__
from trundle.logs.errors import OutputError, TrundleError

EXIT_USER_ERROR = 2
EXIT_OUTPUT_ERROR = 1  # an output the disk refused (read-only, full): not the user's mistake

# command -> one-line help; the order of `trundle --help`
COMMANDS = {
    "demo": "whole pipeline on emulated hardware in a simulated world -> log, map, report",
    "record": "record devices to an MCAP log",
    "daemon": "run the onboard service: supervised drivers, logging, SLAM, status",
    "status": "status of the running daemon: devices, rates, errors, logger, disk",
    "info": "summarise a log: duration, size, topics, types, counts, rates",
    "recover": "salvage a truncated or .active log",
    "replay": "the daemon on a log: play it at any rate into SLAM/markers, the live view and a new log",
    "export": "export one topic as CSV or NDJSON",
    "slam": "build a map and trajectory from a log (LaserScan + odometry)",
    "slam-eval": "relation error (Kuemmerle 2009), ATE and RPE of a SLAM trajectory",
    "inject-faults": "copy a log with realistic odometry faults (heading glitches, slip, scale, dropouts)",
    "localize": "localise a log on a saved map (unknown start, kidnap recovery)",
    "perceive": "run an image-feature pipeline over a log's images",
    "match": "match local features between two images (keypoints, matches, RANSAC model)",
    "import": "convert a public dataset (CARMEN, BreezySLAM, UTIAS MRCLAM) to an MCAP log",
    "emulate": "start a device emulator",
    "characterize": "sensor characteristics (range, resolution, precision, ...) from a log",
    "fleet": "run a one-log job over many logs on a Ray cluster -> results table and summary",
}
MODULES = {"import": "import_data"}


def module_name(command: str) -> str:
    """The module that implements ``command``."""
    return "trundle.tools.cli." + MODULES.get(command, command.replace("-", "_"))


MARKUP = re.compile(r"(?::[a-z]+:)?`+~?([^`]+?)`+")   # ``code``, `title`, :mod:`a.b`, :func:`~a.b`


def plain(text: str) -> str:
    """``text`` with its reST markup (the docstrings' ````--lrf````, ``:mod:`a.b```) as the plain words a
    terminal shows: ``--lrf``, ``a.b``."""
    return MARKUP.sub(r"\1", text)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every command's help: its description's lines as written (lists, examples), and no reST markup
    anywhere (descriptions come from module docstrings)."""

    def _format_text(self, text: str) -> str:
        return super()._format_text(plain(text))

    def _expand_help(self, action: argparse.Action) -> str:
        return plain(super()._expand_help(action))


class Parser(argparse.ArgumentParser):
    """argparse with a usage mistake said in one line (what, and where the help is), exit code 2, and
    help by :class:`HelpFormatter` (also for a command's own subcommands)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        # As Python 3.13's argparse: an argument starting with a minus and a digit ("-5:30", "-1e3")
        # is a value, not an unknown option ("--heading-glitch -5:30" said "expected one argument").
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USER_ERROR, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the command named in ``argv`` (if any) gets its arguments and module."""
    parser = Parser(prog="trundle", description="Onboard software of a wheeled mobile robot.")
    parser.add_argument("--version", action="version", version=f"trundle {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    wanted = next((arg for arg in (sys.argv[1:] if argv is None else argv) if not arg.startswith("-")), None)
    for command, help_text in COMMANDS.items():
        p = sub.add_parser(command, help=help_text)
        if command == wanted:
            importlib.import_module(module_name(command)).register(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command in ``argv`` (default: the process's arguments); returns the exit code."""
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as done:  # --help, --version, or a usage mistake (said in one line by Parser)
        return done.code if isinstance(done.code, int) else 0
    try:
        return int(args.func(args) or 0)
    except TrundleError as error:
        print(f"trundle {args.command}: {error}", file=sys.stderr)
        return EXIT_OUTPUT_ERROR if isinstance(error, OutputError) else EXIT_USER_ERROR
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
    """The process's entry point (console script, ``python -m trundle.tools.cli``): its allocator set to keep
    freed memory for reuse (:mod:`trundle.fusion.mapping.allocator`), then :func:`main`."""
    if len(sys.argv) > 1 and sys.argv[1] in COMMANDS:   # a command to run (not --help, not --version)
        from trundle.fusion.mapping.allocator import keep_freed_memory
        keep_freed_memory()
    sys.exit(main())
