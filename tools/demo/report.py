"""The demo's report: ``report.json`` (every figure of the run, computed from the log, the SLAM
output and the simulator's truth, with the acceptance checks), ``report.md`` (the same for a
reader) and the pictures of the run (trajectories over the map, marker detections in a frame).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
from matplotlib.figure import Figure

from trundle.fusion.evaluation.trajectory_errors import Trajectory, landmark_error, poses_at
from trundle.fusion.mapping.map_plot import Track, save_figure, trajectory_figure
from trundle.logs import messages as m
from trundle.logs.outputs import write_image, write_json, write_text
from trundle.logs.reader import LogReader, damage_dict
from trundle.logs.topics import DIAGNOSTICS_TOPIC, IMAGE_TOPIC
from trundle.perception.images import decode_image
from trundle.tools.demo.ground_truth import Recording
from trundle.tools.demo.scoring import (
    MarkerScore,
    camera_from_info,
    camera_pose,
    map_wall_distances,
    path_length,
    score_trajectory,
)
from trundle.tools.demo.slam import SlamRun
from trundle.tools.jobs.slam import map_check_report
from trundle.tools.sim.camera_render import MAX_INCIDENCE_DEG, MIN_SIDE_PX, CameraRenderer
from trundle.tools.sim.robot import Mount
from trundle.tools.sim.world import World

ATE_LIMIT_M = 0.05          # acceptance: SLAM trajectory error against ground truth ...
LOOP_MIN_M = 50.0           # ... over a loop (the whole route) at least this long
MARKER_MAP_LIMIT_M = 0.05   # acceptance: every marker mapped (as a SLAM landmark) within this of the world file
NO_WORSE_M = 0.001          # "no worse": two runs' ATE of a minute of driving differ by this much for nothing
STARVED_MS = 100.0          # an emulator later than this could not keep real time


def verdict(ok: bool | None) -> str:
    """A check's word: PASS, FAIL, or NOT CHECKED (None: nothing to check it on, e.g. the map self-check
    of a short run); only FAIL fails the demo."""
    return "NOT CHECKED" if ok is None else ("PASS" if ok else "FAIL")


def starved(recording: Recording) -> list[str]:
    """The emulators that were more than ``STARVED_MS`` late while the robot drove."""
    return [name for name, late in recording.emulator_late_ms.items() if late is not None and late > STARVED_MS]


def driver_diagnostics(log: Path) -> dict[str, dict[str, Any]]:
    """The last ``/diagnostics`` status of every component in the log (drivers, logger, disk, ...):
    level, message and values (numbers where they are numbers)."""
    last: dict[str, m.DiagnosticStatus] = {}
    with LogReader(log) as reader:
        for item in reader.messages(topics=[DIAGNOSTICS_TOPIC]):
            if not isinstance(item.msg, m.DiagnosticArray):
                continue
            for status in item.msg.status:
                last[status.name] = status
    levels = {m.OK: "OK", m.WARN: "WARN", m.ERROR: "ERROR", m.STALE: "STALE"}
    return {name: {"level": levels.get(s.level, str(s.level)), "message": s.message,
                   "values": {k: _number(v) for k, v in s.values}} for name, s in sorted(last.items())}


def _number(text: str) -> int | float | str:
    """A diagnostic value as the finite number it spells, else as the text."""
    for kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            continue
        return value if math.isfinite(value) else text
    return text


def _stats(values: np.ndarray) -> dict[str, float]:
    """Median, 95th percentile and maximum of ``values`` (their unit); empty for no values."""
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return {}
    return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)), "max": float(values.max())}


def marker_map(run: SlamRun, world: World, map_to_world) -> dict[str, Any]:
    """The markers SLAM mapped (landmarks) against the world file: each one's position error (m) with
    the map placed in the world by ``map_to_world`` (the trajectory's ATE alignment)."""
    mapped = run.slam.landmarks()
    known = [d for d in world.markers if mapped is not None and str(d.marker_id) in mapped.ids]
    if mapped is None or not known:
        return {"mapped": 0, "errors_m": {}}
    error = landmark_error(mapped.ids, mapped.positions, [str(d.marker_id) for d in known],
                           np.array([[d.x, d.y] for d in known]), map_to_world)
    sightings = dict(zip(mapped.ids, mapped.sightings.tolist(), strict=True))
    assert run.slam.landmark_constraints is not None, "a marker map comes from the grid-landmarks estimator"
    landmark_stats = run.slam.landmark_constraints.stats
    return {"mapped": len(mapped.ids), "errors_m": error.per_landmark_m, "mean_error_m": error.mean_m,
            "max_error_m": error.max_m, "not_in_world": error.extra,
            "sightings": {k: int(v) for k, v in sorted(sightings.items())},
            "sighting_time_offset_s": landmark_stats.time_offset_s,
            "revisited": landmark_stats.revisited}


def build_report(settings: dict[str, Any], recording: Recording, run: SlamRun, score: MarkerScore, world: World,
                 seconds: dict[str, float], plain: SlamRun | None = None) -> dict[str, Any]:
    """Every figure of the run, computed from the log, the SLAM output and the simulator's truth.

    ``settings``: what the run simulated, as JSON values (``duration_s`` None: the whole route,
    which must be a loop); ``seconds``: wall-clock time of each stage (s), kept by reference so
    a stage timed after this call is in the report too. ``run`` is SLAM with the markers as
    landmarks when ``plain`` (the same log without them) is given: the report then has the marker
    map's error against the world file and the two trajectory errors side by side.
    """
    truth = recording.scans
    errors = score_trajectory(run.trajectory, run.odometry, truth)
    ate, odometry_ate, rpe = errors.ate, errors.odometry_ate, errors.rpe
    walls = map_wall_distances(run.grid, world, np.array(ate.alignment_xyt))
    with LogReader(recording.log) as reader:
        info = reader.info()
    expected = sorted(score.in_view)
    detected_rows = score.summary(world)
    detected = {row["id"] for row in detected_rows if row["frames_detected"] > row["false_detections"]}
    in_view_pairs = sum(score.in_view.values())
    stats = run.slam.stats
    plain_ate = score_trajectory(plain.trajectory, plain.odometry, truth).ate if plain is not None else None
    markers = marker_map(run, world, ate.alignment_xyt)
    check = run.slam.check_map()
    report: dict[str, Any] = {
        "ate_rmse_m": ate.rmse_m,
        "ate_rmse_without_markers_m": plain_ate.rmse_m if plain_ate is not None else None,
        "marker_map": markers,
        "path_length_m": path_length(truth.poses),
        "markers_expected": expected,
        "markers_detected": detected_rows,
        "checks": {
            f"ate_rmse_m <= {ATE_LIMIT_M}": ate.rmse_m <= ATE_LIMIT_M,
            **(marker_checks(markers, ate.rmse_m, plain_ate.rmse_m) if plain_ate is not None else {}),
            "every marker in view detected": set(expected) <= detected,
            "no false marker ids": all(row["false_detections"] == 0 for row in detected_rows),
            "every logged scan and frame has ground truth": not any(recording.unmatched.values()),
            "the map passes its self-check": check.passed,  # None: not checked (nothing to compare)
            **({f"a loop of at least {LOOP_MIN_M:.0f} m": path_length(truth.poses) >= LOOP_MIN_M
                and float(np.hypot(*(truth.poses[-1, :2] - truth.poses[0, :2]))) < 1.0}
               if settings["duration_s"] is None else {}),
        },
        "trajectory": {
            "scans": stats.scans, "keyframes": stats.keyframes, "matched": stats.matched,
            "odometry_only": stats.odometry_only, "loop_closures": stats.loop_closures,
            "ate": asdict(ate), "odometry_ate": asdict(odometry_ate),
            "rpe": asdict(rpe) if rpe is not None else None,
            "estimated_path_length_m": path_length(run.trajectory.poses),
            "odometry_path_length_m": path_length(run.odometry.poses),
            "start_to_end_m": float(np.hypot(*(truth.poses[-1, :2] - truth.poses[0, :2]))) if len(truth) else 0.0,
        },
        "map_check": map_check_report(check, run.slam.keyframe_stamps(), info.start_ns or 0),
        "map": {"resolution_m": float(run.grid.resolution), "width": run.grid.width, "height": run.grid.height,
                "occupied_cells": int(walls.size), "wall_distance_m": _stats(walls),
                "occupied_within_0.1_m_of_a_wall": float(np.mean(walls <= 0.1)) if walls.size else 0.0},
        "markers": {"frames": score.frames, "frames_without_truth": score.unmatched,
                    "in_view": {str(k): v for k, v in sorted(score.in_view.items())},
                    "in_view_detected": in_view_pairs - len(score.missed), "in_view_total": in_view_pairs,
                    "detected_ids": sorted({s.id for s in score.sightings}),
                    "detected_beyond_view": sorted({s.id for s in score.sightings if s.in_image and not s.in_view}),
                    "in_world": len(world.markers)},
        "timing": {"scan_stamp_error_ms": _stats((truth.stamps_ns - recording.scan_true_ns) / 1e6),
                   "frame_stamp_latency_ms": _stats((recording.frames.stamps_ns - recording.frame_true_ns) / 1e6)},
        "drivers": driver_diagnostics(recording.log),
        "log": {"file": recording.log.name, "size_bytes": recording.log.stat().st_size, "duration_s": info.duration_s,
                "topics": {t: i.count for t, i in sorted(info.topics.items())}},
        "log_damage": damage_dict(info.damage),
        "ground_truth_unmatched": recording.unmatched,
        "robot_time_s": recording.robot_time_s,
        "cpu_s": recording.cpu_s,
        "emulator_late_ms": recording.emulator_late_ms,
        "starved": starved(recording),
        "load_average": list(os.getloadavg()),
        "seconds": seconds,
        "settings": settings,
        "slam_config": "defaults (trundle.fusion.slam.config.SlamConfig)",
    }
    return report


def marker_checks(markers: dict[str, Any], ate_m: float, plain_ate_m: float) -> dict[str, bool]:
    """The acceptance checks of the markers as landmarks: every marker mapped (each marker the daemon
    placed, i.e. seen large enough in the image) lies within ``MARKER_MAP_LIMIT_M`` of the world file,
    and SLAM with them is no worse than without (by more than ``NO_WORSE_M``)."""
    errors = markers["errors_m"]
    return {f"every marker mapped within {MARKER_MAP_LIMIT_M * 100:.0f} cm":
            bool(errors) and max(errors.values()) <= MARKER_MAP_LIMIT_M,
            "SLAM ATE with markers no worse than without": ate_m <= plain_ate_m + NO_WORSE_M}


def partial_run(report: dict[str, Any]) -> str:
    """What a shortened run (``--duration``) left unjudged ("" for the whole route)."""
    if report["settings"]["duration_s"] is None:
        return ""
    return (f"This run covered {report['robot_time_s']:.0f} s ({report['path_length_m']:.1f} m) of the route, not all "
            f"of it: {len(report['markers_expected'])} of the world's {report['markers']['in_world']} markers came "
            "into view and no loop was driven, so the checks judge only that much (run without --duration for "
            "the whole route and its loop check).")


def markers_seen(report: dict[str, Any]) -> str:
    """The markers in view and detected, in words: ``In view: 96; detected: 3, 96 (3 also ...)``."""
    rows = report["markers_detected"]
    detected = [row["id"] for row in rows if row["frames_detected"] > row["false_detections"]]
    false = [row["id"] for row in rows if row["false_detections"]]
    beyond = report["markers"]["detected_beyond_view"]
    return (f"In view: {', '.join(map(str, report['markers_expected'])) or 'none'}; detected: "
            f"{', '.join(map(str, detected)) or 'none'}"
            + (f" ({', '.join(map(str, beyond))} also where {'it was' if len(beyond) == 1 else 'they were'} in the "
               "image but smaller or more oblique than in view: true detections beyond what is required)"
               if beyond else "")
            + (f"; false detections of {', '.join(map(str, false))}" if false else ""))


def report_markdown(report: dict[str, Any]) -> str:
    """``report.md``: the report's figures for a reader, with the pictures and files."""
    tr, mp, mk = report["trajectory"], report["map"], report["markers"]
    scan_ms, frame_ms = report["timing"]["scan_stamp_error_ms"], report["timing"]["frame_stamp_latency_ms"]
    ate, odo = tr["ate"], tr["odometry_ate"]
    checks = "\n".join(f"- {verdict(ok)}: {name}" for name, ok in report["checks"].items())
    warning = []
    if report["starved"]:
        late = max(report["emulator_late_ms"][name] for name in report["starved"])
        warning = [f"**Warning**: the machine was too busy for real time (load average "
                   f"{report['load_average'][1]:.1f}): the {', '.join(report['starved'])} emulator(s) fell up to "
                   f"{late:.0f} ms behind, which the drivers see as late or bunched stamps; odometry and SLAM "
                   "suffer from it.", ""]
    lines = [
        "# trundle demo",
        "",
        *warning,
        f"The simulated robot drove {report['path_length_m']:.1f} m of the office route in "
        f"{report['robot_time_s']:.0f} s of robot time. The onboard daemon (`trundle daemon --config robot.toml`) "
        f"recorded its laser, wheel encoders and camera from the device emulators into `{report['log']['file']}` "
        f"({report['log']['size_bytes'] / 1e6:.1f} MB, {report['log']['duration_s']:.1f} s). The log was then replayed "
        "through SLAM and marker detection, and everything is scored against the simulator's ground truth.",
        "",
        checks,
        "",
        *([partial_run(report), ""] if partial_run(report) else []),
        "## Trajectory and map",
        "",
        "![trajectory](trajectory.png)",
        "",
        "| figure | value |",
        "|---|---|",
        f"| SLAM trajectory error, ATE RMSE (mean, max) | {ate['rmse_m'] * 100:.1f} cm ({ate['mean_m'] * 100:.1f}, "
        f"{ate['max_m'] * 100:.1f} cm); heading RMSE {ate['rotation_rmse_deg']:.2f} deg |",
        f"| wheel odometry alone, ATE RMSE (max) | {odo['rmse_m'] * 100:.1f} cm ({odo['max_m'] * 100:.1f} cm); "
        f"heading RMSE {odo['rotation_rmse_deg']:.2f} deg |",
    ]
    if report["ate_rmse_without_markers_m"] is not None:
        lines.append(
            f"| SLAM without the markers as landmarks, ATE RMSE | {report['ate_rmse_without_markers_m'] * 100:.1f} cm |"
        )
    if report["marker_map"]["errors_m"]:
        mm = report["marker_map"]
        each = ", ".join(f"{k}: {v * 100:.1f}" for k, v in sorted(mm["errors_m"].items(), key=lambda kv: int(kv[0])))
        lines.append(
            f"| marker map against the world file (mean, max; per id, cm) | {mm['mean_error_m'] * 100:.1f} cm, "
            f"{mm['max_error_m'] * 100:.1f} cm; {each} |"
        )
    if tr["rpe"]:
        rpe = tr["rpe"]
        lines.append(f"| SLAM relative error over {rpe['step']} scans (RMSE) | "
                     f"{rpe['translation_rmse_m'] * 100:.1f} cm, {rpe['rotation_rmse_deg']:.2f} deg |")
    lines += [
        f"| path length: ground truth, SLAM, odometry | {report['path_length_m']:.2f} m, "
        f"{tr['estimated_path_length_m']:.2f} m, {tr['odometry_path_length_m']:.2f} m |",
        f"| scans, keyframes, loop closures | {tr['scans']}, {tr['keyframes']}, {tr['loop_closures']} |",
        f"| map | {mp['width']} x {mp['height']} cells of {mp['resolution_m'] * 100:.0f} cm; "
        f"{mp['occupied_within_0.1_m_of_a_wall'] * 100:.1f} % of {mp['occupied_cells']} occupied cells within 10 cm "
        f"of a wall of the world |",
        f"| laser stamp error (median, p95) | {scan_ms.get('median', math.nan):.1f} ms, "
        f"{scan_ms.get('p95', math.nan):.1f} ms |",
        f"| camera frame latency (median, p95) | {frame_ms.get('median', math.nan):.1f} ms, "
        f"{frame_ms.get('p95', math.nan):.1f} ms |",
        "",
        "Map: `map.png`, and `map.pgm` + `map.yaml` as ROS map_server reads them.",
        "",
        "## Markers",
        "",
        "![detections](camera_detections.png)",
        "",
        f"{mk['frames']} camera frames. A marker is *in view* in a frame when the simulator shows it facing the "
        f"camera within {MAX_INCIDENCE_DEG:.0f} deg, with sides of {MIN_SIDE_PX:.0f} px or more and unoccluded: "
        f"what the detector is held to. {markers_seen(report)}. Detected in {mk['in_view_detected']} of the "
        f"{mk['in_view_total']} (frame, marker) pairs in view.",
        "",
        "Per marker: *frames in view* (as above), *frames detected* (frames with a detection of its id, in view or "
        "not), *false* (detections of it in frames where it was not in the image at all), its distance from the "
        "camera and the detected pose's errors against the world file.",
        "",
        "| id | frames in view | frames detected | false | distance (m) | position error median / max "
        "| angle error median / max |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in report["markers_detected"]:
        if "position_error_m" in row:
            pos, ang, dist = row["position_error_m"], row["angle_error_deg"], row["distance_m"]
            errors = (f"{dist['min']:.1f}-{dist['max']:.1f} | {pos['median'] * 100:.1f} / {pos['max'] * 100:.1f} cm | "
                      f"{ang['median']:.1f} / {ang['max']:.1f} deg")
        else:
            errors = "- | - | -"
        lines.append(f"| {row['id']} | {row['frames_in_view']} | {row['frames_detected']} | {row['false_detections']} "
                     f"| {errors} |")
    lines += ["", "## Drivers (last diagnostics in the log)", "", "| component | level | counters |", "|---|---|---|"]
    for name, status in report["drivers"].items():
        counters = ", ".join(f"{k} {v}" for k, v in status["values"].items()
                             if isinstance(v, int) and not k.endswith("_bytes") and k != "clock_offset_ns")
        lines.append(f"| {name} | {status['level']} ({status['message']}) | {counters} |")
    lines += ["", "## Files", "",
              f"- `{report['log']['file']}`: the log. Foxglove: Open local file -> `{report['log']['file']}`",
              "- `robot.toml`, `camera.yaml`, `daemon.log`: the daemon's configuration, camera calibration and output",
              "- `map.png`, `map.pgm`, `map.yaml`: the SLAM map; `trajectory.png`: trajectories over the map",
              "- `trajectory.csv` (SLAM, map frame), `ground_truth.csv` (per scan) and `frames_ground_truth.csv` "
              "(per camera frame): `t_ns,x,y,theta`, ground truth in the world frame",
              "- `camera_detections.png`: the frame with the most markers in view, detections drawn",
              "- `report.json`: every figure above and more", ""]
    return "\n".join(lines)




def write_report(out: Path, report: dict[str, Any]) -> None:
    """Write ``report`` to ``out/report.json`` (strict JSON: a figure that is not a number is null)
    and, for a reader, ``out/report.md``; both replace the demo's earlier ones."""
    write_json(out / "report.json", report, indent=1, replace=True)
    write_text(out / "report.md", report_markdown(report), replace=True)


# ---------------------------------------------------------------------------------- pictures

def run_figure(grid: m.OccupancyGrid, truth: np.ndarray, estimate: np.ndarray, odometry: np.ndarray,
               loops: Sequence[tuple[np.ndarray, np.ndarray]],
               landmarks: tuple[list[str], np.ndarray, np.ndarray] | None = None) -> Figure:
    """The trajectory-over-map figure (map frame): ground truth (a wide pale band under the others,
    so the SLAM estimate over it leaves it visible), wheel odometry, SLAM estimate, loop closures
    and the mapped markers (landmarks with their 3-sigma ellipses), each named in the legend."""
    tracks = [Track(truth, "ground truth (simulator)", "tab:blue", 6.0, 0.45),
              Track(odometry, "wheel odometry", "tab:orange", 1.5),
              Track(estimate, "SLAM estimate", "tab:red", 1.5)]
    return trajectory_figure(grid, tracks, "demo: ground truth, wheel odometry and SLAM over the SLAM map",
                             loops=loops, landmarks=landmarks)


def plot_run(grid: m.OccupancyGrid, path: Path, truth: np.ndarray, estimate: np.ndarray, odometry: np.ndarray,
             loops: Sequence[tuple[np.ndarray, np.ndarray]],
             landmarks: tuple[list[str], np.ndarray, np.ndarray] | None = None) -> Path:
    """Write the demo's ``trajectory.png`` (:func:`run_figure`)."""
    return save_figure(run_figure(grid, truth, estimate, odometry, loops, landmarks), path, replace=True)


def draw_detections(log: Path, score: MarkerScore, frames: Trajectory, world: World, mount: Mount, path: Path
                    ) -> Path | None:
    """The frame with the most markers in view and detected, annotated: detected outlines and ids
    (green), each pose's axes, and where the world says each marker in view is (red, thin)."""
    if score.best_stamp_ns is None or score.camera_info is None:
        return None
    camera = camera_from_info(score.camera_info)
    with LogReader(log) as reader:
        images = (cast(m.CompressedImage | m.Image, i.msg) for i in reader.messages(topics=[IMAGE_TOPIC]))
        msg = next(image for image in images if image.stamp_ns == score.best_stamp_ns)
    image = decode_image(msg)
    image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    base, _ = poses_at(frames, np.array([msg.stamp_ns]), tolerance_ns=0)
    pose = camera_pose(base[0], mount)
    for decal, corners in CameraRenderer(world, camera).visible_decals(pose):
        if decal.kind == "marker":
            outline = np.round(corners).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(image, [outline], True, (0, 0, 255), 1, cv2.LINE_AA)
    k, d = score.camera_info.k, score.camera_info.d
    for s in (s for s in score.sightings if s.stamp_ns == msg.stamp_ns):
        corners = s.corners.reshape(1, 4, 2).astype(np.float32)
        cv2.aruco.drawDetectedMarkers(image, [corners], np.array([[s.id]]), (0, 200, 0))
        if s.rvec is not None and s.tvec is not None:
            cv2.drawFrameAxes(image, k, d, s.rvec, s.tvec, 0.5 * world.marker(s.id).width, 2)
            text = (f"id {s.id}: {s.distance_m:.2f} m, error {100 * s.position_error_m:.1f} cm "
                    f"{s.angle_error_deg:.1f} deg")
            (width, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
            x, y = np.round(s.corners.min(axis=0)).astype(int)
            at = (int(np.clip(x - 40, 2, max(image.shape[1] - width - 4, 2))), int(max(14, y - 20)))
            cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return write_image(path, image, replace=True)
