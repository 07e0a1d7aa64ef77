"""`trundle record`: devices -> MCAP, until --duration elapses or Ctrl-C / SIGTERM."""

from __future__ import annotations

import argparse
import signal
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

from trundle.drivers.devices import FAMILIES, make_driver
from trundle.drivers.lifecycle import Driver
from trundle.fusion.odometry import OdometrySink, odometry_from_config
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.writer import Logger



def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lrf", action="append", default=[], metavar="URL",
                   help="laser: scip2:///dev/ttyACM0, scip2+tcp://host:10940, rplidar:///dev/ttyUSB0")
    p.add_argument("--can", action="append", default=[], metavar="URL",
                   help="CAN bus: slcan:///dev/ttyACM0@1000000, socketcan://can0, virtual://name")
    p.add_argument("--encoders", metavar="SPEC", help="wheel encoders on the CAN bus, e.g. odrive:0,1")
    p.add_argument("--camera", action="append", default=[], metavar="URL",
                   help="camera: v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG, file:///clip.avi")
    p.add_argument("--config", type=Path, help="TOML with [lrf], [can], [camera] tables of driver options; "
                   "wheel_radius_m and track_m in [can] add wheel odometry (/odom, /tf)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("-o", "--output", required=True, type=Path, help="output .mcap")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"),
                   help="chunk compression (default zstd; lz4 when a camera is recorded, since JPEG "
                        "does not compress and zstd would cost ~1 ms a 720p frame)")
    p.add_argument("--split-size", type=float, metavar="MB", help="start a new file every MB megabytes")
    p.add_argument("--split-duration", type=float, metavar="S", help="start a new file every S seconds")
    p.set_defaults(func=run)


def load_config(path: Path | None) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path} is not valid TOML: {error}") from None


def diagnostics(drivers: list[Driver]) -> m.DiagnosticArray:
    return m.DiagnosticArray(time.time_ns(), tuple(d.diagnostics() for d in drivers))


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    specs = [("lrf", url) for url in args.lrf] + [("can", url) for url in args.can] + [("camera", url) for url in args.camera]
    for family in FAMILIES:
        if not any(f == family for f, _ in specs) and isinstance(config.get(family), dict) and "url" in config[family]:
            specs.append((family, config[family]["url"]))
    if not specs:
        raise UserError("no device given: use --lrf, --can or --camera (or url keys in --config)")
    if args.encoders and not any(f == "can" for f, _ in specs):
        raise UserError("--encoders needs a CAN bus (--can URL)")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    compression = args.compression or ("lz4" if any(f == "camera" for f, _ in specs) else "zstd")
    logger = Logger(args.output, compression=compression,
                    split_bytes=int(args.split_size * 1e6) if args.split_size else None,
                    split_duration_s=args.split_duration,
                    metadata={"command": "record", "devices": " ".join(f"{f}={u}" for f, u in specs)})
    drivers = []
    try:
        for family, url in specs:
            options = dict(config.get(family, {}))
            sink: Any = logger
            if family == "can":
                if args.encoders:
                    options["encoders"] = args.encoders
                odometry = odometry_from_config(options)  # wheel_radius_m + track_m in [can]: /odom and /tf
                if odometry is not None:
                    sink = OdometrySink(logger, odometry)
            drivers.append(make_driver(family, url, sink, options))
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        for driver in drivers:
            for topic, msg in driver.static_messages():
                logger.write(topic, msg)
            driver.start()
        deadline = time.monotonic() + args.duration if args.duration else None
        while not stop.wait(1.0 if deadline is None else max(0.0, min(1.0, deadline - time.monotonic()))):
            logger.write("/diagnostics", diagnostics(drivers))
            if logger.error is not None or (deadline is not None and time.monotonic() >= deadline):
                break
    finally:
        for driver in drivers:
            driver.stop()
        if drivers:
            logger.write("/diagnostics", diagnostics(drivers))
        logger.close()
    for path in logger.files:
        print(f"wrote {path}")
    for topic, counts in logger.stats_dict().items():
        print(f"  {topic:<24} written {counts['written']:>7}  dropped {counts['dropped']:>5}")
    for driver in drivers:
        print(f"  {driver.name}: " + ", ".join(f"{k}={v}" for k, v in sorted(driver.counters.items())))
    return 0
