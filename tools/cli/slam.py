"""`trundle slam LOG -o DIR [--config F]`: map a log; write map files, trajectory, report and an MCAP.

The work is the slam job (:mod:`trundle.tools.jobs.slam`, which lists the outputs); this module
turns the command line into its parameters and prints its summary.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from trundle.fusion.slam.estimators import choices
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.robot import load_config
from trundle.tools.jobs.slam import slam_log


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, help="MCAP log with LaserScan and JointState or Odometry")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (created)")
    p.add_argument("--config", type=Path, help="robot TOML: [slam], [odometry], [laser], [landmarks] tables")
    p.add_argument("--no-loop-closure", action="store_true", help="local SLAM only (no pose-graph loops)")
    p.add_argument("--estimator", choices=choices(),
                   help="graph: the pose graph that fits the log (grid SLAM, with landmark constraints when the log "
                        "has sightings; the landmark graph for logs with sightings but no scans); grid, "
                        "grid-landmarks, landmark-graph: that one; ekf: EKF-SLAM of the landmarks (the log's "
                        "sightings, else laser corners). Default: graph")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the slam job on the command's log and print its summary; exit code 0."""
    report = slam_log(args.log, args.output, load_config(args.config), local_only=args.no_loop_closure,
                      progress=Progress, estimator=args.estimator)
    say_damage(args, report["log_damage"])
    print(f"odometry: {report['odometry_source']}")
    if report["odometry_source"] == "none":
        print(f"warning: {args.log} has no odometry (no wheel states, no odometry messages): the map was made "
              "by matching the scans alone", file=sys.stderr)
    if "estimator" in report:
        print(f"{report['estimator']}: {report['landmarks']} landmarks from {report['landmark_sightings_used']} "
              f"sightings ({report['sightings']}), {report['poses']} poses over {report['duration_s']:.1f} s in "
              f"{report['processing_s']:.1f} s ({report['real_time_factor']:.1f}x real time)")
        print(f"wrote {args.output}/map.pgm, map.yaml, map.png, trajectory.png, trajectory.csv, landmarks.csv, "
              "report.json, slam.mcap")
        return 0
    print(f"{report['scans']} scans ({report['keyframes']} keyframes) of {report['duration_s']:.1f} s in "
          f"{report['processing_s']:.1f} s ({report['real_time_factor']:.1f}x real time); "
          f"{report['loop_closures']} loop closures; mean scan-to-map residual "
          f"{report['scan_to_map_residual_m'].get('mean', float('nan')) * 100:.1f} cm")
    landmarks = report.get("landmarks")
    if landmarks:
        print(f"{landmarks['mapped']} landmarks from {landmarks['sightings']} sightings on {landmarks['topic']} in the "
              f"pose graph")
    print(f"wrote {args.output}/map.pgm, map.yaml, map.png, trajectory.png, scans.png, trajectory.csv, "
          f"{'landmarks.csv, ' if landmarks else ''}report.json, slam.mcap")
    check = report.get("map_check")
    if check is not None and check["passed"] is None:
        print("trundle slam: the map's self-check was not made: no keyframe lies outside the submaps it was "
              "part of, so nothing could be compared (a short or stationary log); report.json says 'not checked'",
              file=sys.stderr)
    elif check is not None and not check["passed"]:
        failing = [
            s for s in check["stretches"] if s["last_keyframe"] - s["first_keyframe"] + 1 >= check["min_stretch"]
        ]
        where = ", ".join(f"{max(s['start_s'], 0.0):.0f}-{max(s['end_s'], 0.0):.0f} s" for s in failing[:5])
        print(f"trundle slam: warning: the map fails its self-check (consistency {check['consistency']:.2f}; "
              f"{check['inconsistent_keyframes']} keyframes contradict the rest of the map, at {where}; "
              f"magenta in trajectory.png)", file=sys.stderr)
    return 0
