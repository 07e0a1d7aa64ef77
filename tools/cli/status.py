"""`trundle status`: ask the running daemon how its devices, logger and disk are doing."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from trundle.tools.daemon.config import default_socket_path, load_config
from trundle.tools.daemon.status import format_status, query_status


def register(p: argparse.ArgumentParser) -> None:
    """The command's options on its subparser ``p``."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--socket", type=Path, help=f"the daemon's status socket (default {default_socket_path()}, "
                                                   "else /run/trundle/status.sock)")
    where.add_argument("--config", type=Path, help="take the socket path from the daemon's robot TOML")
    p.add_argument("--json", action="store_true", help="print the daemon's JSON answer unchanged")
    p.set_defaults(func=run)


SYSTEM_SOCKET = Path("/run/trundle/status.sock")  # the systemd unit's RuntimeDirectory


def run(args: argparse.Namespace) -> int:
    """Ask the daemon at the chosen socket and print its answer (text, or ``--json`` as sent)."""
    if args.socket or args.config:
        path = args.socket or load_config(args.config).status.socket
    else:  # this user's daemon, else the system service's
        path = next((p for p in (default_socket_path(), SYSTEM_SOCKET) if p.exists()), default_socket_path())
    status = query_status(path)
    print(json.dumps(status, indent=2) if args.json else format_status(status))
    return 0
