"""`trundle emulate lrf`: a Hokuyo SCIP 2.0 or Slamtec RPLIDAR emulator on a pty or a TCP port.

    trundle emulate lrf --protocol scip2 --model utm-30lx --link /tmp/lrf --faults checksum=0.02
    trundle record --lrf scip2:///tmp/lrf -o run.mcap --duration 10

The pty's slave is reachable through the ``--link`` symlink (as ``/dev/serial/by-id/...`` would
be); ``--tcp PORT`` serves Ethernet models (``scip2+tcp://127.0.0.1:PORT``). Fault specs are
described in ``tools/emulators/faults.py``, scenes in ``tools/emulators/scene.py``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from trundle.drivers.lifecycle import stop_signals
from trundle.logs.errors import UserError
from trundle.tools.config.arguments import positive, tcp_port
from trundle.tools.emulators import rplidar_emulator, scip2_emulator
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import parse_faults
from trundle.tools.emulators.scene import DEFAULT_SCENE, load_scene

DEFAULT_MODEL = {"scip2": "utm-30lx", "rplidar": "a1"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--protocol", choices=("scip2", "rplidar"), default="scip2", help="device protocol")
    parser.add_argument("--model", choices=(*scip2_emulator.MODELS, *rplidar_emulator.MODELS),
                        help="sensor model (default utm-30lx for scip2, a1 for rplidar)")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--link", type=Path, metavar="PATH", help="symlink to create for the emulated serial port")
    where.add_argument("--tcp", type=tcp_port, metavar="PORT", help="serve on this TCP port of 127.0.0.1 (0: any)")
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="TOML polygon scene (default: a room)")
    parser.add_argument("--faults", default="", metavar="SPEC", help=(
        "comma-separated per-scan probabilities, flags and durations, e.g. checksum=0.02,stall=0.005,"
        f"stall_s=0.3,streaming,seed=1; scip2: {' '.join(scip2_emulator.KINDS)}, flag streaming, wrap=S "
        f"(seconds to the 24-bit clock wrap); rplidar: {' '.join(rplidar_emulator.KINDS)}, flags "
        f"{' '.join(rplidar_emulator.FLAGS)}; durations stall_s, unplug_s, reboot_s"))
    parser.add_argument("--duration", type=positive, metavar="S", help="stop after this many seconds (default: Ctrl-C)")


def build_device(protocol: str, model_name: str | None, scene_path: Path, faults: str, now_ns: int):
    """The emulated device for the command-line choices (UserError on a bad combination)."""
    model_name = model_name or DEFAULT_MODEL[protocol]
    module = scip2_emulator if protocol == "scip2" else rplidar_emulator
    if model_name not in module.MODELS:
        raise UserError(f"model {model_name} does not speak {protocol}; choose {', '.join(module.MODELS)}")
    model = module.MODELS[model_name]
    plan = parse_faults(faults, module.KINDS, module.FLAGS)
    ranges_at = load_scene(scene_path).range_source(model.angles)
    if protocol == "scip2":
        return scip2_emulator.ScipDevice(model, ranges_at, plan, now_ns)
    return rplidar_emulator.RplidarDevice(model, ranges_at, plan, now_ns)


def run(args: argparse.Namespace) -> int:
    device = build_device(args.protocol, args.model, args.scene, args.faults, time.time_ns())
    if args.link is not None and not args.link.parent.is_dir():
        raise UserError(f"folder for --link does not exist: {args.link.parent}")
    # Ctrl-C and SIGTERM (systemd, kill, a test harness) end the emulator alike: its link removed. The
    # handlers come first: a signal landing between making the link and handling it would leave it
    with stop_signals() as stop:
        try:
            server = DeviceServer(device, link_path=args.link) if args.link is not None else DeviceServer(
                device, tcp_port=args.tcp)
        except OSError as error:
            raise UserError(f"cannot serve the emulator: {error.strerror or error}") from None
        try:
            where = f"{args.link} -> {args.link.resolve()}" if args.link is not None else f"tcp://127.0.0.1:{server.port}"
            print(f"emulating {args.protocol} {device.model.name} on {where} (Ctrl-C to stop)", file=sys.stderr,
                  flush=True)
            server.start()
            deadline = None if args.duration is None else time.monotonic() + args.duration
            while not stop.raised and (deadline is None or time.monotonic() < deadline):
                stop.wait(0.2 if deadline is None else max(0.0, min(0.2, deadline - time.monotonic())))
        finally:
            server.stop()
    faults = ", ".join(f"{k} {v}" for k, v in sorted(device.injected.items())) or "none"
    print(f"sent {len(device.sent)} scans; faults injected: {faults}; unplugs {server.unplugs}", file=sys.stderr)
    return 0
