"""`trundle characterize LOG --topic T`: a sensor's characteristics from a log, as a report.

The topic's type says what the sensor is (LaserScan: laser; JointState: wheel encoders;
CompressedImage/Image: camera). Writes report.md, report.json and PNG plots into -o DIR;
``--json`` prints the figures as one JSON object (SI units).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from trundle.logs.outputs import json_text
from trundle.tools.cli.damage import say_damage
from trundle.tools.config.arguments import finite, non_negative_int, positive, positive_int
from trundle.tools.jobs.characterize import characterize_log
from trundle.tools.jobs.sensor_report import markdown


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="MCAP log holding the topic")
    p.add_argument("--topic", required=True, help="sensor topic, e.g. /scan, /wheels, /camera/image/compressed")
    p.add_argument("--reference", type=reference,
                   help="the true value: a number (m, e.g. a wall at a known distance) or a CSV of values over "
                        "time with columns t_ns (or t_s) and value")
    p.add_argument(
        "--beam", type=beam, default="all", help="laser beam index compared with --reference, or 'all' (default)"
    )
    p.add_argument("--stated-min", type=finite, help="device's stated lower limit (default: from the messages)")
    p.add_argument("--stated-max", type=finite, help="device's stated upper limit (default: from the messages)")
    p.add_argument("--bits", type=positive_int, help="A/D bits, for the range / 2^bits resolution")
    p.add_argument("--min-still", type=positive, default=1.0, help="shortest standing-still stretch used, s")
    p.add_argument("-o", "--output", type=Path, help="report folder (report.md, report.json, plots)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    p.set_defaults(func=run)


def reference(text: str) -> Path | float:
    """``--reference``: a number (a constant true value, m) unless a file of that name exists, else a CSV path."""
    if not Path(text).exists():
        try:
            return finite(text)
        except argparse.ArgumentTypeError:
            pass
    return Path(text)


def beam(text: str) -> int | str:
    """``--beam``: ``all`` or a beam index >= 0."""
    return text if text == "all" else int(non_negative_int(text))


def run(args: argparse.Namespace) -> int:
    """Run the characterize job and print the figures (JSON), the files written or the Markdown report."""
    figures = characterize_log(args.log, args.topic, args.output, args.reference, beam=args.beam,
                               stated_min=args.stated_min, stated_max=args.stated_max, bits=args.bits,
                               min_still_s=args.min_still)
    say_damage(args, figures["log_damage"])
    if args.json:
        print(json_text(figures))
    elif args.output:
        print(f"wrote {args.output / 'report.md'}, {args.output / 'report.json'}")
    else:
        print(markdown(figures, args.topic, []))
    return 0
