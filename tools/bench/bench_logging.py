"""Logger throughput against the bare mcap Writer, and CDR cost of a 1081-beam scan.

Goals (issue 2): logger/bare throughput ratio >= 0.9 on the same pre-encoded messages;
encode and decode of a 1081-beam scan with intensities <= 30 us each.
Both writers get the same 200 distinct pre-encoded UTM-30LX-like scans, cycled. Throughput is
messages per CPU second of the whole process (both threads), so a loaded machine shifts both
sides alike; CDR figures are CPU time too.
Run: python tools/bench/bench_logging.py [--messages N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.writer import Writer

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.topics import SCAN_TOPIC
from trundle.logs.writer import COMPRESSION, Logger
from trundle.tools.bench import report


def scan(seed: int = 1) -> m.LaserScan:
    """A UTM-30LX-like scan: a smooth room outline with mm-quantised noise and intensities."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-2.356, 2.356, 1081)
    walls = np.minimum(4.0 / np.maximum(np.abs(np.cos(angles)), 1e-3), 6.0 / np.maximum(np.abs(np.sin(angles)), 1e-3))
    ranges = np.round(np.minimum(walls, 30.0) + rng.normal(0, 0.01, 1081), 3)
    return m.LaserScan(1_763_784_000_000_000_000 + seed, "laser", -2.356, 2.356, np.radians(0.25), 1.7e-5, 0.025,
                       0.023, 30.0, ranges, np.round(3000 / (1 + ranges)))


def bare(path: Path, pool: list[bytes], n: int, compression: str) -> float:
    start = time.process_time()
    with open(path, "wb") as f:
        w = Writer(f, compression=COMPRESSION[compression])
        w.start(profile="ros2", library="bench")
        schema = ros2.schema_text("sensor_msgs/msg/LaserScan").encode()
        sid = w.register_schema("sensor_msgs/msg/LaserScan", "ros2msg", schema)
        cid = w.register_channel(SCAN_TOPIC, "cdr", sid)
        for i in range(n):
            w.add_message(cid, i, pool[i % len(pool)], i, i)
        w.finish()
    return time.process_time() - start


def ours(path: Path, pool: list[bytes], n: int, compression: str) -> float:
    start = time.process_time()
    logger = Logger(path, compression=compression, queue_size=n + 1, salvage=False)
    for i in range(n):
        logger.write_encoded(SCAN_TOPIC, "sensor_msgs/msg/LaserScan", pool[i % len(pool)], i, i)
    logger.close()
    assert logger.stats_dict()[SCAN_TOPIC] == {"written": n, "dropped": 0}
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--messages", type=int, default=20000)
    args = parser.parse_args()
    msg = scan()
    ros_type, data = ros2.encode(msg)
    figures: dict[str, float] = {}
    cpu = time.process_time
    figures["cdr_encode_us"] = report.best_of(lambda: ros2.encode(msg), number=2000, clock=cpu) * 1e6
    figures["cdr_decode_us"] = report.best_of(lambda: ros2.decode(ros_type, data), number=2000, clock=cpu) * 1e6
    figures["rosbags_serialize_only_us"] = report.best_of(
        lambda: ros2.TYPESTORE.serialize_cdr(ros2.MAPPINGS[0].to_ros(msg), ros_type), number=2000, clock=cpu) * 1e6
    pool = [ros2.encode(scan(seed))[1] for seed in range(200)]
    with tempfile.TemporaryDirectory() as tmp:
        for compression in ("none", "zstd"):
            rounds = [
                (
                    bare(Path(tmp) / f"bare-{compression}{i}.mcap", pool, args.messages, compression),
                    ours(Path(tmp) / f"ours-{compression}{i}.mcap", pool, args.messages, compression),
                )
                for i in range(7)
            ]
            b, o = min(r[0] for r in rounds), min(r[1] for r in rounds)  # interleaved: load drift hits both
            figures[f"bare_mcap_msgs_per_cpu_s_{compression}"] = args.messages / b
            figures[f"logger_msgs_per_cpu_s_{compression}"] = args.messages / o
            figures[f"logger_vs_bare_ratio_{compression}"] = b / o
    figures["goal_ratio"] = 0.9
    figures["goal_cdr_us"] = 30.0
    report.write("logging", figures)


if __name__ == "__main__":
    main()
