"""`trundle daemon --config robot.toml`: the onboard service (drivers, logger, processing, health)."""

from __future__ import annotations

import argparse
from pathlib import Path

from trundle.tools.daemon.config import load_config
from trundle.tools.daemon.service import Daemon


def register(p: argparse.ArgumentParser) -> None:
    """The command's options on its subparser ``p``."""
    p.description = ("Runs until SIGTERM or SIGINT (the log is closed cleanly); SIGHUP starts a new log file. "
                     "Under systemd (Type=notify) it reports READY and pings the watchdog. "
                     "See tools/daemon/example.toml for the configuration.")
    p.add_argument("--config", required=True, type=Path, help="robot TOML (devices, logger, disk, processing, ...)")
    p.add_argument("--check", action="store_true", help="only check the configuration and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the configuration (``--check``: and stop there), else run the daemon until it is told to stop."""
    config = load_config(args.config)
    if args.check:
        devices = ", ".join(f"{d.name} ({d.family} {d.url})" for d in config.devices)
        print(f"{args.config}: ok; devices: {devices}; logs in {config.logger.folder}; "
              f"status socket {config.status.socket}")
        return 0
    return Daemon(config).run()
