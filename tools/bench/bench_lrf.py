"""SCIP 2.0 decoding against hokuyolx, and the CPU share of the whole laser record path.

1. Decode of one 1081-beam UTM-30LX scan (MD, and ME with intensities) from the received
   bytes, ours (framer + vectorised decode) against hokuyolx 0.9's decoder on the same bytes
   (its split, checksums and per-value conversion). Goal: >= 20x faster.
2. CPU share of the record path (read + decode + log through trundle.logs.writer.Logger, with the
   /scan/timing companion topic) for an emulated UTM-30LX at 40 Hz streaming 1081 beams,
   against a bare read loop on the same link in the same run. The emulator runs in another
   process; if it falls short of 40 Hz on a busy machine the share is also given per scan
   and scaled to 40 Hz. Goal: < 3 % of one core.

Run: python tools/bench/bench_lrf.py [--duration 60]   (default 10 s per measurement)
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import serial

from trundle.drivers import scip2
from trundle.drivers.scip2 import Measure, ScipFramer
from trundle.drivers.scip2_driver import ScipConfig, ScipDriver
from trundle.logs.writer import Logger
from trundle.tools.bench import report
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
            t_ours = min(t_ours, report.best_of(lambda: ours(raw, measure), repeat=1, number=100))
            t_theirs = min(t_theirs, report.best_of(lambda: theirs(raw, measure), repeat=1, number=5))
        key = command.lower()
        figures[f"decode_{key}_ours_us"] = t_ours * 1e6
        figures[f"decode_{key}_hokuyolx_us"] = t_theirs * 1e6
        figures[f"decode_{key}_speedup"] = t_theirs / t_ours
    return figures


def emulator(link: Path, seconds: float) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", "lrf", "--model", "utm-30lx",
                                "--link", str(link), "--duration", str(seconds)], cwd=REPO,
                               stderr=subprocess.DEVNULL)
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


def record_path(link: Path, out: Path, timing_topic: str = "/scan/timing"):
    def work(seconds: float) -> dict:
        logger = Logger(out, compression="zstd", salvage=False)
        driver = ScipDriver(ScipConfig(port=str(link), timing_topic=timing_topic), logger)
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
        lost = sum(driver.counters[k] for k in ("checksum_errors", "truncated", "missed_scans", "sink_drops"))
        return {"scans": scans, "errors": driver.counters["errors"], "lost": lost}
    return work


def bare_read(link: Path):
    def work(seconds: float) -> int:
        port = serial.Serial(str(link), timeout=0.05)
        port.write(b"QT\nBM\nMD0000108001000\n")
        total, deadline = 0, time.monotonic() + seconds
        while time.monotonic() < deadline:
            total += len(port.read(max(port.in_waiting, 1)))
        port.write(b"QT\n")
        port.close()
        return total
    return work


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=10.0, help="seconds per CPU measurement (goal run: 60)")
    args = parser.parse_args()
    figures = decode_figures()
    with tempfile.TemporaryDirectory() as folder:
        link = Path(folder) / "lrf"
        process = emulator(link, 3 * args.duration + 40)
        try:
            bare_share, received = cpu_share(bare_read(link), args.duration)
            # the record path measures from its first scan (after QT, PP/VV/II and TM sync)
            share, stats = cpu_share(record_path(link, Path(folder) / "run.mcap"), args.duration)
            scan_only, _ = cpu_share(record_path(link, Path(folder) / "scans.mcap", ""), args.duration)
        finally:
            process.terminate()
            process.wait(10)
    rate = stats["scans"] / args.duration
    figures.update({
        "record_seconds": args.duration,
        "record_scan_rate_hz": rate,
        "record_cpu_share_percent": 100 * share,
        "record_cpu_per_scan_ms": 1000 * share / rate if rate else float("inf"),
        "record_cpu_share_at_40hz_percent": 100 * share * 40 / rate if rate else float("inf"),
        "record_scans_lost": stats["lost"],
        "record_without_timing_topic_cpu_share_percent": 100 * scan_only,
        "bare_read_cpu_share_percent": 100 * bare_share,
        "bare_read_kbytes_per_s": received / args.duration / 1000,
        "record_over_bare_read": share / bare_share if bare_share else float("inf"),
        "record_errors": stats["errors"],
    })
    report.write("lrf", figures)


if __name__ == "__main__":
    main()
