"""`trundle emulate can`: an SLCAN adapter on a pty with emulated wheel-encoder nodes behind it.

    trundle emulate can --protocol odrive --link /tmp/ttyCAN0 --script "0:0.5,0.5;4:0.5,-0.5;6:0,0"
    trundle record --can slcan:///tmp/ttyCAN0 --encoders odrive:0,1 -o run.mcap

The velocity script and the faults run on a clock that starts when the host first opens the
adapter (so a recording always begins at the script's start). Faults are scheduled with
``--fault T:KIND[:NODE]`` (T seconds on that clock; NODE = wheel index):
heartbeat-stop, heartbeat-resume, silent, alive (node), errors, bus-off, noise, unplug, replug (adapter).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from trundle.drivers import cia406
from trundle.drivers.dbc_wheels import VESC_DBC
from trundle.drivers.lifecycle import stop_signals
from trundle.logs.errors import UserError
from trundle.tools.config.arguments import number_in, positive
from trundle.tools.emulators.can_nodes import (
    CanNodeRunner,
    EmulatedNode,
    VelocityScript,
    WheelMotion,
    cia406_nodes,
    odrive_nodes,
    vesc_nodes,
)
from trundle.tools.emulators.slcan_emulator import SlcanEmulator

DEFAULT_NODES = {"odrive": "0,1", "cia406": "5,6", "dbc": "9,10"}
NODE_FAULTS = ("heartbeat-stop", "heartbeat-resume", "silent", "alive")
BUS_FAULTS = ("errors", "bus-off", "noise", "unplug", "replug")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--protocol", required=True, choices=("odrive", "cia406", "dbc"),
                        help="odrive (CAN Simple), cia406 (CANopen encoder) or dbc (VESC status per the example DBC)")
    parser.add_argument("--link", required=True, type=Path, help="symlink to create for the adapter's tty")
    parser.add_argument("--nodes", help="node ids, one per wheel (default odrive 0,1; cia406 5,6; dbc 9,10)")
    parser.add_argument(
        "--script",
        help="motor speeds in turns/s from T seconds on: 'T:left,right;T:left,right', e.g. 0:0.5,0.5 "
             "(default: standing still, as the scene of `trundle emulate lrf`, so a first recording of both agrees)",
    )
    parser.add_argument("--duration", type=positive,
                        help="stop this many seconds after the host opened the adapter (default: until Ctrl-C)")
    parser.add_argument("--drop", type=number_in(0.0, 1.0), default=0.0, metavar="P",
                        help="drop each frame with probability P (0 <= P < 1)")
    parser.add_argument("--wrap", action="store_true", help="start the position counters just below their wrap")
    parser.add_argument("--firmware", default="0.5", choices=("0.5", "0.6"), help="ODrive firmware line")
    parser.add_argument("--fault", action="append", default=[], metavar="T:KIND[:WHEEL]",
                        help=f"inject a fault: {', '.join(NODE_FAULTS + BUS_FAULTS)}")


def parse_faults(specs: list[str], wheels: int) -> list[tuple[float, str, int]]:
    """``T:KIND[:WHEEL]`` strings as (time, kind, wheel), sorted by time."""
    faults = []
    for spec in specs:
        parts = spec.split(":")
        try:
            at, kind, wheel = float(parts[0]), parts[1], int(parts[2]) if len(parts) > 2 else 0
        except (ValueError, IndexError):
            raise UserError(f"bad fault {spec!r}: write T:KIND[:WHEEL], e.g. 2.5:heartbeat-stop:1") from None
        if kind not in NODE_FAULTS + BUS_FAULTS:
            raise UserError(f"unknown fault {kind!r}: use one of {', '.join(NODE_FAULTS + BUS_FAULTS)}")
        if not 0 <= wheel < wheels:
            raise UserError(f"fault {spec!r}: wheel must be 0..{wheels - 1}")
        faults.append((at, kind, wheel))
    return sorted(faults)


def build_nodes(protocol: str, ids: list[int], wrap: bool, firmware: str) -> list[EmulatedNode]:
    if protocol == "odrive":
        return odrive_nodes(
            ids, firmware=firmware, count_ms=10 if wrap else 0, count_offset=2**31 - 4096 if wrap else 0
        )
    if protocol == "cia406":
        return cia406_nodes(ids, position_offset=2**24 - 4096 if wrap else 0)
    return vesc_nodes(VESC_DBC, ids, counter_offset=2**31 - 100 if wrap else 0)


def apply_fault(kind: str, node: EmulatedNode, runner: CanNodeRunner, adapter: SlcanEmulator) -> None:
    if kind in ("heartbeat-stop", "heartbeat-resume"):
        node.heartbeat_enabled = kind == "heartbeat-resume"
    elif kind in ("silent", "alive"):
        node.silent = kind == "silent"
    elif kind == "errors":
        runner.error_frames(1)
    elif kind == "bus-off":
        runner.bus_off()
    elif kind == "noise":
        adapter.inject_noise()
    elif kind == "unplug":
        adapter.unplug()
    else:
        adapter.replug()


def run(args: argparse.Namespace) -> int:
    try:
        ids = [int(t, 0) for t in (args.nodes or DEFAULT_NODES[args.protocol]).split(",")]
    except ValueError:
        raise UserError(f"--nodes must be integers separated by commas, got {args.nodes!r}") from None
    # without --script the wheels stand still, as the scene of `emulate lrf` does
    script = VelocityScript.parse(args.script) if args.script else VelocityScript([(0.0, [0.0] * len(ids))])
    if script.wheels != len(ids):
        raise UserError(f"the script gives {script.wheels} speeds per segment for {len(ids)} nodes")
    if not 0.0 <= args.drop < 1.0:
        raise UserError("--drop must be a probability in [0, 1)")
    faults = parse_faults(args.fault, len(ids))
    try:
        nodes = build_nodes(args.protocol, ids, args.wrap, args.firmware)
    except (ValueError, KeyError) as error:
        raise UserError(f"cannot emulate {args.protocol} nodes {ids}: {error}") from None
    if not args.link.parent.is_dir():
        raise UserError(f"no directory for the link: {args.link.parent}")
    spec = {"odrive": "odrive", "cia406": "cia406", "dbc": f"dbc:{VESC_DBC}"}[args.protocol]
    encoders = spec if args.protocol == "dbc" else f"{spec}:{','.join(map(str, ids))}"
    motion = ("the wheels stand still (give --script to drive them)" if not script.speeds.any()
              else f"wheel speeds (turns/s) {args.script}")
    # Ctrl-C and SIGTERM end the emulator alike: its link removed, its counts said, exit 0. The handlers
    # come first: a signal landing between making the link and handling it would leave the link behind
    with stop_signals() as stop:
        adapter = SlcanEmulator(str(args.link)).start()
        runner = CanNodeRunner(adapter.bus, nodes, WheelMotion(script, start_s=float("inf")), adapter=adapter)
        runner.drop_probability = args.drop
        try:
            print(f"SLCAN adapter on {args.link} ({args.protocol} nodes {ids}); {motion}; record with:\n"
                  f"  trundle record --can slcan://{args.link} --encoders {encoders} -o run.mcap", flush=True)
            if args.protocol == "cia406":
                print(f"  (EDS of the emulated encoders: {cia406.DEFAULT_EDS})", flush=True)
            if args.protocol == "dbc":
                signals = ", ".join(f'"VESC_Status5_id{i}.Tachometer"' for i in ids)
                print(f"  with --config holding:\n  [can.dbc]\n  signals = [{signals}]\n  units_per_rev = 42",
                      flush=True)
            runner.start()
            start = None
            while not stop.raised:
                if start is None:
                    if not adapter.is_open:
                        stop.wait(0.005)
                        continue
                    start = time.monotonic()
                    runner.motion = WheelMotion(script, start_s=runner.t)
                    print("host opened the adapter: script and fault clock started", flush=True)
                elapsed = time.monotonic() - start
                while faults and faults[0][0] <= elapsed:
                    at, kind, wheel = faults.pop(0)
                    apply_fault(kind, nodes[wheel], runner, adapter)
                    print(f"{at:8.2f} s  fault: {kind}" + (f" (wheel {wheel})" if kind in NODE_FAULTS else ""),
                          flush=True)
                if args.duration is not None and elapsed >= args.duration:
                    break
                stop.wait(0.05)
        finally:
            runner.stop()
            adapter.close()
    print(f"frames sent {runner.stats['sent']}, dropped {runner.stats['dropped']}, "
          f"to host {adapter.stats['to_host']}, from host {adapter.stats['from_host']}")
    return 0
