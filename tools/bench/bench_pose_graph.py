"""Pose-graph back end on the Intel g2o graph (1228 poses, 1483 edges): our LM against GTSAM's.

Both optimise from the same start: our LAGO-style linear initialisation of the dead-reckoning
graph (GTSAM's own LM cannot start from dead reckoning on this graph: its Cholesky declares the
near-singular information matrices indeterminate, and with QR it stops after 100 iterations far
from the optimum). GTSAM runs Levenberg-Marquardt with its default parameters except the
MULTIFRONTAL_QR linear solver. Figures, best of ``--repeat`` interleaved runs:
  ours_initialize_ms          linear initialisation (orientations, then positions)
  ours_optimize_ms            our LM from that start to convergence
  gtsam_optimize_ms           GTSAM LM from the same start to convergence
  ours_over_gtsam             ours_optimize_ms / gtsam_optimize_ms (lower is better; 1 = parity)
  ours_chi2, gtsam_chi2       final sum of weighted squared errors, each in its own error convention
                              (g2o's t2v for ours, GTSAM's Pose2 Logmap), and their relative difference
  *_iterations                LM iterations
Run: python tools/bench/bench_pose_graph.py [--repeat N]
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from trundle.fusion.optimization.pose_graph import PoseGraph, read_g2o
from trundle.tools.bench import report

INTEL_G2O = Path(__file__).resolve().parents[3] / "shared" / "data" / "intel-posegraph" / "input_INTEL.g2o"


def gtsam_problem(g2o_path: Path, start_poses: np.ndarray) -> tuple:
    """GTSAM factors of a g2o file with vertex 0 held by a tight prior, ``start_poses`` as initial
    values, and LM parameters (defaults, QR linear solver)."""
    import gtsam

    factors, _ = gtsam.readG2o(str(g2o_path), False)
    factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*start_poses[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    initial = gtsam.Values()
    for k, pose in enumerate(start_poses):
        initial.insert(k, gtsam.Pose2(*pose))
    params = gtsam.LevenbergMarquardtParams()
    # GTSAM's Cholesky declares this graph's near-singular information matrices indeterminate
    params.setLinearSolverType("MULTIFRONTAL_QR")
    return factors, initial, params


def gtsam_solve(factors, initial, params) -> tuple[float, np.ndarray, int]:
    """GTSAM Levenberg-Marquardt: final chi2 (2 x GTSAM's error), poses (N, 3), iterations."""
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, initial, params)
    solution = optimizer.optimize()
    poses = np.array([[solution.atPose2(k).x(), solution.atPose2(k).y(), solution.atPose2(k).theta()]
                      for k in range(initial.size())])
    return 2.0 * factors.error(solution), poses, optimizer.iterations()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--g2o", type=Path, default=INTEL_G2O)
    args = parser.parse_args()
    if not args.g2o.exists():
        raise SystemExit(f"{args.g2o} absent: the Intel pose graph is in ../shared/data/intel-posegraph")
    if importlib.util.find_spec("gtsam") is None:
        raise SystemExit("GTSAM is the baseline: pip install gtsam")

    raw = read_g2o(args.g2o)
    init_s = float("inf")
    for _ in range(args.repeat):
        template = copy.deepcopy(raw)
        start = time.perf_counter()
        template.initialize()
        init_s = min(init_s, time.perf_counter() - start)
    start_poses = template.poses

    problem = gtsam_problem(args.g2o, start_poses)

    def ours(graph: PoseGraph) -> tuple[float, int]:
        result = graph.optimize()
        return result.chi2, result.iterations

    def theirs() -> tuple[float, int]:
        chi2, _, iterations = gtsam_solve(*problem)
        return chi2, iterations

    best_ours = best_gtsam = float("inf")
    for _ in range(args.repeat):  # interleaved, so load changes hit both alike
        graph = copy.deepcopy(template)
        t0 = time.perf_counter()
        ours_chi2, ours_iterations = ours(graph)
        t1 = time.perf_counter()
        gtsam_chi2, gtsam_iterations = theirs()
        t2 = time.perf_counter()
        best_ours, best_gtsam = min(best_ours, t1 - t0), min(best_gtsam, t2 - t1)

    report.write("pose_graph", {
        "graph": f"{args.g2o.name}: {len(template)} poses, {template.num_edges} edges",
        "ours_initialize_ms": init_s * 1e3,
        "ours_optimize_ms": best_ours * 1e3,
        "gtsam_optimize_ms": best_gtsam * 1e3,
        "ours_over_gtsam": best_ours / best_gtsam,
        "ours_chi2": ours_chi2,
        "gtsam_chi2": gtsam_chi2,
        "chi2_relative_difference": abs(ours_chi2 - gtsam_chi2) / gtsam_chi2,
        "ours_iterations": ours_iterations,
        "gtsam_iterations": gtsam_iterations,
        "initial_chi2_dead_reckoning": raw.chi2(),
        "initial_chi2_after_initialize": template.chi2(),
        "gtsam_version": metadata.version("gtsam"),
        "numpy_version": np.__version__,
    })


if __name__ == "__main__":
    main()
