"""`trundle inject-faults LOG -o OUT.mcap`: a copy of a log with realistic wheel-odometry faults.

For testing how odometry faults show in SLAM and localization on real scans. Times are
seconds after the first odometry reading. Faults (each option may be repeated):

  --heading-glitch T:DEG[:S]   the odometry heading turns DEG degrees within S s (default 0.6) from T
  --slip T:S:FRACTION          the wheels report 1 + FRACTION times the distance driven from T for S s
  --scale FRACTION             the whole log's distances off by FRACTION (a wrong wheel radius)
  --dropout T:S                no odometry from T for S s
  --glitches N                 N heading glitches of --glitch-deg over --glitch-s at random times (--seed)
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from trundle.fusion.odometry.faults import OdometryFault, random_glitches
from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text
from trundle.logs.reader import LogReader
from trundle.tools.cli.damage import say_damage
from trundle.tools.config.arguments import finite, non_negative_int, positive
from trundle.tools.config.robot import load_config
from trundle.tools.jobs.inject_faults import inject_faults


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.add_argument("log", type=Path, help="MCAP log with odometry (nav_msgs/Odometry or wheel JointState)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .mcap")
    p.add_argument("--heading-glitch", action="append", default=[], metavar="T:DEG[:S]",
                   help="heading turns DEG degrees within S s (default 0.6) from T s")
    p.add_argument("--slip", action="append", default=[], metavar="T:S:FRACTION",
                   help="wheels report 1 + FRACTION times the distance from T s for S s")
    p.add_argument("--scale", type=finite, metavar="FRACTION", help="distance scale error over the whole log")
    p.add_argument("--dropout", action="append", default=[], metavar="T:S", help="no odometry from T s for S s")
    p.add_argument(
        "--glitches", type=non_negative_int, default=0, metavar="N", help="N heading glitches at random times"
    )
    p.add_argument("--glitch-deg", type=finite, default=20.0, help="size of each random glitch (default 20 deg)")
    p.add_argument("--glitch-s", type=positive, default=0.6, help="duration of each random glitch (default 0.6 s)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the random glitches' times and signs")
    p.add_argument("--config", type=Path, help="robot TOML: its [odometry] table is the wheel model of a wheel log")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def _numbers(text: str, option: str, count: tuple[int, ...]) -> list[float]:
    try:
        values = [float(v) for v in text.split(":")]
    except ValueError:
        values = []
    if len(values) not in count or not all(math.isfinite(v) for v in values):
        forms = {"--heading-glitch": "T:DEG or T:DEG:S", "--slip": "T:S:FRACTION", "--dropout": "T:S"}
        raise UserError(f"{option} {text!r}: expected {forms[option]} (numbers)")
    return values


def faults_from_args(args: argparse.Namespace, span_s: float) -> list[OdometryFault]:
    """The faults the options ask for; ``span_s`` is the odometry's duration (random glitches, scale)."""
    try:
        faults = []
        for text in args.heading_glitch:
            t, degrees, *rest = _numbers(text, "--heading-glitch", (2, 3))
            faults.append(OdometryFault("heading_glitch", t, rest[0] if rest else 0.6, math.radians(degrees)))
        for text in args.slip:
            t, duration, fraction = _numbers(text, "--slip", (3,))
            faults.append(OdometryFault("slip", t, duration, fraction))
        for text in args.dropout:
            t, duration = _numbers(text, "--dropout", (2,))
            faults.append(OdometryFault("dropout", t, duration))
        if args.scale is not None:
            faults.append(OdometryFault("scale", 0.0, span_s, args.scale))
        faults += random_glitches(args.glitches, span_s, math.radians(args.glitch_deg), args.glitch_s, args.seed)
    except ValueError as error:
        raise UserError(str(error)) from None
    if not faults:
        raise UserError("no fault asked for: give --heading-glitch, --slip, --scale, --dropout or --glitches")
    return faults


def run(args: argparse.Namespace) -> int:
    info = LogReader(args.log).info()
    span_s = max(((t.last_ns - t.first_ns) * 1e-9 for t in info.topics.values()
                  if t.ros_type in ("nav_msgs/msg/Odometry", "sensor_msgs/msg/JointState")
                  and t.first_ns is not None and t.last_ns is not None), default=0.0)
    report = inject_faults(args.log, args.output, faults_from_args(args, span_s), load_config(args.config))
    say_damage(args, report["log_damage"])
    if args.json:
        print(json_text(report, indent=2))
        return 0
    for fault in report["faults"]:
        value = f" {math.degrees(fault['value']):+.1f} deg" if fault["kind"] == "heading_glitch" else (
            f" {fault['value']:+.3f}" if fault["kind"] in ("slip", "scale") else "")
        print(f"{fault['kind']} at {fault['start_s']:.2f} s for {fault['duration_s']:.2f} s{value}")
    changed = ", ".join(f"{topic} {c['kept']} of {c['messages']} kept ({c['dropped']} dropped)"
                        for topic, c in report["topics"].items())
    print(f"wrote {args.output}: odometry {changed}")
    return 0
