"""`trundle import carmen|breezyslam|mrclam IN -o OUT.mcap`: public dataset formats -> trundle MCAP logs.

``carmen``: CARMEN ``.clf``/``.log``/``.gfs.log`` (ODOM, FLASER, RLASER, ROBOTLASER1). With
``--drift`` the odometry is made from the laser lines' poses (in GMapping output: the corrected
path) with systematic and random drift (:mod:`trundle.fusion.odometry.drift`), for evaluating SLAM
against those poses; ``--reference`` writes those poses as ``t_ns,x,y,theta`` CSV.
``breezyslam``: BreezySLAM ``.dat`` (wheel ticks -> JointState, URG-04LX ranges -> LaserScan).
``mrclam``: one robot of a UTIAS MRCLAM dataset folder (speeds -> Odometry, barcode sightings ->
LandmarkList on /landmarks); ``--reference`` writes its Vicon ground truth as ``t_ns,x,y,theta`` CSV,
``--landmarks-reference`` the surveyed landmarks as ``id,x,y,sx,sy`` CSV (the files ``trundle slam``
writes, for ``trundle slam-eval``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from trundle.fusion.mapping.map_io import write_landmarks_csv, write_trajectory_csv
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.logs.errors import UserError
from trundle.logs.importers import mcap_output
from trundle.logs.importers.breezyslam import import_breezyslam
from trundle.logs.importers.carmen import ODOMETRY_SOURCES, choose_odometry, import_carmen, read_carmen, scan_poses
from trundle.logs.importers.mrclam import ROBOT_SUBJECTS, import_mrclam
from trundle.logs.outputs import writing_files
from trundle.logs.paths import new_file
from trundle.tools.config.arguments import finite, non_negative_int, number_in, positive


def register(p: argparse.ArgumentParser) -> None:
    formats = p.add_subparsers(dest="format", metavar="FORMAT")
    formats.required = True
    c = formats.add_parser("carmen", help="CARMEN log (.clf, .log, .gfs.log; .gz too)")
    c.add_argument("input", type=Path, help="CARMEN log file")
    c.add_argument("-o", "--output", type=Path, required=True, help="output .mcap (must not exist)")
    c.add_argument("--odometry", choices=ODOMETRY_SOURCES, default="auto",
                   help="odometry source: ODOM lines, the laser lines' odometry fields, or none; auto (default): "
                        "the ODOM lines if there are any, else the laser lines' fields")
    c.add_argument("--max-range", type=positive, help="no-return range of FLASER/RLASER, m (default: inferred)")
    c.add_argument("--drift", action="store_true",
                   help="odometry = laser poses with drift (implies --odometry laser)")
    c.add_argument("--drift-scale", type=number_in(-0.5, 0.5), default=0.05,
                   help="systematic translation scale error (-0.5 .. 0.5; default 0.05)")
    c.add_argument("--drift-heading", type=finite, default=2.0, help="systematic heading drift, deg per metre")
    c.add_argument("--seed", type=non_negative_int, default=0, help="seed of the random part of the drift")
    c.add_argument("--reference", type=Path, help="write the laser poses as t_ns,x,y,theta CSV")
    c.set_defaults(func=run_carmen)
    b = formats.add_parser("breezyslam", help="BreezySLAM / CoreSLAM .dat log")
    b.add_argument("input", type=Path, help="BreezySLAM .dat file")
    b.add_argument("-o", "--output", type=Path, required=True, help="output .mcap (must not exist)")
    b.set_defaults(func=run_breezyslam)
    r = formats.add_parser(
        "mrclam", help="UTIAS MRCLAM dataset folder (RobotN_Odometry.dat, RobotN_Measurement.dat, ...)"
    )
    r.add_argument("input", type=Path, help="dataset folder")
    r.add_argument("--robot", type=number_in(min(ROBOT_SUBJECTS), max(ROBOT_SUBJECTS), whole=True), required=True,
                   help=f"robot number ({min(ROBOT_SUBJECTS)}-{max(ROBOT_SUBJECTS)})")
    r.add_argument("-o", "--output", type=Path, required=True, help="output .mcap (must not exist)")
    r.add_argument("--reference", type=Path, help="write RobotN_Groundtruth.dat as t_ns,x,y,theta CSV")
    r.add_argument("--landmarks-reference", type=Path, help="write Landmark_Groundtruth.dat as id,x,y,sx,sy CSV")
    r.set_defaults(func=run_mrclam)


def _summary(counts: dict[str, int], output: Path) -> None:
    listing = ", ".join(f"{topic} {n}" for topic, n in sorted(counts.items()))
    print(f"wrote {output}: {listing}")


def _outputs(args: argparse.Namespace, *extra: Path | None) -> list[Path]:
    """The log ``-o`` and the ``extra`` files asked for, written together (all or none, never half)."""
    return [mcap_output(args.output), *(p for p in extra if p)]


def run_carmen(args: argparse.Namespace) -> int:
    new_file(mcap_output(args.output), "-o")
    if args.reference:
        new_file(args.reference, "--reference")
    log = read_carmen(args.input)
    stamps, poses = scan_poses(log)
    if args.drift:
        odometry = "laser"
        laser_odometry = drifting_odometry(poses, scale_error=args.drift_scale,
                                           heading_drift_rad_per_m=math.radians(args.drift_heading), seed=args.seed)
        description = (f"the laser lines' poses with drift (scale {args.drift_scale:g}, "
                       f"heading {args.drift_heading:g} deg/m, seed {args.seed})")
    else:
        odometry, description = choose_odometry(log, args.odometry)
        laser_odometry = None
    with writing_files(*_outputs(args, args.reference)) as temps:
        counts = import_carmen(args.input, temps[0], odometry=odometry, laser_odometry=laser_odometry,
                               max_range_m=args.max_range, log=log, description=description)
        if args.reference:
            write_trajectory_csv(temps[1], stamps, poses)
    _summary(counts, args.output)
    print(f"odometry: {description}")
    if odometry == "none":
        print("warning: the log has no odometry: trundle slam will match the scans alone", file=sys.stderr)
    if log.malformed:
        print(f"skipped {log.malformed} malformed lines")
    return 0


def run_breezyslam(args: argparse.Namespace) -> int:
    new_file(mcap_output(args.output), "-o")
    with writing_files(*_outputs(args)) as temps:
        counts = import_breezyslam(args.input, temps[0])
    _summary(counts, args.output)
    return 0


def run_mrclam(args: argparse.Namespace) -> int:
    new_file(mcap_output(args.output), "-o")
    for option, path in (("--reference", args.reference), ("--landmarks-reference", args.landmarks_reference)):
        if path:
            new_file(path, option)
    with writing_files(*_outputs(args, args.reference, args.landmarks_reference)) as temps:
        counts, run, dropped = import_mrclam(args.input, args.robot, temps[0])
        extra = iter(temps[1:])
        if args.reference:
            if run.groundtruth is None or run.groundtruth_ns is None:
                raise UserError(f"--reference: no Robot{args.robot}_Groundtruth.dat in {args.input}")
            write_trajectory_csv(next(extra), run.groundtruth_ns, run.groundtruth)
        if args.landmarks_reference:
            surveyed = sorted(s for s in run.landmarks if s not in ROBOT_SUBJECTS)
            write_landmarks_csv(next(extra), [str(s) for s in surveyed],
                                np.array([run.landmarks[s][:2] for s in surveyed]),
                                np.array([run.landmarks[s][2:] for s in surveyed]))
    _summary(counts, args.output)
    print(f"dropped {dropped['robot_sightings']} sightings of other robots and {dropped['unknown_barcodes']} of "
          f"barcodes not in Barcodes.dat")
    for name, count in sorted(run.malformed.items()):
        print(f"skipped {count} malformed rows of {name}")
    return 0
