"""`trundle localize LOG --map DIR`: localise a log's scans on a saved map, from an unknown start.

DIR holds ``map.yaml`` + ``map.pgm`` as ``trundle slam`` (or ROS's map_saver) writes them; the map
is only read. Odometry comes from the log's ``Odometry`` messages or its wheel ``JointState``
(wheel model from the log's ``robot`` metadata or the config's ``[odometry]`` table, as for
``trundle slam``); without either, the localizer runs on the scans alone. The laser mount comes
from ``/tf_static`` or the config's ``[laser]`` table. Prints when the pose converged, each
kidnapping detected (and the recovery), and writes the tracked poses with ``-o``. A map folder with
``landmarks.csv`` and a log with marker sightings (``/landmarks``) add landmark fixes: global
localisation from two mapped landmarks, and kidnap recovery.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trundle.logs.outputs import json_text
from trundle.logs.paths import new_file
from trundle.logs.topics import SCAN_TOPIC
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import positive
from trundle.tools.config.robot import load_config
from trundle.tools.jobs.localize import localize_log


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.add_argument("log", type=Path, help="MCAP log with LaserScan (and Odometry or wheel JointState)")
    p.add_argument("--map", type=Path, required=True, help="folder with map.yaml + map.pgm, or the map YAML itself")
    p.add_argument("--config", type=Path, help="TOML with [odometry] and [laser] tables (as for trundle slam)")
    p.add_argument("--scan-topic", default=SCAN_TOPIC, help=f"LaserScan topic (default {SCAN_TOPIC})")
    p.add_argument("--max-range", type=positive, default=30.0, help="ignore returns farther than this (m, default 30)")
    p.add_argument("--no-odometry", action="store_true", help="ignore the log's odometry (scans alone)")
    p.add_argument("-o", "--output", type=Path, help="write the tracked poses as t_ns,x,y,theta CSV (must not exist)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the localize job and print its report; exit code 1 if the pose never converged (text mode)."""
    if args.output is not None:
        new_file(args.output, "-o")
    report = localize_log(args.log, args.map, load_config(args.config), scan_topic=args.scan_topic,
                          max_range_m=args.max_range, use_odometry=not args.no_odometry,
                          trajectory_csv=args.output, progress=Progress)
    say_damage(args, report["log_damage"])
    if args.json:
        print(json_text(report, indent=2))
        return 0
    converged, kidnaps = report["converged_at_scans"], report["kidnaps_detected_at_scans"]
    first = f"converged at scan {converged[0] + 1}" if converged else "never converged"
    print(f"{report['scans']} scans ({'with' if report['odometry'] else 'without'} odometry): {first}; "
          f"{len(kidnaps)} kidnapping(s) detected at scan(s) {[k + 1 for k in kidnaps]}, "
          f"{len(converged) - 1 if converged else 0} recovery(ies); {report['global_searches']} global search(es), "
          f"{report['false_alarms']} false alarm(s); {report['tracked_scans']} scans tracked"
          + (f", mean match score {report['match_score_tracking']['mean']:.2f}"
             if report["match_score_tracking"] else "")
          + (f"; {report['landmark_fixes']} landmark fix(es) from {report['landmarks_in_map']} mapped landmarks "
             f"({report['landmark_fixes_rejected']} disagreeing)" if report["landmarks_in_map"] else ""))
    if report["final_pose"]:
        x, y, theta = report["final_pose"]
        print(f"final pose x {x:.3f} m, y {y:.3f} m, theta {np.degrees(theta):.1f} deg; "
              f"{report['processing_s']:.1f} s for {report['duration_s']:.1f} s of log")
    if args.output is not None:
        print(f"wrote {args.output}")
    return 0 if converged else 1

