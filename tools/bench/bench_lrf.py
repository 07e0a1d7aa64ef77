"""SCIP 2.0 decoding against hokuyolx, and the CPU share of the whole laser record path.

1. Decode of one 1081-beam UTM-30LX scan (MD, and ME with intensities) from the received
   bytes, ours (framer + vectorised decode) against hokuyolx 0.9's decoder on the same bytes
   (its split, checksums and per-value conversion). Goal: >= 20x faster.
2. CPU share of the record path (read + decode + log through trundle.logs.writer.Logger with
   zstd, and for SCIP the /scan/timing companion topic) for emulated lasers, against a bare
   read loop on the same link in the same run: a UTM-30LX at 40 Hz streaming 1081 beams with
   intensities (ME), and an RPLIDAR S2 in its fastest mode (DenseBoost, 32 kHz, 2880 samples a
   revolution). The bare loop reads through the drivers' own transport (``SerialLink``, reads
   batched every ``STREAM_BATCH_S``). The emulators run in another process; shares are process CPU time per wall
   second, the minimum over ``--rounds`` interleaved rounds (a busy moment of a shared machine
   hits every side alike), also given per scan and scaled to the device's nominal scan rate in
   case the emulator fell behind. Goal: < 3 % of one core for the UTM-30LX.

Run: python tools/bench/bench_lrf.py [--duration 10] [--rounds 3]   (seconds per round and side)
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from trundle.drivers import rplidar as rp
from trundle.drivers import scip2
from trundle.drivers.rplidar_driver import RplidarConfig, RplidarDriver
from trundle.drivers.scip2 import Measure, ScipFramer
from trundle.drivers.scip2_driver import ScipConfig, ScipDriver
from trundle.drivers.serial_link import STREAM_BATCH_S, SerialLink
from trundle.logs.writer import Logger
from trundle.tools.bench import report
from trundle.tools.emulators.rplidar_emulator import MODELS as RPLIDAR_MODELS
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import MODELS, intensity_of, to_millimetres

REPO = Path(__file__).resolve().parents[2]


def scan_bytes(measure: Measure) -> bytes:
    model = MODELS["utm-30lx"]
    ranges = load_scene().range_source(model.angles, seed=1)(0.0)
    return scip2.encode_scan(measure, 123_456, to_millimetres(ranges, model),
                             intensity_of(ranges) if measure.intensity else None, remaining=0)


def ours(raw: bytes, measure: Measure) -> np.ndarray:
    framer = ScipFramer()
    framer.expect(measure.echo())
    return scip2.decode_scan(framer.feed(raw)[0], measure).distances


def theirs(raw: bytes, measure: Measure) -> np.ndarray:
    """hokuyolx's path from the bytes it received to the values (HokuyoLX._recv/_send_req/_iter_meas)."""
    from hokuyolx import HokuyoLX

    laser = HokuyoLX.__new__(HokuyoLX)
    lines = raw[:-2].decode("ascii").split("\n")
    lines.pop(0)
    HokuyoLX._check_sum(lines.pop(0))
    HokuyoLX._convert2int(HokuyoLX._check_sum(lines.pop(0)))
    return laser._process_scan_data(lines, measure.intensity)


def decode_figures() -> dict[str, float]:
    figures: dict[str, float] = {}
    for command in ("MD", "ME"):
        measure = Measure(command, 0, 1080)
        raw = scan_bytes(measure)
        got, want = ours(raw, measure), theirs(raw, measure)
        np.testing.assert_array_equal(got, want[:, 0] if measure.intensity else want)
        t_ours = t_theirs = float("inf")
        for _ in range(7):  # interleaved, so a busy moment of the machine hits both alike
            t_ours = min(t_ours, report.best_of(partial(ours, raw, measure), repeat=1, number=100))
            t_theirs = min(t_theirs, report.best_of(partial(theirs, raw, measure), repeat=1, number=5))
        key = command.lower()
        figures[f"decode_{key}_ours_us"] = t_ours * 1e6
        figures[f"decode_{key}_hokuyolx_us"] = t_theirs * 1e6
        figures[f"decode_{key}_speedup"] = t_theirs / t_ours
    return figures


def emulator(link: Path, seconds: float, *args: str) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", "lrf", *args,
                                "--link", str(link), "--duration", str(seconds)], cwd=REPO, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 30
    while not link.exists():
        if time.monotonic() > deadline or process.poll() is not None:
            raise RuntimeError("the emulator did not start")
        time.sleep(0.05)
    return process


def cpu_share(work, seconds: float) -> tuple[float, object]:
    """Process CPU time per wall second while ``work`` runs for ``seconds``."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = work(seconds)
    return (time.process_time() - cpu) / (time.perf_counter() - wall), result


def record_path(make_driver, out: Path, lost_counters: tuple[str, ...]):
    """Logger + driver; measured from the driver's first scan (after its start-up)."""
    def work(seconds: float) -> dict:
        logger = Logger(out, compression="zstd", salvage=False)
        driver = make_driver(logger)
        for topic, msg in driver.static_messages():
            logger.write(topic, msg)
        driver.start()
        deadline = time.monotonic() + 15
        while driver.counters["scans"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        first = driver.counters["scans"]
        time.sleep(seconds)
        scans = driver.counters["scans"] - first
        driver.stop()
        logger.close()
        out.unlink()
        return {
            "scans": scans,
            "errors": driver.counters["errors"],
            "lost": sum(driver.counters[k] for k in lost_counters),
        }

    return work


def bare_read(link: Path, baud: int, start: bytes, stop: bytes):
    """The drivers' transport alone: the same SerialLink reads, nothing decoded or logged."""
    def work(seconds: float) -> int:
        link_ = SerialLink(str(link), baud, batch_s=STREAM_BATCH_S)
        link_.write(start)
        total, deadline = 0, time.monotonic() + seconds
        while time.monotonic() < deadline:
            total += len(link_.read())
        link_.close(lambda port: port.write(stop))
        return total
    return work


def scip2_sides(link: Path, folder: Path) -> dict:
    lost = ("checksum_errors", "truncated", "missed_scans", "sink_drops")
    return {
        "bare_read": bare_read(link, 115200, b"QT\nBM\nME0000108001000\n", b"QT\n"),
        "record": record_path(lambda sink: ScipDriver(ScipConfig(port=str(link), intensity=True), sink),
                              folder / "scip.mcap", lost),
        "record_without_timing_topic": record_path(
            lambda sink: ScipDriver(ScipConfig(port=str(link), intensity=True, timing_topic=""), sink),
            folder / "scip-nt.mcap", lost)}


def rplidar_sides(link: Path, folder: Path) -> dict:
    dense = RPLIDAR_MODELS["s2"].mode("DenseBoost").mode
    start = (rp.request(rp.HQ_MOTOR_SPEED_CTRL, struct.pack("<H", 600))
             + rp.request(rp.EXPRESS_SCAN, struct.pack("<BHH", dense.id, 0, 0)))
    lost = ("corrupt_revolutions", "incomplete_revolutions", "sink_drops")
    return {"bare_read": bare_read(link, 1000000, start, rp.request(rp.STOP)),
            "record": record_path(lambda sink: RplidarDriver(RplidarConfig(port=str(link), model="s2"), sink),
                                  folder / "rplidar.mcap", lost)}


def measure(sides: dict, seconds: float, rounds: int) -> dict:
    """Per side the least CPU share over interleaved rounds, with the last round's stats."""
    shares: dict[str, list[float]] = {name: [] for name in sides}
    stats: dict[str, object] = {}
    for _ in range(rounds):
        for name, work in sides.items():
            share, stats[name] = cpu_share(work, seconds)
            shares[name].append(share)
    return {name: (min(values), stats[name]) for name, values in shares.items()}


def path_figures(prefix: str, result: dict, seconds: float, nominal_hz: float) -> dict[str, float]:
    bare, received = result["bare_read"]
    share, stats = result["record"]
    rate = stats["scans"] / seconds
    figures = {
        f"{prefix}_scan_rate_hz": rate,
        f"{prefix}_record_cpu_share_percent": 100 * share,
        f"{prefix}_record_cpu_per_scan_ms": 1000 * share / rate if rate else float("inf"),
        f"{prefix}_record_cpu_share_at_{nominal_hz:g}hz_percent": 100 * share * nominal_hz / rate
        if rate
        else float("inf"),
        f"{prefix}_record_scans_lost": stats["lost"],
        f"{prefix}_record_errors": stats["errors"],
        f"{prefix}_bare_read_cpu_share_percent": 100 * bare,
        f"{prefix}_bare_read_kbytes_per_s": received / seconds / 1000,
        f"{prefix}_record_over_bare_read": share / bare if bare else float("inf"),
    }
    if "record_without_timing_topic" in result:
        figures[f"{prefix}_record_without_timing_topic_cpu_share_percent"] = (
            100 * result["record_without_timing_topic"][0]
        )
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per round and side (goal run: 60)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    args = parser.parse_args()
    figures: dict[str, float] = {"load_average_1min": os.getloadavg()[0]}
    figures.update(decode_figures())
    figures.update({"record_seconds": args.duration, "record_rounds": args.rounds})
    with tempfile.TemporaryDirectory() as folder:
        for prefix, sides, emulate, hz in (("utm30lx", scip2_sides, ("--model", "utm-30lx"), 40.0),
                                           ("rplidar_s2_denseboost", rplidar_sides,
                                            ("--protocol", "rplidar", "--model", "s2"), 11.1)):
            link = Path(folder) / prefix
            process = emulator(link, (len(sides(link, Path(folder))) * args.rounds + 4) * (args.duration + 15),
                               *emulate)
            try:
                figures.update(path_figures(prefix, measure(sides(link, Path(folder)), args.duration, args.rounds),
                                            args.duration, hz))
            finally:
                process.terminate()
                process.wait(10)
    figures["load_average_1min_after"] = os.getloadavg()[0]
    report.write("lrf", figures)


if __name__ == "__main__":
    main()
