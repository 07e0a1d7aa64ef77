"""`trundle record`: devices -> MCAP, until --duration elapses or Ctrl-C / SIGTERM.

Devices come from ``--lrf``/``--can``/``--camera`` URLs and the ``url`` of the tables in
``--config`` (a robot config, checked as the daemon checks it; a table without a url gives the
options of the device named on the command line). Every device is built, so every URL and
option checked, before the log is created. A device that cannot be opened or gives no usable
data is said on stderr in one line (and its recovery too); if a device gave no data at all, the
command ends with exit code 1.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

from trundle.drivers.devices import FAMILIES, make_driver
from trundle.drivers.health import HealthReporter
from trundle.drivers.lifecycle import Driver, SignalFlag
from trundle.drivers.serial_link import check_free
from trundle.fusion.odometry.diff_drive import OdometrySink, odometry_from_config
from trundle.logs import messages as m
from trundle.logs.errors import OutputError, PortBusyError, UserError
from trundle.logs.frames import FrameTree
from trundle.logs.outputs import is_output_failure, output_error
from trundle.logs.paths import output_folder, writable
from trundle.logs.topics import DIAGNOSTICS_TOPIC, TF_STATIC_TOPIC
from trundle.logs.writer import Logger, LoggerError
from trundle.tools.cli.progress import StatusLine
from trundle.tools.config.arguments import positive
from trundle.tools.config.robot import Device, RobotConfig, load_config


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.add_argument("--lrf", action="append", default=[], metavar="URL",
                   help="laser: scip2:///dev/ttyACM0, scip2+tcp://host:10940, rplidar:///dev/ttyUSB0")
    p.add_argument("--can", action="append", default=[], metavar="URL",
                   help="CAN bus: slcan:///dev/ttyACM0@1000000, socketcan://can0, virtual://name")
    p.add_argument("--encoders", metavar="SPEC", help="wheel encoders on the CAN bus, e.g. odrive:0,1")
    p.add_argument("--camera", action="append", default=[], metavar="URL",
                   help="camera: v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG, file:///clip.avi")
    p.add_argument("--config", type=Path, help="robot TOML with [lrf], [can], [camera] tables of driver options; "
                   "wheel_radius_m and track_m in [can] add wheel odometry (/odom, /tf)")
    p.add_argument("--duration", type=positive, help="stop after this many seconds")
    p.add_argument("-o", "--output", required=True, type=Path, help="output .mcap (must not exist)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"),
                   help="chunk compression (default zstd; lz4 when a camera is recorded, since JPEG "
                        "does not compress and zstd would cost ~1 ms a 720p frame)")
    p.add_argument("--split-size", type=positive, metavar="MB", help="start a new file every MB megabytes")
    p.add_argument("--split-duration", type=positive, metavar="S", help="start a new file every S seconds")
    p.set_defaults(func=run)


def devices_to_record(args: argparse.Namespace, config: RobotConfig) -> list[Device]:
    """The command line's devices (with their family's options from the config), then the config's
    devices of the families the command line does not name."""
    urls = {"lrf": args.lrf, "can": args.can, "camera": args.camera}
    devices: list[Device] = []
    for family in FAMILIES:
        if urls[family]:
            options = config.options(family)
            for i, url in enumerate(urls[family]):
                devices.append(Device(family, family if len(urls[family]) == 1 else f"{family}{i}", url, dict(options)))
            continue
        for device in (d for d in config.devices if d.family == family):
            if not device.url:
                raise UserError(f"{config.source}: [{family}] has no url: add one, or give --{family} URL")
            devices.append(device)
    if not devices:
        raise UserError("no device given: use --lrf, --can or --camera (or url keys in --config)")
    if args.encoders:
        if not any(d.family == "can" for d in devices):
            raise UserError("--encoders needs a CAN bus (--can URL)")
        for d in devices:
            if d.family == "can":
                d.options["encoders"] = args.encoders
    return devices


def diagnostics(drivers: list[Driver]) -> m.DiagnosticArray:
    return m.DiagnosticArray(time.time_ns(), tuple(d.diagnostics() for d in drivers))


class _Deferred:
    """The drivers' sink until the logger exists (drivers are built, so checked, before the file is made)."""

    def __init__(self) -> None:
        self.target: Any = None

    def __call__(self, topic: str, msg: m.Message, log_time_ns: int) -> object:
        return self.target(topic, msg, log_time_ns)


def _recorded_nothing(drivers: list[Driver]) -> bool:
    """True when no device gave usable data: a log would hold diagnostics alone."""
    return not any(d.counters[d.usable] for d in drivers)


def _discard(paths: list[Path]) -> None:
    """Remove the files of a recording that holds nothing recorded."""
    for path in paths:
        path.unlink(missing_ok=True)


PROGRESS_PERIOD_S = 10.0   # a progress line this often when stderr is no terminal (a log file, journald)
QUIET_TOPICS = (DIAGNOSTICS_TOPIC, TF_STATIC_TOPIC)   # not the devices' data: left out of the progress line


class TopicRates:
    """Each topic's message rate (Hz) since the last ``update``, from the logger's written counts."""

    def __init__(self, logger: Logger) -> None:
        self.logger = logger
        self._counts: dict[str, int] = {}
        self._time = time.monotonic()

    def update(self) -> dict[str, float]:
        now = time.monotonic()
        counts = {topic: c["written"] for topic, c in self.logger.stats_dict().items() if topic not in QUIET_TOPICS}
        seconds = max(now - self._time, 1e-6)
        rates = {topic: (n - self._counts.get(topic, 0)) / seconds for topic, n in counts.items()}
        self._counts, self._time = counts, now
        return rates


def progress_text(elapsed_s: float, duration_s: float | None, rates: dict[str, float], logger: Logger) -> str:
    """The progress line: time recorded (of ``duration_s``), each topic's rate, the file and its size."""
    path = logger.current_path
    try:
        size = f"{path.stat().st_size / 1e6:.1f} MB in {path.name}" if path is not None else "no file open"
    except OSError:
        size = f"{path.name}" if path is not None else "no file open"
    of = f" of {duration_s:g} s" if duration_s else " (Ctrl-C stops)"
    topics = ", ".join(f"{topic} {rate:.1f} Hz" for topic, rate in rates.items()) or "no messages yet"
    return f"recording {elapsed_s:.0f} s{of}: {topics}; {size}"


def say(text: str) -> None:
    print(f"trundle record: {text}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    devices = devices_to_record(args, config)
    if args.output.is_dir():
        raise UserError(f"-o {args.output} is a folder: give a file name such as {args.output / 'run.mcap'}")
    sink = _Deferred()
    drivers: list[Driver] = []
    for device in devices:
        target: Any = sink
        odometry = odometry_from_config(device.options) if device.family == "can" else None
        if odometry is not None:  # wheel_radius_m + track_m in [can]: /odom and /tf
            target = OdometrySink(sink, odometry)
        try:
            drivers.append(make_driver(device.family, device.url, target, device.options))
        except UserError as error:
            raise UserError(f"{device.family} {device.url}: {error}") from None
    for driver in drivers:
        check_free(driver.serial_port)
    output_folder(writable(args.output).parent, empty=False)  # the logger refuses to overwrite a recording
    compression = args.compression or ("lz4" if any(d.family == "camera" for d in devices) else "zstd")
    metadata = {"command": "record", "robot": {"name": config.robot},
                "devices": {d.name: {"family": d.family, "url": d.url, **d.options} for d in devices}}
    if config.source:
        metadata["config_file"] = config.source
    try:
        logger = Logger(args.output, compression=compression,
                        split_bytes=int(args.split_size * 1e6) if args.split_size else None,
                        split_duration_s=args.split_duration, metadata=metadata)
    except OSError as error:
        if is_output_failure(error):
            raise output_error(error, args.output) from None
        raise
    for salvaged in logger.salvaged:  # crash files a killed recorder or daemon left next to the output
        say(salvaged.line())
    sink.target = logger
    health = HealthReporter(say)
    busy: PortBusyError | None = None
    line, rates = StatusLine(every_s=PROGRESS_PERIOD_S), TopicRates(logger)
    try:
        stop = SignalFlag()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, stop.raise_)
        static_frames = FrameTree.configured(config.transforms, time.time_ns())
        for driver in drivers:
            for topic, msg in driver.static_messages():
                if not static_frames.add(topic, msg):
                    logger.write(topic, msg)
        if static_frames.frames:  # the config's [[transforms]] and the drivers' mounts; the config wins
            logger.write(TF_STATIC_TOPIC, static_frames.static_message())
        for driver in drivers:
            driver.start()
        started = time.monotonic()
        deadline = started + args.duration if args.duration else None
        while not stop.wait(1.0 if deadline is None else max(0.0, min(1.0, deadline - time.monotonic()))):
            status = diagnostics(drivers)
            logger.write(DIAGNOSTICS_TOPIC, status)
            health.update(status.status)
            line.update(progress_text(time.monotonic() - started, args.duration, rates.update(), logger))
            busy = next((d.port_busy for d in drivers if d.port_busy is not None), None)
            if busy or logger.error is not None or (deadline is not None and time.monotonic() >= deadline):
                break
    finally:
        line.close()
        for driver in drivers:
            driver.stop()
        logger.write(DIAGNOSTICS_TOPIC, diagnostics(drivers))
        try:
            logger.close()
        except LoggerError as error:
            if not _recorded_nothing(drivers):
                raise  # the .active keeps what was flushed: the message says how to recover it
            _discard(logger.files + ([Path(error.path)] if error.path else []))
            raise OutputError(f"cannot write {args.output}: "
                              f"{error.cause.strerror if error.cause else error} (no device had recorded "
                              "anything: nothing was kept)") from None
    nothing = _recorded_nothing(drivers)
    if nothing:  # a log of diagnostics alone is no recording: not kept (said below)
        _discard(logger.files)
    if busy is not None:  # taken by another program after the check above
        raise busy
    for path in [] if nothing else logger.files:
        print(f"wrote {path}")
    for topic, counts in logger.stats_dict().items():
        print(f"  {topic:<24} written {counts['written']:>7}  dropped {counts['dropped']:>5}")
    for driver in drivers:
        print(f"  {driver.name}: " + ", ".join(f"{k}={v}" for k, v in sorted(driver.counters.items())))
    silent = [d for d in drivers if not d.counters[d.usable]]
    for driver in silent:
        why = driver.open_error or driver.silence_reason() or driver.last_error or "no data"
        say(f"{driver.name}: recorded no {driver.usable.replace('_', ' ')}: {why}")
    if nothing:
        say(f"no device recorded anything: no log was kept ({args.output} not written)")
    return 1 if silent else 0
