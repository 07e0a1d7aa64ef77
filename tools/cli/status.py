"""`trundle status`: ask the running daemon how its devices, logger and disk are doing.

Without ``--socket`` or ``--config`` it asks the daemon at the first status socket that exists
of: this user's (``$RUNTIME_DIRECTORY``, ``$XDG_RUNTIME_DIR/trundle``, ``/tmp/trundle-<uid>``),
the system service's (``/run/trundle/status.sock``, where the example config and the systemd
unit put it) and the one named in the system config ``/etc/trundle/robot.toml``.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text
from trundle.tools.config.robot import default_socket_path, load_config
from trundle.tools.daemon.status import format_status, query_status

SYSTEM_SOCKET = Path("/run/trundle/status.sock")  # the systemd unit's RuntimeDirectory
SYSTEM_CONFIG = Path("/etc/trundle/robot.toml")  # the systemd unit's config


def register(p: argparse.ArgumentParser) -> None:
    """The command's options on its subparser ``p``."""
    p.description = __doc__
    where = p.add_mutually_exclusive_group()
    where.add_argument("--socket", type=Path, help="the daemon's status socket")
    where.add_argument("--config", type=Path, help="take the socket path from the daemon's robot TOML")
    p.add_argument("--json", action="store_true", help="print the daemon's JSON answer unchanged")
    p.set_defaults(func=run)


def candidate_sockets() -> list[Path]:
    """Where a daemon's status socket may be, in the order asked (see the module doc)."""
    candidates = [default_socket_path(), SYSTEM_SOCKET]
    if SYSTEM_CONFIG.is_file():
        with contextlib.suppress(UserError):  # a broken system config names no socket; the daemon would refuse it too
            candidates.append(load_config(SYSTEM_CONFIG).status.socket)
    return list(dict.fromkeys(candidates))


def run(args: argparse.Namespace) -> int:
    """Ask the daemon at the chosen socket and print its answer (text, or ``--json`` as sent)."""
    if args.socket or args.config:
        path = args.socket or load_config(args.config).status.socket
    else:
        candidates = candidate_sockets()
        path = next((p for p in candidates if p.exists()), None)
        if path is None:
            raise UserError(f"no trundle daemon status socket at {', '.join(map(str, candidates))} "
                            "(is the daemon running? give --config robot.toml or --socket)")
    status = query_status(path)
    print(json_text(status, indent=2) if args.json else format_status(status))
    return 0
