"""Start-up cost of the `trundle` command against bare Python, measured in the same run.

Goals (issue 12): `trundle --help` within 3x of `python -c pass`; `trundle info` on a 1 MB log
under 0.5 s. Each command is run as a new process, as a user runs it, rounds interleaved so a
loaded machine disturbs every command alike; the figure is the median wall time of the rounds.
Baselines: `python -c pass` (the interpreter alone) and, for `info`, reading the same file's
summary with the mcap library's own reader (`python -c "...get_summary()"`).
Run: python tools/bench/bench_cli.py [--rounds N]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from trundle.logs import messages as m
from trundle.logs.topics import SCAN_TOPIC
from trundle.logs.writer import Logger
from trundle.tools.bench import report

SCANS = 300  # noisy 1081-beam scans at 40 Hz: about 1 MB with zstd


def small_log(path: Path, scans: int = SCANS) -> Path:
    """A 7.5 s log of ``scans`` noisy UTM-30LX-like scans (zstd), as `trundle record` writes it."""
    rng = np.random.default_rng(0)
    logger = Logger(path, salvage=False, queue_size=scans + 1)
    stamp = time.time_ns()
    for i in range(scans):
        ranges = np.round(rng.uniform(0.1, 30.0, 1081), 3)
        logger.write(SCAN_TOPIC, m.LaserScan(stamp + i * 25_000_000, "laser", -2.356, 2.356, np.radians(0.25), 1.7e-5,
                                          0.025, 0.023, 30.0, ranges))
    logger.close()
    return path


def wall_s(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tempfile.gettempdir())
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=15, help="runs of each command (default 15)")
    args = parser.parse_args()
    trundle = str(Path(sys.executable).with_name("trundle"))
    with tempfile.TemporaryDirectory() as folder:
        log = small_log(Path(folder) / "small.mcap")
        commands = {
            "bare_python": [sys.executable, "-c", "pass"],
            "mcap_summary": [sys.executable, "-c", "import sys; from mcap.reader import make_reader; "
                             "make_reader(open(sys.argv[1], 'rb')).get_summary()", str(log)],
            "help": [trundle, "--help"],
            "version": [trundle, "--version"],
            "info": [trundle, "info", str(log)],
        }
        times: dict[str, list[float]] = {name: [] for name in commands}
        for _ in range(args.rounds):
            for name, command in commands.items():
                times[name].append(wall_s(command))
        median = {name: statistics.median(values) for name, values in times.items()}
        size = log.stat().st_size
    bare = median["bare_python"]
    report.write("cli", {
        "rounds": args.rounds,
        "log_bytes": size,
        "bare_python_s": bare,
        "help_s": median["help"],
        "version_s": median["version"],
        "info_s": median["info"],
        "mcap_summary_s": median["mcap_summary"],
        "help_over_bare": median["help"] / bare,
        "version_over_bare": median["version"] / bare,
        "info_over_bare": median["info"] / bare,
        "info_over_mcap_summary": median["info"] / median["mcap_summary"],
        "goal_help_within_3x": median["help"] / bare <= 3.0,
        "goal_info_under_0.5s": median["info"] < 0.5,
    })


if __name__ == "__main__":
    main()
