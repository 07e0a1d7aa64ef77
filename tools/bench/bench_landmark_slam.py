"""Landmark SLAM: EKF update cost against the map size, the Victoria Park graph against GTSAM, and
MRCLAM robot 1 through `trundle slam` against reading the log.

Figures (best of ``--repeat``; times in ms unless said):
  ekf_update_ms_N           one EKF-SLAM update with 5 re-sighted landmarks in a map of N landmarks
                            (N = 10 .. 500), and ekf_update_over_10_N its ratio to N = 10
  ekf_update_exponent       slope of log(time) against log(N) over N >= 50 (2 = the O(n^2) covariance update)
  victoria_ours_s, victoria_gtsam_s   LM on the Victoria Park graph from GTSAM's initial values, ours and
                            GTSAM's (default parameters), seconds; victoria_ours_over_gtsam their ratio
  victoria_ours_chi2, victoria_gtsam_chi2, victoria_chi2_relative_difference   the optima reached
  mrclam_read_s             decoding every message of the imported robot-1 log (the baseline)
  mrclam_graph_s, mrclam_ekf_s   `trundle slam` (landmark graph) and `--estimator ekf` on it, processing
                            seconds; *_over_read their ratios to the baseline; *_real_time_factor the
                            1,894 s of log over the processing time
Run: python tools/bench/bench_landmark_slam.py [--repeat N]   (writes bench-results/landmark_slam.json;
with --picture PATH also the MRCLAM picture of docs/landmark_slam.md)
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from trundle.fusion.optimization.isam_graph import read_isam_graph
from trundle.fusion.slam.ekf_slam import EkfSlam
from trundle.logs import messages as m
from trundle.logs.importers.mrclam import import_mrclam
from trundle.logs.reader import LogReader
from trundle.tools.bench import report
from trundle.tools.jobs.landmark_slam import landmark_slam_log

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
SIZES = (10, 20, 50, 100, 200, 500)


def ekf_with(n: int, rng: np.random.Generator) -> EkfSlam:
    """An EKF-SLAM state holding ``n`` landmarks around the robot."""
    ekf = EkfSlam(pose_covariance=np.diag([0.01, 0.01, 0.001]))
    r = np.diag([0.01, 0.0004])
    for k in range(n):
        ekf.update([m.LandmarkObservation(str(k), rng.uniform(1, 10), rng.uniform(-math.pi, math.pi), r)])
    return ekf


def ekf_update_figures(repeat: int) -> dict[str, float]:
    rng = np.random.default_rng(0)
    figures: dict[str, float] = {}
    for n in SIZES:
        ekf = ekf_with(n, rng)
        _, positions, _ = ekf.landmarks()
        picks = rng.choice(n, 5, replace=False)
        sightings = [
            m.LandmarkObservation(
                str(j),
                float(np.hypot(*positions[j])),
                math.atan2(positions[j][1], positions[j][0]),
                np.diag([0.01, 0.0004]),
            )
            for j in picks
        ]
        figures[f"ekf_update_ms_{n}"] = report.best_of(partial(ekf.update, sightings), repeat, 20) * 1e3
    for n in SIZES:
        figures[f"ekf_update_over_10_{n}"] = figures[f"ekf_update_ms_{n}"] / figures["ekf_update_ms_10"]
    big = [n for n in SIZES if n >= 50]
    figures["ekf_update_exponent"] = float(np.polyfit(np.log(big), np.log([figures[f"ekf_update_ms_{n}"] for n in big]),
                                                      1)[0])
    return figures


def victoria_figures() -> dict[str, float]:
    path = DATA / "victoria-park" / "gtsam_victoria_park.txt"
    if not path.exists() or importlib.util.find_spec("gtsam") is None:
        print(f"skipping Victoria Park: needs {path} and GTSAM")
        return {}
    import gtsam

    graph = read_isam_graph(path).graph
    start = time.perf_counter()
    result = graph.optimize(max_iterations=400)
    ours_s = time.perf_counter() - start
    factors, values = gtsam.load2D(str(path))
    start = time.perf_counter()
    solution = gtsam.LevenbergMarquardtOptimizer(factors, values, gtsam.LevenbergMarquardtParams()).optimize()
    gtsam_s = time.perf_counter() - start
    theirs = 2.0 * factors.error(solution)
    return {"victoria_factors": graph.num_factors, "victoria_values": len(graph), "victoria_ours_s": ours_s,
            "victoria_gtsam_s": gtsam_s, "victoria_ours_over_gtsam": ours_s / gtsam_s,
            "victoria_ours_chi2": result.chi2, "victoria_gtsam_chi2": theirs,
            "victoria_chi2_relative_difference": (result.chi2 - theirs) / theirs}


def mrclam_figures(picture: Path | None) -> dict[str, float]:
    folder = DATA / "mrclam"
    if not (folder / "Robot1_Odometry.dat").exists():
        print(f"skipping MRCLAM: no {folder}")
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "r1.mcap"
        _, run, _ = import_mrclam(folder, 1, log)
        start = time.perf_counter()
        for _ in LogReader(log).messages():
            pass
        read_s = time.perf_counter() - start
        figures: dict[str, float] = {"mrclam_read_s": read_s}
        outputs = {}
        for estimator, name in (("graph", "landmark-graph"), ("ekf", "ekf")):
            result = landmark_slam_log(log, Path(tmp) / estimator, estimator=name)
            figures[f"mrclam_{estimator}_s"] = result["processing_s"]
            figures[f"mrclam_{estimator}_over_read"] = result["processing_s"] / read_s
            figures[f"mrclam_{estimator}_real_time_factor"] = result["real_time_factor"]
            outputs[estimator] = Path(tmp) / estimator
        if picture is not None:
            draw_mrclam(picture, run, outputs)
    return figures


def draw_mrclam(path: Path, run, outputs: dict[str, Path]) -> None:
    """The MRCLAM picture: Vicon path and survey against each estimator's path and landmarks, aligned (SE(2))."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from trundle.fusion.evaluation.trajectory_errors import Trajectory, absolute_trajectory_error, landmark_error
    from trundle.fusion.geometry import compose
    from trundle.fusion.mapping.map_io import read_landmarks_csv, read_trajectory_csv

    truth = Trajectory(run.groundtruth_ns, run.groundtruth)
    survey_ids = [str(s) for s in sorted(run.landmarks) if s > 5]
    survey = np.array([run.landmarks[int(s)][:2] for s in survey_ids])
    figure, axes = plt.subplots(1, len(outputs), figsize=(5.0 * len(outputs), 7.5), sharey=True)
    for ax, (name, folder) in zip(np.atleast_1d(axes), outputs.items(), strict=True):
        estimate = Trajectory(*read_trajectory_csv(folder / "trajectory.csv"))
        ate = absolute_trajectory_error(estimate, truth, 20_000_000)
        aligned = compose(np.array(ate.alignment_xyt), estimate.poses)
        ids, positions, _ = read_landmarks_csv(folder / "landmarks.csv")
        error = landmark_error(ids, positions, survey_ids, survey, ate.alignment_xyt)
        mapped = compose(np.array(ate.alignment_xyt), np.column_stack([positions, np.zeros(len(ids))]))
        ax.plot(truth.poses[:, 0], truth.poses[:, 1], color="0.6", lw=0.6, label="Vicon")
        ax.plot(aligned[::10, 0], aligned[::10, 1], color="tab:red" if name == "graph" else "tab:blue", lw=0.6,
                label=f"{name}: ATE {ate.rmse_m * 100:.1f} cm")
        ax.scatter(survey[:, 0], survey[:, 1], marker="s", s=40, facecolors="none", edgecolors="k", label="survey")
        ax.scatter(mapped[:, 0], mapped[:, 1], marker="x", s=40, color="tab:purple",
                   label=f"landmarks: mean error {error.mean_m * 100:.1f} cm")
        ax.set_title(
            f"MRCLAM Dataset 2, robot 1: {'landmark graph (default)' if name == 'graph' else 'EKF-SLAM alone'}"
        )
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, fontsize=8)
    np.atleast_1d(axes)[0].set_ylabel("y (m)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--picture", type=Path, help="also draw the MRCLAM picture here (PNG)")
    args = parser.parse_args()
    figures = ekf_update_figures(args.repeat)
    figures.update(victoria_figures())
    figures.update(mrclam_figures(args.picture))
    report.write("landmark_slam", figures)


if __name__ == "__main__":
    main()
