"""`trundle fleet JOB LOG_OR_GLOB... -o OUT`: one job over many logs on a Ray cluster -> results table.

Each log is one Ray task running the job's own code (:mod:`trundle.tools.jobs`); its outputs go to
``OUT/<log name>/`` (``report.json`` for every job). ``OUT/results.csv`` (and ``results.parquet``
with pyarrow) has one row per log: status (ok, failed, skipped, cancelled), one-line error,
seconds, input size and SHA-256, robot, start and duration, and the job's figures flattened from
its report; ``summary.md`` and ``summary.png`` summarise the fleet. A rerun skips the logs whose
result is complete for the same input and options. Without ``--address`` (or ``RAY_ADDRESS``)
a local Ray is started. Logs are paths on a filesystem every node mounts, folders (every
``*.mcap`` below), globs (quoted, ``**`` allowed) or object-store URLs (fsspec). See docs/fleet.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path
from typing import Any

from trundle.logs.errors import UsageError, UserError
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import non_negative_int, positive, positive_int

JOBS = ("info", "slam", "perceive", "characterize", "localize")


def _job_help() -> str:
    """The job options of every job, from the jobs' own signatures."""
    from trundle.tools.fleet.jobs import describe

    lines = ["job options (--job-options KEY=VALUE ...; the keyword parameters of each job):"]
    lines += [f"  {job:<13} {describe(job) or 'none'}" for job in JOBS]
    return "\n".join(lines)


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.epilog = _job_help() if {"-h", "--help"} & set(sys.argv[1:]) else None
    p.add_argument("job", choices=JOBS, help="the one-log job run on every log")
    p.add_argument("logs", nargs="+", metavar="LOG_OR_GLOB", help="log files, folders, quoted globs or URLs")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (created)")
    p.add_argument("--address", help="Ray cluster HOST:PORT (default: RAY_ADDRESS, else a local Ray)")
    p.add_argument(
        "--retries", type=non_negative_int, default=3, help="runs again of a task lost with its worker (default 3)"
    )
    p.add_argument("--job-options", nargs="+", default=[], metavar="KEY=VALUE", help="the job's options (below)")
    p.add_argument("--num-cpus", type=positive_int, help="CPUs of the local Ray (default: all of this machine)")
    p.add_argument("--cpus-per-log", type=positive, default=1.0, help="CPUs each log's task reserves (default 1)")
    p.add_argument("--force", action="store_true", help="recompute logs whose result is complete")
    p.add_argument("--continue", dest="continue_from", type=Path, metavar="MAPDIR",
                   help="slam only: each robot's logs are sessions in time order, the first continuing the map "
                        "in MAPDIR (a trundle slam output), each next one the output of the one before")
    p.set_defaults(func=run)


def _line(row: dict[str, Any], fleet: Any) -> None:
    """One line on stderr per finished log (when no progress bar is drawn)."""
    done = len(fleet.rows)
    error = f": {row['error']}" if row.get("error") else ""
    seconds = f" ({row['seconds']:.1f} s)" if row.get("seconds") is not None and row["status"] == "ok" else ""
    print(f"[{done}] {row['status']} {row['log']}{seconds}{error}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Run the fleet; exit code 0 if every log is ok or skipped, 1 if any failed, 130 if interrupted."""
    if importlib.util.find_spec("ray") is None:   # found, not imported: a local Ray is set up before its import
        raise UserError("trundle fleet needs Ray: pip install 'trundle[fleet]'")
    from trundle.tools.fleet.jobs import parse_options
    from trundle.tools.fleet.run import figures, run_fleet
    from trundle.tools.jobs.sessions import read_bundle

    options = parse_options(args.job, args.job_options)
    if args.continue_from is not None:
        if args.job != "slam":
            raise UsageError("--continue goes with the slam job only")
        if "continue_from" in options:
            raise UsageError("give the map to continue once: --continue MAPDIR, not continue_from= as well")
        read_bundle(args.continue_from)  # a bad MAPDIR is said before Ray starts
    bar_shown = sys.stderr.isatty()
    fleet = run_fleet(args.job, args.logs, args.output, options, address=args.address, retries=args.retries,
                      num_cpus=args.num_cpus, cpus_per_log=args.cpus_per_log, force=args.force,
                      progress=Progress, on_row=None if bar_shown else _line,
                      say=lambda text: print(text, file=sys.stderr, flush=True), continue_from=args.continue_from)
    counts = ", ".join(f"{fleet.count(s)} {s}" for s in ("ok", "failed", "skipped", "cancelled") if fleet.count(s))
    rate = figures(fleet)["logs_per_minute"]
    print(f"{len(fleet.rows)} logs: {counts} in {fleet.wall_s:.1f} s (Ray's start {fleet.ray_start_s:.1f} s; "
          f"the logs {fleet.elapsed_s:.1f} s on {fleet.cpus:g} CPU{'' if fleet.cpus == 1 else 's'}, "
          f"{rate:.1f} logs/min)")
    for row in fleet.rows:
        if row["status"] == "failed":
            print(f"failed {row['log']}: {row['error']}")
        say_damage(args, row.get("log_damage"))
    print(f"wrote {args.output}/<name>/ and " + ", ".join(p.name for p in fleet.files))
    if fleet.interrupted:
        print(f"trundle fleet: interrupted; cancelled {fleet.count('cancelled')} logs, the results so far are in "
              f"{args.output}", file=sys.stderr)
        return 130
    return 1 if fleet.count("failed") else 0
