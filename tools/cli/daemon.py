"""`trundle daemon --config robot.toml`: the onboard service (drivers, logger, processing, health)."""

from __future__ import annotations

import argparse
from importlib.resources import files
from pathlib import Path

from trundle.logs.errors import UserError
from trundle.tools.config.robot import check_daemon_config, load_config


def register(p: argparse.ArgumentParser) -> None:
    """The command's options on its subparser ``p``."""
    p.description = ("Runs until SIGTERM or SIGINT (the log is closed cleanly); SIGHUP starts a new log file. "
                     "Under systemd (Type=notify) it reports READY and pings the watchdog. "
                     "`trundle daemon --print-example-config > robot.toml` writes a commented example to start from.")
    p.add_argument("--config", type=Path, help="robot TOML (devices, logger, disk, processing, ...)")
    p.add_argument("--check", action="store_true",
                   help="check the configuration exactly as the daemon does at start, then exit")
    p.add_argument("--print-example-config", action="store_true", help="print the example robot TOML and exit")
    p.set_defaults(func=run)


def example_config() -> str:
    """The commented example robot configuration shipped with trundle."""
    return files("trundle.tools.config").joinpath("example.toml").read_text(encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    """Print the example (``--print-example-config``), check the configuration (``--check``: and stop
    there), else run the daemon until it is told to stop."""
    if args.print_example_config:
        print(example_config(), end="")
        return 0
    if args.config is None:
        raise UserError("--config robot.toml is required (start from: trundle daemon --print-example-config)")
    config = load_config(args.config)
    check_daemon_config(config)
    if args.check:
        devices = ", ".join(f"{d.name} ({d.family} {d.url})" for d in config.devices)
        print(f"{args.config}: ok; devices: {devices}; logs in {config.logger.folder}; "
              f"status socket {config.status.socket}")
        from trundle.tools.daemon.disk_guard import other_logs_notice  # reads MCAP: only for --check

        assert config.logger.folder is not None  # check_daemon_config
        notice = other_logs_notice(config.logger.folder, config.robot)
        if notice:
            print(notice)
        return 0
    from trundle.tools.daemon.service import Daemon  # the drivers and the logger: only to run

    return Daemon(config).run()
