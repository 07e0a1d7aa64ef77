"""`trundle slam-eval RESULT REFERENCE`: relation error (Kuemmerle et al. 2009), ATE and RPE of a SLAM trajectory.

RESULT is the ``trajectory.csv`` (``t_ns,x,y,theta``) written by ``trundle slam``. REFERENCE is a
Freiburg ``.relations`` file (relation error only), or a reference trajectory: a
``t_ns,x,y,theta`` CSV or a CARMEN log (its laser lines' poses, e.g. GMapping's corrected
``.gfs.log``), from which the relations between scans ``--step`` apart are taken and ATE and RPE
are computed as well, and the relations between revisits (reference poses less than
``--revisit-m`` apart and more than ``--revisit-s`` apart in time: where a doubled map shows).
Poses are paired by timestamp within ``--tolerance-ms``. With
``--landmarks REF.csv`` (``id,x,y,sx,sy``, e.g. a survey) the ``landmarks.csv`` beside RESULT is
scored too, in the frame of the ATE alignment.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict
from pathlib import Path

from trundle.fusion.evaluation.trajectory_errors import (
    Trajectory,
    evaluate,
    landmark_error,
    read_reference,
)
from trundle.fusion.mapping.map_io import read_landmarks_csv
from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text
from trundle.tools.config.arguments import non_negative, number_in, positive, positive_int

MAX_TOLERANCE_MS = 86_400_000.0  # a day: pairing poses further apart than that compares nothing


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.add_argument("result", help="trajectory.csv from `trundle slam` (t_ns,x,y,theta)")
    p.add_argument("reference", help=".relations file, t_ns,x,y,theta CSV or CARMEN log")
    p.add_argument("--step", type=positive_int, default=1,
                   help="relations and RPE between reference poses this many scans apart (default 1: consecutive)")
    p.add_argument("--tolerance-ms", type=number_in(0.0, MAX_TOLERANCE_MS), default=1.0,
                   help="largest time difference when pairing poses (default 1 ms; at most a day)")
    p.add_argument("--revisit-m", type=positive, default=3.0,
                   help="revisits: reference poses at most this far apart (default 3 m) ...")
    p.add_argument("--revisit-s", type=non_negative, default=30.0,
                   help="... and more than this far apart in time (default 30 s)")
    p.add_argument("--landmarks", help="reference landmarks id,x,y,sx,sy: score the landmarks.csv beside RESULT")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def _text(report: dict) -> str:
    e = report["relation_error"]
    lines = [f"Relations:            {e['count']} ({report['relations']}; {e['missing']} without estimated poses)",
             "Relation error (Kuemmerle et al. 2009), mean +- std:",
             f"  translation abs     {e['translation_abs_m']['mean']:.4f} +- {e['translation_abs_m']['std']:.4f} m"
             f"   (max {e['translation_max_m']:.4f} m)",
             f"  translation sq      {e['translation_sq_m2']['mean']:.4f} +- {e['translation_sq_m2']['std']:.4f} m^2",
             f"  rotation abs        {e['rotation_abs_deg']['mean']:.3f} +- {e['rotation_abs_deg']['std']:.3f} deg"
             f"   (max {e['rotation_max_deg']:.3f} deg)",
             f"  rotation sq         {e['rotation_sq_deg2']['mean']:.3f} +- {e['rotation_sq_deg2']['std']:.3f} deg^2"]
    if "ate" in report:
        a, r = report["ate"], report["rpe"]
        lines += [
            f"ATE (SE(2)-aligned):  rmse {a['rmse_m']:.4f} m, mean {a['mean_m']:.4f} m, median {a['median_m']:.4f} m,"
            f" max {a['max_m']:.4f} m, heading rmse {a['rotation_rmse_deg']:.3f} deg over {a['count']} poses",
            f"RPE ({r['step']} scan{'s' if r['step'] > 1 else ''}):"
            f"         translation rmse {r['translation_rmse_m']:.4f} m,"
            f" rotation rmse {r['rotation_rmse_deg']:.3f} deg",
        ]
        v = report["revisits"]
        lines.append(f"Revisits (< {v['max_distance_m']:g} m, > {v['min_gap_s']:g} s apart): {v['count']} relations, "
                     f"mean {v['translation_abs_m']['mean']:.4f} m, {v['rotation_abs_deg']['mean']:.3f} deg"
                     if v["count"] else f"Revisits (< {v['max_distance_m']:g} m, > {v['min_gap_s']:g} s apart): none")
    if "landmarks" in report:
        k = report["landmarks"]
        lines.append(f"Landmarks (same alignment): mean {k['mean_m']:.4f} m, rmse {k['rmse_m']:.4f} m, "
                     f"max {k['max_m']:.4f} m over {k['count']} ({len(k['missing'])} not mapped, "
                     f"{len(k['extra'])} not in the reference)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    result = read_reference(args.result)
    if not isinstance(result, Trajectory):
        raise UserError(f"{args.result}: RESULT must be a trajectory (t_ns,x,y,theta CSV or CARMEN log)")
    report = evaluate(result, read_reference(args.reference), args.step, int(round(args.tolerance_ms * 1e6)),
                      args.revisit_m, args.revisit_s)
    if args.landmarks:
        if "ate" not in report:
            raise UserError("--landmarks needs a reference trajectory (its ATE alignment places the map)")
        reference = read_landmarks_csv(args.landmarks)  # the file the user named is checked first
        mapped = read_landmarks_csv(Path(args.result).parent / "landmarks.csv")
        report["landmarks"] = asdict(landmark_error(mapped[0], mapped[1], reference[0], reference[1],
                                                    report["ate"]["alignment_xyt"]))
    print(json_text(report, indent=2) if args.json else _text(report))
    return 0
