"""`trundle slam LOG -o DIR [--config F] [--continue MAPDIR [--freeze] [--allow-new-area]]`: map a log; write
map files, trajectory, report, an MCAP and the session bundle (``--continue``: the map of MAPDIR continued).

The work is the slam job (:mod:`trundle.tools.jobs.slam`, which lists the outputs); this module
turns the command line into its parameters and prints its summary.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from trundle.fusion.slam.estimators import choices
from trundle.logs.errors import UsageError
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
    p.add_argument("--continue", dest="continue_from", type=Path, metavar="MAPDIR",
                   help="continue the map in MAPDIR (the output folder of an earlier trundle slam): place this log "
                        "in it with no initial pose, close loops across the sessions, write the joint map")
    p.add_argument("--freeze", action="store_true", help="with --continue: the old sessions' poses stay as they are")
    p.add_argument("--allow-new-area", action="store_true",
                   help="with --continue: a log that cannot be placed in the map becomes a disconnected part of it")
    p.set_defaults(func=run)


def say_continued(args: argparse.Namespace, report: dict[str, Any]) -> None:
    """The summary of a continued map: where the log was placed, the cross-session closures, the map check."""
    placement, closures, check = report["placement"], report["cross_session_closures"], report["map_check"]
    if report.get("other_laser"):
        print(f"trundle slam: warning: {report['other_laser']}", file=sys.stderr)
    x, y, theta = placement["first_pose"]
    if placement["placed"]:
        print(f"placed in the map of {args.continue_from}: starts at ({x:.2f} m, {y:.2f} m, "
              f"{math.degrees(theta):.1f} deg), match scores {placement['scores'][0]:.2f} and "
              f"{placement['scores'][1]:.2f}; {closures['accepted']} cross-session closures accepted, "
              f"{closures['rejected']} rejected")
    else:
        print(f"not placed in the map of {args.continue_from}: a disconnected new part starting at "
              f"({x:.2f} m, {y:.2f} m)")
    print(f"{len(report['sessions'])} sessions, {report['keyframes']} keyframes; mapping the log took "
          f"{report['processing_s']:.1f} s, continuing the map {report['continue_s']:.1f} s; "
          f"map check {check['status']}")
    print(f"wrote {args.output}/map.pgm, map.yaml, map.png, sessions.png, trajectory.png, trajectory.csv, report.json, "
          "slam.mcap, session/")


def run(args: argparse.Namespace) -> int:
    """Run the slam job on the command's log and print its summary; exit code 0."""
    if (args.freeze or args.allow_new_area) and args.continue_from is None:
        raise UsageError("--freeze and --allow-new-area go with --continue MAPDIR")
    report = slam_log(args.log, args.output, load_config(args.config), local_only=args.no_loop_closure,
                      progress=Progress, estimator=args.estimator, continue_from=args.continue_from,
                      freeze=args.freeze, allow_new_area=args.allow_new_area)
    say_damage(args, report["log_damage"])
    if args.continue_from is not None:
        say_continued(args, report)
        return 0
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
          f"{'landmarks.csv, ' if landmarks else ''}report.json, slam.mcap, session/ (to --continue from)")
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
