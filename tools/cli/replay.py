"""`trundle replay LOG`: the daemon on a log. Plays the log in log-time order at any rate (from
``--start`` to ``--end`` seconds into it, ``--loop``), runs the daemon's online processing on it
(``--config``, ``--slam``, ``--markers``), serves it live to Foxglove (``--live``) and writes the
replayed messages with the processing's results (``-o OUT.mcap``). The work is
:class:`trundle.tools.daemon.replay.LogReplay`; this module parses, checks and prints.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable
from pathlib import Path

from trundle.logs.errors import UsageError
from trundle.logs.metadata import read_metadata
from trundle.logs.paths import input_file
from trundle.logs.reader import LogReader, damage_dict
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import host_port, non_negative, positive
from trundle.tools.config.robot import load_config
from trundle.tools.daemon.live_view import LiveView
from trundle.tools.daemon.processing import Processing, Publish
from trundle.tools.daemon.replay import (
    LogReplay,
    live_channels,
    missing_inputs,
    no_interrupts,
    output_topics,
    replay_window,
    writing_output,
)
from trundle.tools.jobs.slam import replay_estimator


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, help="MCAP log")
    p.add_argument("--rate", type=non_negative, default=1.0, help="time scale: 1 real time, 0 as fast as possible")
    p.add_argument("--start", type=non_negative, default=0.0, metavar="S", help="from S seconds into the log")
    p.add_argument("--end", type=positive, metavar="E", help="up to E seconds into the log")
    p.add_argument("--topics", nargs="+", help="only these topics")
    p.add_argument("--loop", action="store_true", help="play again from the start at the end, until Ctrl-C")
    p.add_argument("--config", type=Path, help="robot TOML: the daemon's [processing], [slam], [frames] ...")
    p.add_argument("--slam", action="store_true", help="run the daemon's online SLAM (/slam/pose, /tf, /map, /path)")
    p.add_argument("--markers", action="store_true", help="run the daemon's marker detection (markers, /landmarks)")
    p.add_argument("--live", type=host_port, metavar="[HOST:]PORT",
                   help="serve the replay to Foxglove over WebSocket (host 127.0.0.1 unless given)")
    p.add_argument("-o", "--output", type=Path, help="write the replayed messages and the results to this new .mcap")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check everything, say what the log lacks, replay, print the summary; exit code 0."""
    log = input_file(args.file, "MCAP log")
    if args.loop and args.output is not None:
        raise UsageError("--loop plays until Ctrl-C: it cannot write -o (leave out one of them)")
    info = LogReader(log).info()
    say_damage(args, info.damage)
    topics, start_ns, end_ns = replay_window(log, info, args.topics, args.start, args.end)
    absent = [t for t in topics or () if t not in info.topics]
    if absent:
        print(f"trundle replay: {log} has no {', '.join(absent)}: playing the other topics", file=sys.stderr)
    config = load_config(args.config)
    wanted = config.processing.model_copy(update={"slam": config.processing.slam or args.slam,
                                                  "markers": config.processing.markers or args.markers})

    def make_processing(publish: Publish, clock: Callable[[], int]) -> Processing:
        slam = replay_estimator(info, config, wanted.markers) if wanted.slam else None
        return Processing(wanted, config.frames, publish, slam, clock)

    probe = make_processing(lambda topic, msg: None, lambda: 0)
    if probe.active:
        missing = missing_inputs(info, probe, topics)
        if missing:
            print(f"trundle replay: {log} has {', '.join(missing)}", file=sys.stderr)
        replaced = output_topics(info, probe)
        if replaced:
            print(f"trundle replay: the log's own {', '.join(replaced)} are left out: the processing makes them anew",
                  file=sys.stderr)
    live: LiveView | None = None
    output = None
    with contextlib.ExitStack() as stack:
        if args.live is not None:
            host, port = args.live
            live = LiveView(host, port, name=f"trundle replay {log.name}", log_time=True,
                            channels=live_channels(info, topics, probe if probe.active else None))
            stack.callback(_close_live, live)
            print(f"live view: ws://{host}:{live.port} (Foxglove: open connection, Foxglove WebSocket)",
                  flush=True)
        if args.output is not None:
            source = read_metadata(info.metadata)
            fields = {k: v for k, v in source.fields.items() if k not in ("trundle_version", "host")}
            output = stack.enter_context(writing_output(args.output, {
                **fields, "robot": dict(source.robot), "devices": {k: dict(v) for k, v in source.devices.items()},
                "command": "replay", "source": str(log), "source_command": source.command,
                "config_file": config.source, "processing": {"slam": wanted.slam, "markers": wanted.markers},
                "rate": args.rate, "log_damage": damage_dict(info.damage)}))
        t0 = info.start_ns or 0
        window_s = ((end_ns if end_ns is not None else info.end_ns or t0) - start_ns) * 1e-9
        progress = Progress("replay", max(window_s, 1e-9))
        replay = LogReplay(log, rate=args.rate, topics=topics, start_ns=start_ns, end_ns=end_ns, loop=args.loop,
                           make_processing=make_processing if probe.active else None, live=live, output=output,
                           map_frames=(config.frames.map, config.frames.odom), progress=progress.update)
        result = replay.run()
        progress.close()
    passes = f" in {result.passes} passes" if result.passes > 1 else ""
    print(f"replayed {result.messages} messages ({result.log_s:.2f} s of log{passes}) in {result.wall_s:.2f} s: "
          f"rate achieved {result.rate:.2f}x" + (" (stopped by Ctrl-C)" if result.interrupted else ""))
    for topic in sorted(result.counts):
        print(f"  {topic:<28} {info.topics[topic].ros_type:<40} {result.counts[topic]:>7} msgs")
    if probe.slam is not None:
        print(f"slam: {result.scans} scans processed, {result.skipped_scans} skipped to keep up"
              + (f", {result.dropped} messages dropped (queue full)" if result.dropped else ""))
    if result.errors:
        print(f"trundle replay: {result.errors} message(s) failed to process: {result.last_error}", file=sys.stderr)
    if result.published:
        print("results: " + ", ".join(f"{topic} {n}" for topic, n in sorted(result.published.items())))
    if output is not None:
        print(f"wrote {args.output}")
    return 0


def _close_live(live: LiveView) -> None:
    """Close the live view, Ctrl-C ignored meanwhile."""
    with no_interrupts():
        live.close()
