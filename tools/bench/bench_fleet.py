"""Fleet throughput: logs per minute of `trundle fleet slam` on a local Ray with 1 and with 2
worker CPUs, and the scaling efficiency (rate with 2 CPUs / twice the rate with 1; goal >= 0.8
on a 2-core machine), against the baseline measured in the same run: the single-log command
`trundle slam` in a shell loop over the same logs.

The logs are copies of the BreezySLAM exp2 run (641 scans of a real Hokuyo with wheel ticks,
imported with `trundle import breezyslam`) from ../shared/data; the benchmark says so and
writes nothing when that file is absent. Every figure is end-to-end wall time of the command as
a user runs it (Ray's start and stop included); ``*_run_*`` figures count only the span from the
first task submitted to the last finished (run.json), i.e. without the Ray start-up;
``*_cpu_share`` is the jobs' CPU seconds over (that span x CPUs): well below 1, the machine was
busy with other work and the scaling figures say more about that load than about the fleet.
Run: python tools/bench/bench_fleet.py [--logs N]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from trundle.logs.importers.breezyslam import import_breezyslam
from trundle.tools.bench import report

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "breezyslam" / "exp2.dat"


def wall_s(command: list[str], cwd: Path) -> float:
    """Wall seconds of one run of ``command`` (its output discarded; a failure stops the benchmark)."""
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=cwd)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", type=int, default=16,
                        help="copies of the log (default 16: enough that Ray's fixed ~5 s start is not the figure)")
    args = parser.parse_args()
    if not DATA.exists():
        print(f"bench_fleet: skipped, public data not available: {DATA} (see ../shared/data/README.md)")
        return
    trundle = str(Path(sys.executable).with_name("trundle"))
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        logs = root / "logs"
        logs.mkdir()
        import_breezyslam(DATA, logs / "run00.mcap")
        for i in range(1, args.logs):
            shutil.copy(logs / "run00.mcap", logs / f"run{i:02d}.mcap")
        loop = (f'for f in "{logs}"/*.mcap; do '
                f'"{trundle}" slam "$f" -o "{root}/loop/$(basename "$f" .mcap)" || exit 1; done')
        shell_s = wall_s(["bash", "-c", loop], root)
        fleet_s, run_s, share = {}, {}, {}
        for cpus in (1, 2):
            out = root / f"fleet{cpus}"
            fleet_s[cpus] = wall_s([trundle, "fleet", "slam", str(logs), "-o", str(out), "--num-cpus", str(cpus)], root)
            run = json.loads((out / "run.json").read_text())
            if run["ok"] != args.logs:
                raise SystemExit(f"bench_fleet: {run['ok']} of {args.logs} logs ok with {cpus} CPU(s): see {out}")
            run_s[cpus] = run["elapsed_s"]
            share[cpus] = run["job_cpu_seconds"] / (run["elapsed_s"] * cpus)
    per_min = {cpus: 60.0 * args.logs / s for cpus, s in fleet_s.items()}
    run_per_min = {cpus: 60.0 * args.logs / s for cpus, s in run_s.items()}
    shell_per_min = 60.0 * args.logs / shell_s
    report.write("fleet", {
        "logs": args.logs,
        "shell_loop_logs_per_min": shell_per_min,
        "fleet_1cpu_logs_per_min": per_min[1],
        "fleet_2cpu_logs_per_min": per_min[2],
        "fleet_1cpu_over_shell_loop": per_min[1] / shell_per_min,
        "fleet_2cpu_over_shell_loop": per_min[2] / shell_per_min,
        "scaling_efficiency": per_min[2] / (2 * per_min[1]),
        "fleet_1cpu_run_logs_per_min": run_per_min[1],
        "fleet_2cpu_run_logs_per_min": run_per_min[2],
        "run_scaling_efficiency": run_per_min[2] / (2 * run_per_min[1]),
        "fleet_1cpu_cpu_share": share[1],
        "fleet_2cpu_cpu_share": share[2],
    })


if __name__ == "__main__":
    main()
