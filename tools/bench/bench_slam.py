"""SLAM speed: real-time factor on exp2 and the imported Intel log, and milliseconds per scan match.

Goal (issue 7): real-time factor (log duration / processing time) >= 15 on this 2-core machine,
Cartographer's Intel figure on a 6-core desktop (Hess et al. 2016, Table V). The logs are imported
to MCAP first and mapped from the MCAP exactly as ``trundle slam`` does (decode included). The
Intel log gets the drifting odometry of the acceptance test (5 %, 2 deg/m, seed 1); its relation
error against GMapping's poses is reported with the speed, and its ATE with and without loop
closure; ``bench-results/slam_intel_loops.png`` draws GMapping's path (blue), ours without loop
closure (green) and ours (red) over our map.

Scan matches are timed on Intel scans 40..119 against a submap built from the 20 scans before
each, from GMapping's pose perturbed by (0.1 m, -0.1 m, 3 deg): the correlative search alone
(its branch-and-bound pyramid already built, as it is for every scan matched against a finished
submap; the first search with the build is reported too) is the baseline; the full match
(search + Levenberg-Marquardt), the refinement alone, point-to-line ICP and an exhaustive search
over the same lattice are given as ratios to it; matches are timed in CPU seconds. Wall-clock
figures depend on the machine's load (shared with other work), so CPU time and the load average
are recorded too.
fr079 (issue 14) is mapped laser-only from GMapping's corrected scans, as ``trundle import carmen
--odometry none`` makes it (and once more by ``trundle slam`` in its own process for its peak
resident memory), and scored against the corrected poses (consecutive relations, revisits
less than 3 m and more than 30 s apart, ATE). Each log's real-time factor is given with
Cartographer's published figure for it (Hess et al. 2016, Table V: Intel 15x, fr079 17x, CSAIL
12x, on a 6-core desktop) and their ratio; the MIT CSAIL log is not in ../shared/data, so its
figure is not measured here.
One scan-to-map match against OpenKarto's (issue 25; ``karto-scanmatcher``, slam_toolbox's matcher, in
the bench extra) on fr079 and Intel: every fifth scan i matched against scans i-5..i-1 at their
corrected poses, the same 0.05 m grid, the same seeded start offsets (up to 0.15 m and 5 deg), both
searching +-0.3 m / +-10 deg, Karto with slam_toolbox's defaults. Timed in CPU seconds, the two
matchers interleaved scan by scan so load disturbs both alike; per match: trundle's search and
refinement (its fields and pyramid included, they are per reference) against Karto's ``match_scan``
(which builds its own correlation grid from the five scans each call), and trundle's reference build
(ray casting the five scans into the grid) against the same Karto call; of the build, the new grid
(its box and three zeroed arrays, ``..._reference_grid_ms``) is printed too, the part a heap's history
moves most. Goals: match at most 2x Karto, build at most 1x; median position and heading errors of both
against the corrected poses. The goals' figures come from a process of its own per log, as a benchmark
runner such as asv runs each benchmark: after the whole logs mapped in this process its heap spans
hundreds of megabytes, several times the last-level cache, and a new reference grid there lands on memory
the cache has not seen, so its time follows the heap's history (docs/slam.md, part twelve). The same
comparison in this process after the whole logs is printed too, ``..._after_whole_logs``. Both run as a
``trundle`` process does, its allocator keeping freed memory for reuse
(:mod:`trundle.fusion.mapping.allocator`; ``allocator_keeps_freed_memory`` says whether it could), and so
does Karto in the same process.
The compiled kernels' first-call times (numba: compiled into an empty cache, then loaded from it)
are measured in fresh processes.
Run: python tools/bench/bench_slam.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.evaluation.trajectory_errors import (
    Trajectory,
    absolute_trajectory_error,
    relation_error,
    revisit_relations,
    trajectory_relations,
)
from trundle.fusion.geometry import scan_to_points, transform_points, voxel_filter, wrap_angle
from trundle.fusion.mapping.allocator import keep_freed_memory
from trundle.fusion.mapping.map_plot import Track, save_figure, trajectory_figure
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.matching.icp import LineReference, icp
from trundle.fusion.matching.scan_matching import (
    MatchResult,
    angular_step,
    correlative_search,
    match_scan,
    refine_pose,
    samples_walls_densely,
)
from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.estimators import EstimatorInputs, make_estimator
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs.importers import breezyslam, carmen
from trundle.logs.messages import LaserScan
from trundle.logs.reader import LogReader
from trundle.tools.bench import report

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
CARTOGRAPHER_RTF = {"intel": 15.0, "fr079": 17.0, "csail": 12.0}  # Hess et al. 2016, Table V


def map_log(
    path: Path, wheels: DiffDriveOdometry | None, loop_closure: bool = True
) -> tuple[Slam, float, float, float]:
    """Run SLAM over an MCAP log as ``trundle slam`` does; returns it, duration, wall and CPU seconds."""
    reader = LogReader(path)
    duration = reader.info().duration_s
    slam = make_estimator("grid", EstimatorInputs(SlamConfig().replace("loop_closure", enabled=loop_closure), wheels))
    assert isinstance(slam, Slam)
    wall, cpu = time.perf_counter(), time.process_time()
    for item in reader.messages():
        slam.process(item.topic, item.msg)
    slam.finish()
    slam.build_map()
    return slam, duration, time.perf_counter() - wall, time.process_time() - cpu


def exhaustive(grid: LogOddsGrid, points: np.ndarray, pose: np.ndarray, window: float, window_theta: float,
               step: float) -> float:
    """Best lattice score by scoring every pose of the window (the baseline branch and bound prunes)."""
    field = grid.likelihood_field(grid.resolution)
    limit = int(math.ceil(window / grid.resolution))
    offsets = np.arange(-limit, limit + 1)
    best = 0.0
    for theta in pose[2] + step * np.arange(-int(window_theta / step), int(window_theta / step) + 1):
        c, s = math.cos(theta), math.sin(theta)
        world = points @ np.array([[c, -s], [s, c]]).T + pose[:2]
        cells = np.floor((world - grid.origin) / grid.resolution).astype(np.int64)
        cols = np.clip(cells[:, 0][None, None] + offsets[:, None, None], 0, field.shape[1] - 1)
        rows = np.clip(cells[:, 1][None, None] + offsets[None, :, None], 0, field.shape[0] - 1)
        best = max(best, float(field[rows, cols].mean(axis=2).max()))
    return best


def matchers(grid: LogOddsGrid, points: np.ndarray, guess: np.ndarray, near: np.ndarray, window: float,
             window_theta: float) -> list[tuple[str, Callable[[], object]]]:
    """The timed matchers on one scan: searches from ``guess``, refinements from ``near`` (m, rad).

    "cold" and "search" are the same call: the first one builds the grid's pyramid.
    """
    step = math.radians(0.5)
    return [("cold", lambda: correlative_search(grid, points, guess, window_xy_m=window,
                                                window_theta_rad=window_theta, angular_step_rad=step)),
            ("search", lambda: correlative_search(grid, points, guess, window_xy_m=window,
                                                  window_theta_rad=window_theta, angular_step_rad=step)),
            ("match", lambda: match_scan(grid, points, guess, window_xy_m=window,
                                         window_theta_rad=window_theta, angular_step_rad=step)),
            ("refine", lambda: refine_pose(grid, points, near)),
            ("icp", lambda: icp(LineReference(grid.occupied_points()), points, near)),
            ("exhaustive", lambda: exhaustive(grid, points, guess, window, window_theta, step))]


def time_matches(log: carmen.CarmenLog, first: int, count: int) -> dict[str, float]:
    _, reference = carmen.scan_poses(log)
    scans = [carmen.to_scan(laser, "laser", carmen.infer_no_return(log)) for laser in log.lasers]
    offset = np.array([0.1, -0.1, math.radians(3.0)])
    window, window_theta = 0.3, math.radians(10.0)
    times: dict[str, list[float]] = {"cold": [], "search": [], "match": [], "refine": [], "icp": [], "exhaustive": []}
    errors: list[float] = []
    for k in range(first, first + count):
        grid = LogOddsGrid(0.05)
        for j in range(k - 20, k):
            grid.insert_rays(reference[j][:2], transform_points(reference[j], scan_to_points(scans[j], range_max=30.0)))
        points = voxel_filter(scan_to_points(scans[k], range_max=30.0), 0.05)
        guess = reference[k] + offset
        grid.likelihood_field(0.05), grid.distance_field(0.5)  # fields are shared by all matchers: not timed
        for name, run in matchers(grid, points, guess, reference[k] + offset / 5, window, window_theta):
            start = time.process_time()
            result = run()
            times[name].append(time.process_time() - start)
            if name == "match" and isinstance(result, MatchResult):  # else None: no match
                errors.append(float(np.hypot(*(result.pose[:2] - reference[k][:2]))))
    median = {name: float(np.median(values)) * 1e3 for name, values in times.items()}
    base = median["search"]
    return {
        "match_scans": count,
        "search_with_pyramid_build_ms": median["cold"],
        "search_ms": base,
        "full_match_ms": median["match"],
        "full_match_vs_search": median["match"] / base,
        "refine_only_ms": median["refine"],
        "refine_only_vs_search": median["refine"] / base,
        "icp_ms": median["icp"],
        "icp_vs_search": median["icp"] / base,
        "exhaustive_ms": median["exhaustive"],
        "exhaustive_vs_search": median["exhaustive"] / base,
        "match_error_to_gmapping_median_m": float(np.median(errors)),
        "search_angular_step_formula_deg": math.degrees(angular_step(0.05, 30.0)),
    }


def karto_scans(scans: list[LaserScan], config: Any) -> list[Any]:  # karto_scanmatcher's binding has no types
    """Karto's LocalizedRangeScan of each LaserScan (ranges as they are: inf and NaN are no return)."""
    import karto_scanmatcher as karto
    return [karto.LocalizedRangeScan(config, [float(r) for r in scan.ranges], karto.Pose2(0.0, 0.0, 0.0),
                                     karto.Pose2(0.0, 0.0, 0.0), k, k * 0.1) for k, scan in enumerate(scans)]


def karto_matcher(resolution: float) -> Any:
    """OpenKarto's scan matcher with slam_toolbox's defaults (``minimum_distance_penalty`` 0.5: Karto's own
    default 1.0 switches the distance penalty off), searching +-0.3 m and +-10 deg at ``resolution``."""
    import karto_scanmatcher as karto
    config = karto.ScanMatcherConfig()
    config.resolution = resolution
    config.search_size = 0.6
    config.smear_deviation = 0.05
    config.distance_variance_penalty = 0.25
    config.angle_variance_penalty = 1.0
    config.minimum_distance_penalty = 0.5
    config.minimum_angle_penalty = 0.9
    config.coarse_angle_resolution = math.radians(2.0)
    config.coarse_search_angle_offset = math.radians(10.0)
    config.fine_search_angle_resolution = math.radians(0.2)
    config.range_threshold = 30.0
    config.use_response_expansion = True
    return karto.Wrapper(config)


def against_karto(name: str, log: carmen.CarmenLog, count: int, seed: int = 1) -> dict[str, object]:
    """One match per fifth scan (up to ``count``), trundle and Karto side by side (see the module docstring)."""
    import karto_scanmatcher as karto
    _, reference = carmen.scan_poses(log)
    no_return = carmen.infer_no_return(log)
    scans = [carmen.to_scan(laser, "laser", no_return) for laser in log.lasers if laser.kind != "RLASER"]
    first = scans[0]
    laser = karto.LaserScanConfig(first.angle_min, first.angle_max, first.angle_increment, 0.0, 30.0, 30.0, "laser")
    kscans = karto_scans(scans, laser)
    matcher = karto_matcher(0.05)
    tracking = SlamConfig().tracking
    rng = np.random.default_rng(seed)
    ours: dict[str, list[float]] = {"build": [], "grid": [], "match": [], "error_m": [], "error_deg": []}
    theirs: dict[str, list[float]] = {"match": [], "error_m": [], "error_deg": []}
    for i in range(5, len(scans), 5)[:count]:
        turn, reach = rng.uniform(-math.pi, math.pi), rng.uniform(0.0, 0.15)
        guess = reference[i] + np.array([reach * math.cos(turn), reach * math.sin(turn),
                                         math.radians(rng.uniform(-5.0, 5.0))])
        references = [(reference[j][:2], transform_points(reference[j], scan_to_points(scans[j], range_max=30.0)))
                      for j in range(i - 5, i)]
        raw = scan_to_points(scans[i], range_max=30.0)
        points = voxel_filter(raw, SlamConfig().scan.voxel_m)
        for j in range(i - 5, i):
            kscans[j].corrected_pose = karto.Pose2(*reference[j])
        kscans[i].corrected_pose = kscans[i].odom_pose = karto.Pose2(*guess)
        start = time.process_time()
        grid = LogOddsGrid(0.05, subcell=True)
        # one allocation for the five; a column's min and max (numpy's axis-0 reduction over (N, 2) took 24 us)
        x, y = np.concatenate([sensor[None] for sensor, _ in references] + [hits for _, hits in references]).T
        grid.ensure_contains(np.array([x.min(), y.min()]), np.array([x.max(), y.max()]))
        allocated = time.process_time()
        for sensor, hits in references:
            grid.insert_rays(sensor, hits)
        built = time.process_time()
        result = match_scan(grid, points, guess, window_xy_m=0.3, window_theta_rad=math.radians(10.0),
                            angular_step_rad=tracking.search_angular_step_rad, shaped_covariance=True,
                            wall_lines=samples_walls_densely(raw, 0.05))
        matched = time.process_time()
        found = matcher.match_scan(kscans[i], kscans[i - 5:i], True, True)
        theirs["match"].append(time.process_time() - matched)
        ours["build"].append(built - start)
        ours["grid"].append(allocated - start)
        ours["match"].append(matched - built)
        for figures, pose in ((ours, None if result is None else result.pose),
                              (theirs, np.array([found.best_pose.x, found.best_pose.y, found.best_pose.yaw]))):
            if pose is None:
                figures["error_m"].append(math.inf)
                figures["error_deg"].append(math.inf)
                continue
            figures["error_m"].append(float(np.hypot(*(pose[:2] - reference[i][:2]))))
            figures["error_deg"].append(abs(math.degrees(wrap_angle(pose[2] - reference[i][2]))))
    median = {f"{who}_{key}": float(np.median(values)) for who, figures in (("trundle", ours), ("karto", theirs))
              for key, values in figures.items()}
    karto_ms = 1e3 * median["karto_match"]
    return {f"{name}_karto_matches": len(ours["match"]),
            f"{name}_trundle_match_ms": 1e3 * median["trundle_match"],
            f"{name}_trundle_reference_build_ms": 1e3 * median["trundle_build"],
            f"{name}_trundle_reference_grid_ms": 1e3 * median["trundle_grid"],
            f"{name}_karto_match_ms": karto_ms,
            f"{name}_match_vs_karto": 1e3 * median["trundle_match"] / karto_ms,
            f"{name}_reference_build_vs_karto": 1e3 * median["trundle_build"] / karto_ms,
            f"{name}_trundle_error_median_m": median["trundle_error_m"],
            f"{name}_trundle_error_median_deg": median["trundle_error_deg"],
            f"{name}_karto_error_median_m": median["karto_error_m"],
            f"{name}_karto_error_median_deg": median["karto_error_deg"]}


# against_karto in a process of its own (argv: the bench's folder, log name, log path, matches); prints JSON.
KARTO_IN_OWN_PROCESS = """
import json, sys
sys.path.insert(0, sys.argv[1])
import bench_slam
bench_slam.keep_freed_memory()
from trundle.logs.importers import carmen
print(json.dumps(bench_slam.against_karto(sys.argv[2], carmen.read_carmen(sys.argv[3]), int(sys.argv[4]))))
"""


def against_karto_in_own_process(name: str, path: Path, count: int) -> dict[str, object]:
    """:func:`against_karto` in a fresh process: the matches timed apart from the memory that whole-log runs
    before them left to a process's allocator (a heap of hundreds of megabytes, freed and reused)."""
    done = subprocess.run([sys.executable, "-c", KARTO_IN_OWN_PROCESS, str(Path(__file__).parent), name, str(path),
                           str(count)], capture_output=True, text=True, check=True)
    figures: dict[str, object] = json.loads(done.stdout.splitlines()[-1])
    return figures


def after_whole_logs(figures: dict[str, object]) -> dict[str, object]:
    """The times and ratios of :func:`against_karto` run in the bench's process after its whole logs, named
    ``..._after_whole_logs``."""
    return {f"{key}_after_whole_logs": value for key, value in figures.items() if key.endswith(("_ms", "_vs_karto"))}


KERNEL_CALLS = """
import time
start = time.perf_counter()
import numpy as np
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.matching.scan_matching import match_scan
imported = time.perf_counter()
angles = np.linspace(-2.0, 2.0, 200)
points = np.stack([3.0 * np.cos(angles), 3.0 * np.sin(angles)], axis=1)
grid = LogOddsGrid(0.05, subcell=True)
grid.insert_rays(np.zeros(2), points)
match_scan(grid, points, np.array([0.05, -0.05, 0.02]))
print(imported - start, time.perf_counter() - imported)
"""


def kernel_first_calls() -> dict[str, float]:
    """Seconds to import the matcher (numba included) and for its first match in a fresh process: with an
    empty numba cache (cold: every kernel compiled) and again with that cache (warm: loaded)."""
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as cache:
        for state in ("cold", "warm"):
            done = subprocess.run([sys.executable, "-c", KERNEL_CALLS], capture_output=True, text=True, check=True,
                                  env={**os.environ, "NUMBA_CACHE_DIR": cache})
            imported, first = (float(v) for v in done.stdout.split())
            figures[f"kernels_{state}_import_s"] = imported
            figures[f"kernels_{state}_first_match_s"] = first
    return figures


# Runs a command and prints its peak resident memory (KiB). A command started from the bench itself would
# not do: on Linux a child inherits the high-water mark of the process it was forked from (the bench holds
# gigabytes of maps by then); one started from this small process inherits little.
PEAK_RSS = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def peak_rss_mb(command: list[str]) -> float:
    """Peak resident memory (MiB) of ``command`` run to its end in a process of its own."""
    done = subprocess.run([sys.executable, "-c", PEAK_RSS, *command], capture_output=True, text=True, check=True)
    return int(done.stdout.split()[-1]) / 1024.0


def fr079_figures(path: Path, folder: Path) -> dict[str, object]:
    """fr079 laser-only: speed against Cartographer's figure, and accuracy against the corrected poses."""
    log = carmen.read_carmen(path)
    stamps, poses = carmen.scan_poses(log)
    mcap = folder / "fr079.mcap"
    carmen.import_carmen(path, mcap, odometry="none", log=log)
    slam, duration, wall, cpu = map_log(mcap, None)
    peak_mb = peak_rss_mb([sys.executable, "-m", "trundle.tools.cli", "slam", str(mcap), "-o", str(folder / "fr079")])
    estimate, reference = Trajectory(*slam.trajectory()), Trajectory(stamps, poses)
    consecutive = relation_error(estimate, trajectory_relations(reference))
    revisits = relation_error(estimate, revisit_relations(reference, 3.0, 30.0))
    check = slam.check_map()
    return {"fr079_duration_s": duration, "fr079_processing_s": wall, "fr079_cpu_s": cpu,
            "fr079_real_time_factor": duration / wall, "fr079_real_time_factor_cpu": duration / cpu,
            "fr079_vs_cartographer_rtf": duration / wall / CARTOGRAPHER_RTF["fr079"],
            "fr079_trundle_slam_peak_rss_mb": peak_mb,
            "fr079_scans": slam.stats.scans, "fr079_loop_closures": slam.stats.loop_closures,
            "fr079_consecutive_translation_mean_m": consecutive.translation_abs_m.mean,
            "fr079_consecutive_rotation_mean_deg": consecutive.rotation_abs_deg.mean,
            "fr079_revisit_relations": revisits.count,
            "fr079_revisit_translation_mean_m": revisits.translation_abs_m.mean,
            "fr079_revisit_rotation_mean_deg": revisits.rotation_abs_deg.mean,
            "fr079_ate_rmse_m": absolute_trajectory_error(estimate, reference).rmse_m,
            "fr079_map_check_passed": check.passed, "fr079_map_consistency": check.consistency}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="exp2 and 20 matches only (no Intel run)")
    args = parser.parse_args()
    exp2, intel = DATA / "breezyslam" / "exp2.dat", DATA / "intel" / "intel.gfs.log"
    for path in (exp2, intel):
        if not path.exists():
            raise SystemExit(f"public data not available: {path} (see ../shared/data/README.md)")
    figures: dict[str, object] = {"load_average_1min_at_start": os.getloadavg()[0], "cpus": os.cpu_count(),
                                  "allocator_keeps_freed_memory": keep_freed_memory()}
    with tempfile.TemporaryDirectory() as folder:
        exp2_mcap = Path(folder) / "exp2.mcap"
        breezyslam.import_breezyslam(exp2, exp2_mcap)
        slam, duration, wall, cpu = map_log(exp2_mcap, DiffDriveOdometry(breezyslam.WHEEL_RADIUS_M, breezyslam.TRACK_M))
        figures.update({"exp2_duration_s": duration, "exp2_processing_s": wall, "exp2_cpu_s": cpu,
                        "exp2_real_time_factor": duration / wall, "exp2_real_time_factor_cpu": duration / cpu,
                        "exp2_scans": slam.stats.scans, "exp2_ms_per_scan": 1e3 * wall / slam.stats.scans,
                        "exp2_loop_closures": slam.stats.loop_closures,
                        "exp2_scan_to_submap_residual_m": float(np.mean(slam.stats.residuals))})
        log = carmen.read_carmen(intel)
        if not args.quick:
            stamps, reference = carmen.scan_poses(log)
            intel_mcap = Path(folder) / "intel.mcap"
            carmen.import_carmen(intel, intel_mcap, odometry="laser", log=log,
                                 laser_odometry=drifting_odometry(reference, seed=1))
            slam, duration, wall, cpu = map_log(intel_mcap, None)
            error = relation_error(Trajectory(*slam.trajectory()), trajectory_relations(Trajectory(stamps, reference)))
            open_loop, _, _, _ = map_log(intel_mcap, None, loop_closure=False)
            ate = absolute_trajectory_error(Trajectory(*slam.trajectory()), Trajectory(stamps, reference))
            ate_open = absolute_trajectory_error(Trajectory(*open_loop.trajectory()), Trajectory(stamps, reference))
            report.RESULTS.mkdir(exist_ok=True)
            tracks = [Track(reference, "reference (laser poses of the log)", "tab:blue", 4.0, 0.5),
                      Track(open_loop.trajectory()[1], "SLAM without loop closure", "tab:green"),
                      Track(slam.trajectory()[1], "SLAM with loop closure", "tab:red")]
            figure = trajectory_figure(slam.build_map().to_message(0), tracks,
                                       "Intel Research Lab: SLAM with and without loop closure")
            save_figure(figure, report.RESULTS / "slam_intel_loops.png", replace=True)   # the bench's own folder
            figures.update({"intel_ate_rmse_m": ate.rmse_m, "intel_ate_rmse_without_loop_closure_m": ate_open.rmse_m})
            figures.update({"intel_duration_s": duration, "intel_processing_s": wall, "intel_cpu_s": cpu,
                            "intel_real_time_factor": duration / wall, "intel_real_time_factor_cpu": duration / cpu,
                            "intel_scans": slam.stats.scans, "intel_ms_per_scan": 1e3 * wall / slam.stats.scans,
                            "intel_loop_closures": slam.stats.loop_closures,
                            "intel_relation_translation_mean_m": error.translation_abs_m.mean,
                            "intel_relation_rotation_mean_deg": error.rotation_abs_deg.mean,
                            "intel_vs_cartographer_rtf": duration / wall / CARTOGRAPHER_RTF["intel"]})
            fr079 = DATA / "fr079" / "fr079-corrected-gfs.log.gz"
            if fr079.exists():
                figures.update(fr079_figures(fr079, Path(folder)))
            else:
                figures["fr079"] = f"not measured: {fr079} absent"
            figures["csail"] = "not measured: the MIT CSAIL log is not in ../shared/data"
    figures.update(time_matches(log, 40, 20 if args.quick else 80))
    matches = {"intel": 20, "fr079": 40} if args.quick else {"intel": 180, "fr079": 957}   # the same both ways
    figures.update(after_whole_logs(against_karto("intel", log, matches["intel"])))
    figures.update(against_karto_in_own_process("intel", intel, matches["intel"]))
    fr079 = DATA / "fr079" / "fr079-corrected-gfs.log.gz"
    if fr079.exists():
        figures.update(after_whole_logs(against_karto("fr079", carmen.read_carmen(fr079), matches["fr079"])))
        figures.update(against_karto_in_own_process("fr079", fr079, matches["fr079"]))
    figures.update(kernel_first_calls())
    figures["load_average_1min_at_end"] = os.getloadavg()[0]
    report.write("slam", figures)


if __name__ == "__main__":
    main()
