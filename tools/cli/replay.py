"""`trundle replay FILE`: play a log in (scaled) real time, with progress and a per-topic summary."""

from __future__ import annotations

import argparse
import collections
import time

from trundle.logs.reader import LogMessage, LogReader
from trundle.logs.replay import replay
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import non_negative


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file")
    p.add_argument("--rate", type=non_negative, default=1.0, help="time scale: 1 real time, 0 as fast as possible")
    p.add_argument("--topics", nargs="+", help="only these topics")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    info = LogReader(args.file).info()
    say_damage(args, info.damage)
    counts: collections.Counter[str] = collections.Counter()
    first: dict[str, int] = {}
    last: dict[str, int] = {}
    progress = Progress("replay", max(info.duration_s, 1e-9))
    t0 = info.start_ns or 0

    def deliver(item: LogMessage) -> None:
        counts[item.topic] += 1
        first.setdefault(item.topic, item.log_time_ns)
        last[item.topic] = item.log_time_ns
        progress.update((item.log_time_ns - t0) * 1e-9, f"{(item.log_time_ns - t0) * 1e-9:7.1f}s")

    started = time.monotonic()
    total = replay(args.file, deliver, rate=args.rate, topics=args.topics)
    progress.close()
    wall = time.monotonic() - started
    print(f"replayed {total} messages of {info.duration_s:.2f}s of log in {wall:.2f}s")
    for topic in sorted(counts):
        span = (last[topic] - first[topic]) * 1e-9
        rate = (counts[topic] - 1) / span if span > 0 else 0.0
        print(f"  {topic:<28} {info.topics[topic].ros_type:<40} {counts[topic]:>7} msgs {rate:8.2f} Hz")
    return 0 if total or info.complete else 1
