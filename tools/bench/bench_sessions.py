"""Multi-session mapping (issue 27) on real logs: fr079 and Intel, each cut in two at a place both
halves visit (:mod:`trundle.tools.bench.session_halves`), the second half continuing the first half's
map (``trundle slam B --continue A``) and the other way round; and Intel's second half onto fr079's
first half (another building: refused; with ``--allow-new-area`` two disconnected parts).

Figures per dataset and order: where the continued session was placed against the reference (the
corrected poses of the CARMEN file; the old map is brought into the reference frame by the SE(2)
alignment of the old session's trajectory), the cross-session closures accepted and rejected and how
many of each are wrong / right against the reference (a closure is right when its relative pose is
within 0.2 m and 3 deg of the reference's), the relation error (consecutive scans and revisits, as
``trundle slam-eval``) of the joint trajectory against a single run over the whole log, and the time
of continuing against mapping the half alone (``processing_s`` of the run; ``continue_s`` the
placement, cross-session search, optimisation and joint map check on top; the wall-clock time of the
whole command, reading and writing included, for both; the halves are mapped again in every run, so the
times compare under one load).
The logs are imported as the issue says (fr079 ``--odometry none``, Intel ``--drift``).

The demo world (``--dataset demo``): two ``trundle demo`` runs, the first from the office's start with
seed 0, the second with seed 1 from another start, the route's third corner (the office world with its
route turned to begin there, :func:`turned_world`); the second run's log continues the first's map
(both with the markers the daemon saw in their pose graphs). Figures: each marker's error against the
world file (the joint map placed in the world by the ATE alignment of both sessions' trajectories to the
simulator's ground truth, as the demo's own report does), the map check, the placement.
Run: python tools/bench/bench_sessions.py [--work DIR] [--dataset fr079|intel|foreign|demo]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.evaluation.trajectory_errors import (
    Trajectory,
    absolute_trajectory_error,
    align_se2,
    evaluate,
    landmark_error,
    poses_at,
    read_carmen_trajectory,
)
from trundle.fusion.geometry import compose, relative, wrap_angle
from trundle.fusion.mapping.map_io import read_landmarks_csv, read_trajectory_csv
from trundle.tools.bench import report
from trundle.tools.bench.session_halves import split_index, write_halves
from trundle.tools.jobs.sessions import read_bundle
from trundle.tools.sim.world import DEFAULT_WORLD, load_world

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
DATASETS = {"fr079": ("fr079/fr079-corrected-gfs.log.gz", ["--odometry", "none"]),
            "intel": ("intel/intel.gfs.log", ["--drift"])}
RIGHT_M, RIGHT_RAD = 0.2, math.radians(3.0)


def trundle(*argv: str) -> tuple[int, str, str]:
    """Run the CLI as a command, as a user does: exit code, stdout, stderr."""
    done = subprocess.run([sys.executable, "-m", "trundle.tools.cli", *argv], capture_output=True, text=True)
    return done.returncode, done.stdout, done.stderr


def run(*argv: str) -> tuple[dict[str, Any], float]:
    """``trundle slam ...``: its report and wall-clock seconds; a failure stops the bench."""
    started = time.perf_counter()
    code, out, err = trundle("slam", *argv)
    if code != 0:
        raise SystemExit(f"trundle slam {' '.join(argv)} failed: {err.strip()}")
    folder = Path(argv[argv.index("-o") + 1])
    return json.loads((folder / "report.json").read_text()), time.perf_counter() - started


def prepared(name: str, work: Path) -> tuple[Path, Path, Path, Trajectory]:
    """The imported log, its two halves and the reference trajectory of dataset ``name``."""
    source, options = DATASETS[name]
    carmen = DATA / source
    if not carmen.is_file():
        raise SystemExit(f"{carmen} is missing (see ../shared/data/README.md)")
    log, first, second = work / f"{name}.mcap", work / f"{name}_a.mcap", work / f"{name}_b.mcap"
    if not log.is_file():
        code, _, err = trundle("import", "carmen", str(carmen), "-o", str(log), *options)
        if code != 0:
            raise SystemExit(err)
    reference = read_carmen_trajectory(carmen)
    k = split_index(reference.poses, reference.stamps_ns)
    if not second.is_file():
        write_halves(log, int(reference.stamps_ns[k]), first, second)
    return log, first, second, reference


def keyframe_stamps(folder: Path) -> np.ndarray:
    """The keyframes' stamps (ns) of a slam output's session bundle, by node."""
    with open(folder / "session" / "nodes.csv") as f:
        return np.array([int(row["t_ns"]) for row in csv.DictReader(f)], np.int64)


def trajectory_sessions(folder: Path) -> np.ndarray:
    with open(folder / "trajectory.csv") as f:
        return np.array([int(row["session"]) for row in csv.DictReader(f)], np.int64)


def continued_figures(folder: Path, reference: Trajectory, single: dict[str, Any]) -> dict[str, Any]:
    """Placement error, closures right and wrong, and relation errors of the joint map in ``folder``."""
    result = json.loads((folder / "report.json").read_text())
    stamps, poses = read_trajectory_csv(folder / "trajectory.csv")
    sessions = trajectory_sessions(folder)
    old = sessions == 0
    ref_old, found = poses_at(reference, stamps[old])
    alignment = align_se2(poses[old][found, :2], ref_old[found, :2])
    alignment[2] = wrap_angle(alignment[2])
    new_first = stamps[sessions == 1].min()
    ref_first, ok = poses_at(reference, np.array([new_first]))
    placed = compose(alignment, np.array(result["placement"]["first_pose"]))
    error = relative(ref_first[0], placed) if ok[0] else np.full(3, np.nan)
    nodes = keyframe_stamps(folder)

    def right(closure: dict[str, Any]) -> bool:
        ref, seen = poses_at(reference, nodes[[closure["old"], closure["new"]]])
        if not seen.all():
            return False
        step = relative(relative(ref[0], ref[1]), np.array(closure["measurement"]))
        return bool(math.hypot(step[0], step[1]) <= RIGHT_M and abs(float(wrap_angle(step[2]))) <= RIGHT_RAD)

    closures = result["cross_session_closures"]
    metrics = evaluate(Trajectory(stamps, poses), reference)
    consecutive = metrics["relation_error"]["translation_abs_m"]["mean"]
    revisits = metrics["revisits"]["translation_abs_m"]["mean"]
    return {
        "placement_error_m": float(math.hypot(error[0], error[1])),
        "placement_error_deg": float(abs(math.degrees(wrap_angle(error[2])))),
        "closures_accepted": closures["accepted"],
        "closures_accepted_wrong": sum(not right(c) for c in closures["accepted_closures"]),
        "closures_rejected": closures["rejected"],
        "closures_rejected_right": sum(right(c) for c in closures["rejected_closures"]),
        "relation_error_m": consecutive,
        "relation_error_rot_deg": metrics["relation_error"]["rotation_abs_deg"]["mean"],
        "revisit_error_m": revisits,
        "relation_error_vs_single": consecutive / single["relation_error_m"],
        "revisit_error_vs_single": revisits / single["revisit_error_m"],
        "map_check": result["map_check"]["status"],
        "processing_s": result["processing_s"], "continue_s": result["continue_s"],
    }


def single_figures(folder: Path, reference: Trajectory) -> dict[str, Any]:
    stamps, poses = read_trajectory_csv(folder / "trajectory.csv")
    metrics = evaluate(Trajectory(stamps, poses), reference)
    return {"relation_error_m": metrics["relation_error"]["translation_abs_m"]["mean"],
            "revisit_error_m": metrics["revisits"]["translation_abs_m"]["mean"]}


def dataset(name: str, work: Path) -> dict[str, Any]:
    log, first, second, reference = prepared(name, work)
    figures: dict[str, Any] = {}
    outputs = {key: work / f"{name}_{key}" for key in ("full", "a", "b", "fwd", "rev")}
    if not (outputs["full"] / "report.json").is_file():
        run(str(log), "-o", str(outputs["full"]))
    single = single_figures(outputs["full"], reference)
    figures.update({f"{name} single {k}": v for k, v in single.items()})
    for key, half in (("a", first), ("b", second)):   # mapped again each time: the times compare within one run
        shutil.rmtree(outputs[key], ignore_errors=True)
        alone, wall = run(str(half), "-o", str(outputs[key]))
        figures[f"{name} half {key} alone s"] = alone["processing_s"]
        figures[f"{name} half {key} alone wall s"] = wall
    for key, half, old in (("fwd", second, outputs["a"]), ("rev", first, outputs["b"])):
        shutil.rmtree(outputs[key], ignore_errors=True)
        _, wall = run(str(half), "-o", str(outputs[key]), "--continue", str(old))
        figures[f"{name} {key} wall s"] = wall
        figures.update({f"{name} {key} {k}": v for k, v in continued_figures(outputs[key], reference, single).items()})
    return figures


def foreign(work: Path) -> dict[str, Any]:
    """Intel's second half onto fr079's first half's map: refused; with --allow-new-area, two parts."""
    _, _, intel_b, _ = prepared("intel", work)
    fr079_a = work / "fr079_a"
    if not (fr079_a / "report.json").is_file():
        _, first, _, _ = prepared("fr079", work)
        run(str(first), "-o", str(fr079_a))
    shutil.rmtree(work / "foreign_new_area", ignore_errors=True)
    code, _, err = trundle("slam", str(intel_b), "-o", str(work / "foreign"), "--continue", str(fr079_a))
    result, _ = run(str(intel_b), "-o", str(work / "foreign_new_area"), "--continue", str(fr079_a),
                    "--allow-new-area")
    graph = read_bundle(work / "foreign_new_area")[0]
    old, new = graph.poses[graph.session == 0], graph.poses[graph.session == 1]
    return {"foreign exit code": code, "foreign stderr lines": len(err.strip().splitlines()),
            "foreign message": err.strip(), "foreign new area placed": result["placement"]["placed"],
            "foreign new area cross closures": result["cross_session_closures"]["accepted"],
            "foreign new area cross edges": int(graph.cross_edges().size),
            "foreign new area gap m": float(new[:, 0].min() - old[:, 0].max()),
            "foreign new area continue s": result["continue_s"]}


def turned_world(path: Path, corner: int = 2) -> Path:
    """The default world with its closed route turned to begin at waypoint ``corner`` (and its start pose
    there, facing the next one), written to ``path``."""
    world = json.loads(DEFAULT_WORLD.read_text())
    route = np.array(world["route"], np.float64)
    corners = route[:-1] if np.allclose(route[0], route[-1]) else route
    turned = np.roll(corners, -corner, axis=0)
    turned = np.vstack([turned, turned[:1]])
    heading = math.atan2(turned[1, 1] - turned[0, 1], turned[1, 0] - turned[0, 0])
    world.update(route=turned.tolist(), start=[float(turned[0, 0]), float(turned[0, 1]), heading])
    path.write_text(json.dumps(world))
    return path


def demo(work: Path) -> dict[str, Any]:
    """Two demo runs, the second continuing the first's map: markers against the world, map check."""
    runs = [(work / "demo1", 0, DEFAULT_WORLD), (work / "demo2", 1, turned_world(work / "office_turned.json"))]
    for folder, seed, world in runs:
        if not (folder / "report.json").is_file():
            code, _, err = trundle("demo", "-o", str(folder), "--seed", str(seed), "--world", str(world))
            if not (folder / "demo.mcap").is_file():
                raise SystemExit(f"trundle demo failed ({code}): {err.strip()}")
    first, second = work / "demo1_map", work / "demo_continued"
    if not (first / "report.json").is_file():
        run(str(runs[0][0] / "demo.mcap"), "-o", str(first))
    shutil.rmtree(second, ignore_errors=True)
    result, wall = run(str(runs[1][0] / "demo.mcap"), "-o", str(second), "--continue", str(first))
    stamps, poses = read_trajectory_csv(second / "trajectory.csv")
    truth_parts = [read_trajectory_csv(folder / "ground_truth.csv") for folder, _, _ in runs]
    truth = Trajectory(np.concatenate([t for t, _ in truth_parts]), np.concatenate([p for _, p in truth_parts]))
    ate = absolute_trajectory_error(Trajectory(stamps, poses), truth)
    markers = load_world(DEFAULT_WORLD).markers
    ids, positions, _ = read_landmarks_csv(second / "landmarks.csv")
    known = [d for d in markers if str(d.marker_id) in ids]
    error = landmark_error(ids, positions, [str(d.marker_id) for d in known], np.array([[d.x, d.y] for d in known]),
                           ate.alignment_xyt)
    closures = result["cross_session_closures"]
    return {"demo markers in world": len(markers), "demo markers mapped": len(known),
            "demo marker errors m": error.per_landmark_m, "demo marker max error m": error.max_m,
            "demo ate rmse m": ate.rmse_m, "demo map check": result["map_check"]["status"],
            "demo placed": result["placement"]["placed"], "demo closures accepted": closures["accepted"],
            "demo closures rejected": closures["rejected"], "demo continue wall s": wall}


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, help="folder for the logs and outputs (default: a temporary one)")
    parser.add_argument("--dataset", choices=[*DATASETS, "foreign", "demo"], action="append",
                        help="only these (default: fr079, intel, foreign and demo)")
    args = parser.parse_args()
    chosen = args.dataset or [*DATASETS, "foreign", "demo"]
    with tempfile.TemporaryDirectory() as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        figures: dict[str, Any] = {}
        special = {"foreign": foreign, "demo": demo}
        for name in chosen:
            figures.update(special[name](work) if name in special else dataset(name, work))
        report.write("sessions" if not args.dataset else "sessions_" + "_".join(chosen), figures)


if __name__ == "__main__":
    cli()
