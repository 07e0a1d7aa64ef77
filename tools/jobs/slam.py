"""The slam job: map one log; write map files, trajectory, report and an MCAP into a folder.

Outputs: ``map.pgm`` + ``map.yaml`` (map_server), ``map.png``, ``trajectory.png`` (the path and
loop closures over the map, the stretches that fail the map self-check in magenta), ``scans.png``
(every keyframe's scan endpoints at its optimised pose: doubled walls show here, not in the
occupancy map), ``trajectory.csv`` (``t_ns,x,y,theta`` of every scan in the map frame),
``report.json`` (with ``map_check``, see :mod:`trundle.fusion.mapping.map_check`), ``session/`` (what
``--continue`` needs to map on from here, :mod:`trundle.tools.jobs.sessions`) and ``slam.mcap``
with ``/map``, ``/tf`` (map -> odom per scan) and ``/path``. A log with landmark sightings
(``/landmarks``) puts them into the pose graph (the ``grid-landmarks`` estimator of
:mod:`trundle.fusion.slam.estimators`) and adds ``landmarks.csv`` (``id,x,y,sx,sy``), the landmarks
on ``trajectory.png`` and ``/landmarks/map`` in ``slam.mcap``. The wheel model comes from the
config's ``[odometry]`` table or the log's metadata (see
:func:`trundle.tools.jobs.config.make_odometry`); ``[slam]`` holds
:class:`trundle.fusion.slam.config.SlamConfig`; ``[laser]`` (``x_m``, ``y_m``, ``yaw_rad``) overrides
the laser mount of the log's ``/tf_static``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.geometry import transform_points
from trundle.fusion.mapping.map_check import MapCheck
from trundle.fusion.mapping.map_io import save_map, write_trajectory_csv
from trundle.fusion.mapping.map_plot import Track, plot_scans, plot_sessions, plot_trajectory
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.estimators import GRID, EstimatorInputs, make_estimator, resolve
from trundle.fusion.slam.grid_slam import Slam
from trundle.fusion.slam.sessions import SessionGraph, build_grid, check_graph, continue_map, from_slam
from trundle.fusion.slam.stats import summary
from trundle.logs import messages as m
from trundle.logs.errors import UsageError, UserError
from trundle.logs.importers import write_log
from trundle.logs.outputs import write_json, writing_file, writing_folder
from trundle.logs.paths import output_folder
from trundle.logs.reader import LogInfo, LogReader, damage_dict
from trundle.logs.topics import LANDMARK_MAP_TOPIC, MAP_TOPIC, PATH_TOPIC, TF_TOPIC
from trundle.tools.config.robot import RobotConfig
from trundle.tools.jobs.config import JobConfig, laser_pose, make_odometry, odometry_source, robot_config
from trundle.tools.jobs.landmark_slam import landmark_markers, landmark_slam_log, landmark_topic, write_landmarks
from trundle.tools.jobs.progress import NoProgress, ProgressFactory
from trundle.tools.jobs.sessions import check_config, check_laser, read_bundle, write_bundle


def map_check_report(check: MapCheck, stamps_ns: np.ndarray, t0_ns: int) -> dict[str, Any]:
    """The map self-check for report.json: its ``status`` (passed, failed or not checked: nothing to
    compare, ``passed`` and ``consistency`` None then), the figure, and each inconsistent stretch with
    its times (s after the log's start)."""
    stretches = [{"first_keyframe": a, "last_keyframe": b, "start_s": (int(stamps_ns[a]) - t0_ns) * 1e-9,
                  "end_s": (int(stamps_ns[b]) - t0_ns) * 1e-9,
                  "consistency": float(np.nanmean(check.keyframe_consistency[a:b + 1]))} for a, b in check.stretches]
    return {"status": check.status, "passed": check.passed, "consistency": check.consistency,
            "compared_keyframes": check.compared_keyframes, "inconsistent_keyframes": check.inconsistent_keyframes,
            "min_stretch": check.min_stretch, "stretches": stretches}


def grid_estimator(info: LogInfo, config: RobotConfig, name: str = "grid", landmark_topic: str | None = None,
                   local_only: bool = False) -> Slam:
    """The grid SLAM ``name`` (``grid`` or ``grid-landmarks``, sightings on ``landmark_topic``; None: the
    registry's default) for ``info``'s log, from the registry: the ``[slam]`` options (loop closure off
    with ``local_only``), the wheel model (:func:`make_odometry`) and the laser mount of ``config`` or the
    log. ``trundle slam`` and ``trundle replay`` build their SLAM here, so they run the same one."""
    slam_config = SlamConfig.from_mapping(config.slam)
    if local_only:
        slam_config = slam_config.replace("loop_closure", enabled=False)
    slam = make_estimator(name, EstimatorInputs(slam_config, make_odometry(info, config), laser_pose(info, config),
                                                landmark_topic))
    assert isinstance(slam, Slam)
    return slam


def replay_estimator(info: LogInfo, config: JobConfig, markers: bool = False) -> Slam:
    """The grid SLAM ``trundle slam`` runs on ``info``'s log (with the log's landmark sightings in its pose
    graph); with ``markers``, the one taking the sightings of the online marker detection (``/landmarks``)
    instead. ``trundle replay --slam`` runs it."""
    config = robot_config(config)
    topic = None if markers else landmark_topic(info, config)
    return grid_estimator(info, config, "grid-landmarks" if markers or topic is not None else "grid", topic)


def slam_log(log: Path, output: Path, config: JobConfig = None, local_only: bool = False,
             progress: ProgressFactory = NoProgress, estimator: str | None = None,
             continue_from: Path | None = None, freeze: bool = False, allow_new_area: bool = False) -> dict[str, Any]:
    """Run SLAM over ``log`` and write its outputs into the folder ``output`` (created; an existing
    one must be empty, so a result is never overwritten).

    ``config`` is the robot config (``[slam]``, ``[odometry]``, ``[laser]``, ``[landmarks]`` tables;
    none by default); ``local_only`` turns loop closure off whatever the config says. ``progress``
    shows the log seconds done. ``estimator``: a name of :mod:`trundle.fusion.slam.estimators` (``grid``,
    ``grid-landmarks``, ``ekf``, ``landmark-graph``; the last two by :mod:`trundle.tools.jobs.landmark_slam`),
    or ``graph`` / None: the pose graph that fits the log (the grid SLAM, with the log's landmark
    sightings as constraints; a log with sightings but no scans gets the landmark graph).
    ``continue_from``: the output folder of an earlier run (its session bundle,
    :mod:`trundle.tools.jobs.sessions`) whose map this log continues (:func:`trundle.tools.jobs.sessions.continue_log`
    writes the outputs then; ``freeze``, ``allow_new_area`` as there).
    Returns the report (also written as ``report.json``): what the log's damage skipped (``log_damage``,
    None for an intact log; see :class:`trundle.logs.reader.LogDamage`), the odometry it used (``odometry_source``:
    wheel encoders, odometry messages or ``none``), counts, timings (s), residuals (m), path length
    (m), map size and the SLAM options used.
    """
    config = robot_config(config)
    old = None if continue_from is None else read_bundle(continue_from)  # a bad MAPDIR is said before any work
    reader = LogReader(log)
    info = reader.info()
    slam_config = SlamConfig.from_mapping(config.slam)
    scan_info = info.topics.get(slam_config.scan.topic)
    has_scans = scan_info is not None and scan_info.ros_type == "sensor_msgs/msg/LaserScan"
    topic = landmark_topic(info, config)
    name = resolve(estimator, has_scans, topic is not None)
    if name not in GRID:
        if old is not None:
            raise UsageError(f"--continue needs a grid SLAM estimator (grid, grid-landmarks), not {name}")
        return landmark_slam_log(log, output, config, name, progress)
    if name == "grid-landmarks" and topic is None:
        raise UsageError(f"{log}: the grid-landmarks estimator needs landmark sightings (a LandmarkList topic)")
    info.require(slam_config.scan.topic, "sensor_msgs/msg/LaserScan")
    slam = grid_estimator(info, config, name, topic, local_only)
    slam_config = slam.config
    if old is not None and continue_from is not None:
        check_config(continue_from, old[1], slam_config)
    odometry = odometry_source(info, config, slam.wheels) or "none"
    output_folder(output, create=False)  # checked before the work, made once there is a result

    bar = progress("slam", max(info.duration_s, 1e-9))
    t0 = info.start_ns or 0
    transforms: list[tuple[str, m.Message, int]] = []
    started, cpu_started = time.perf_counter(), time.process_time()
    for item in reader.messages():
        result = slam.process(item.topic, item.msg)
        if result is not None:
            transforms.append((TF_TOPIC, m.TFMessage((m.TransformStamped.planar(
                result.stamp_ns, "map", "odom", *(float(v) for v in slam.map_to_odom)),)), item.log_time_ns))
            bar.update((item.log_time_ns - t0) * 1e-9, f"{slam.stats.scans} scans {slam.stats.loop_closures} loops")
    slam.finish()
    grid = slam.build_map()
    processing_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    bar.close()
    if slam.stats.scans == 0:
        raise UserError(f"{log}: no scans on {slam_config.scan.topic}")
    landmarks = slam.landmarks()
    if old is not None and continue_from is not None:
        laser = check_laser(continue_from, old[2], slam.keyframe_scans_taken[0], slam.keyframe_mounts[0],
                            allow_new_area)
        timing = {"duration_s": info.duration_s, "processing_s": processing_s, "cpu_s": cpu_s}
        return continue_log(log, continue_from, output, old, from_slam(slam, landmarks), slam_config,
                            {"log_damage": damage_dict(reader.last_damage), "odometry_source": odometry,
                             "other_laser": laser, **timing}, freeze, allow_new_area)

    stamps, poses = slam.trajectory()
    end_ns = int(stamps.max())
    map_msg = grid.to_message(end_ns, "map")
    keyframes = slam.keyframe_poses()
    loops = [(keyframes[i], keyframes[j]) for i, j in slam.loop_edges()]
    check = slam.check_map()
    drawn = None if landmarks is None else (landmarks.ids, landmarks.positions, landmarks.covariances)
    path_msg = m.Path(end_ns, "map", stamps, poses)
    extra: list[tuple[str, m.Message, int]] = (
        [] if landmarks is None else [(LANDMARK_MAP_TOPIC, landmark_markers(landmarks, end_ns), end_ns)])

    counts = slam.report()
    landmark_counts = counts.pop("landmarks", None)
    duration = info.duration_s
    report = {
        "log": str(log), "log_damage": damage_dict(reader.last_damage), "odometry_source": odometry,
        "duration_s": duration,
        "processing_s": processing_s, "cpu_s": cpu_s,
        "real_time_factor": duration / processing_s if processing_s > 0 else None,
        **counts,
        "scan_to_map_residual_m": summary(list(slam.map_residuals(grid))),
        "path_length_m": float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T))) if len(poses) > 1 else 0.0,
        "map": {"resolution": float(map_msg.resolution), "width": map_msg.width, "height": map_msg.height},
        "map_check": map_check_report(check, slam.keyframe_stamps(), t0),
        "config": slam_config.model_dump(),
    }
    if landmarks is not None:
        report["landmarks"] = {"topic": topic, "mapped": len(landmarks.ids), **landmark_counts}
    with writing_folder(output):  # every file or, on any failure, none
        save_map(map_msg, output / "map", f"SLAM map of {log.name}")
        write_trajectory_csv(output / "trajectory.csv", stamps, poses)
        plot_trajectory(map_msg, output / "trajectory.png", [Track(poses, "SLAM trajectory", "tab:red")],
                        f"SLAM trajectory of {log.name}", loops=loops,
                        highlights=[slam.keyframe_scans(a, b) for a, b in check.stretches], landmarks=drawn)
        plot_scans(map_msg, output / "scans.png", slam.keyframe_endpoints(), check.keyframe_consistency < 0.5,
                   f"every keyframe's scan at its pose: {log.name}")
        with writing_file(output / "slam.mcap") as tmp:
            write_log(transforms + [(MAP_TOPIC, map_msg, end_ns), (PATH_TOPIC, path_msg, end_ns)] + extra, tmp,
                      metadata={"command": "slam", "source": str(log)})
        if landmarks is not None:
            write_landmarks(output / "landmarks.csv", landmarks)
        write_json(output / "report.json", report)
        write_bundle(output, from_slam(slam, landmarks), slam_config, [str(log)])
    return report


SESSION_COLOURS = ("tab:blue", "tab:red", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink",
                   "tab:olive", "tab:cyan", "tab:gray")


def continue_log(log: Path, mapdir: Path, output: Path, old: tuple[SessionGraph, SlamConfig, dict[str, Any]],
                 new: SessionGraph, config: SlamConfig, run: dict[str, Any], freeze: bool = False,
                 allow_new_area: bool = False) -> dict[str, Any]:
    """Continue the map of ``mapdir`` (its bundle ``old``) with ``new``, the session ``log`` was just mapped as
    (:func:`trundle.fusion.slam.sessions.continue_map`) and write the joint map into ``output``: ``map.pgm`` +
    ``map.yaml`` + ``map.png``, ``sessions.png`` (each session's scan endpoints in its own colour),
    ``trajectory.png`` (each session's path in its own colour, cross-session closures as lines),
    ``trajectory.csv`` (``t_ns,x,y,theta,session``), ``report.json`` (where the session was placed and how
    sure, the cross-session closures accepted and rejected, the map check), ``slam.mcap`` (``/map``,
    ``/path``) and ``session/``. A log that cannot be placed is one UserError line (unless ``allow_new_area``:
    a disconnected new part of the map). ``run``: the report's figures of the run of ``log``."""
    graph, _, meta = old
    started, cpu_started = time.perf_counter(), time.process_time()
    continued = continue_map(graph, new, config, freeze, allow_new_area)
    if continued is None:
        raise UserError(f"{log}: cannot be placed in the map of {mapdir} (no place in it where two of its submaps "
                        "agree and its scans close loops; another building or too little overlap); "
                        "--allow-new-area adds it as a disconnected part")
    joined = continued.graph
    grid = build_grid(joined, config)
    check = check_graph(joined, config)
    continue_s, continue_cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    stamps, poses, sessions = joined.trajectory()
    order = np.argsort(stamps, kind="stable")
    end_ns = int(stamps.max())
    map_msg = grid.to_message(end_ns, "map")
    logs = [str(s.get("log")) for s in meta["sessions"]] + [str(log)]
    placement = continued.placement
    report = {
        "log": str(log), "continued": str(mapdir), "sessions": logs, **run,
        "continue_s": continue_s, "continue_cpu_s": continue_cpu_s,
        "placement": {"placed": placement is not None, "new_area": placement is None,
                      "first_pose": [float(v) for v in continued.first_pose],
                      **({} if placement is None else placement.as_dict())},
        "cross_session_closures": continued.closures.as_dict(),
        "freeze": freeze,
        "keyframes": len(joined), "scans": int(stamps.size),
        "map": {"resolution": float(map_msg.resolution), "width": map_msg.width, "height": map_msg.height},
        "map_check": map_check_report(check, joined.stamps, int(joined.stamps.min())),
        "config": config.model_dump(),
    }
    if joined.landmarks is not None:
        report["landmarks"] = {"mapped": len(joined.landmarks.ids)}
    tracks = [Track(poses[sessions == k], f"session {k}: {Path(name).name}", SESSION_COLOURS[k % len(SESSION_COLOURS)])
              for k, name in enumerate(logs)]
    cross = [(joined.poses[i], joined.poses[j]) for i, j in joined.edges[0][joined.cross_edges()]]
    drawn = (None if joined.landmarks is None
             else (joined.landmarks.ids, joined.landmarks.positions, joined.landmarks.covariances))
    with writing_folder(output):  # every file or, on any failure, none
        save_map(map_msg, output / "map", f"map of {len(logs)} sessions, the last {log.name}")
        write_trajectory_csv(output / "trajectory.csv", stamps[order], poses[order], sessions=sessions[order])
        plot_trajectory(map_msg, output / "trajectory.png", tracks, f"{len(logs)} sessions, each in its colour",
                        loops=cross, landmarks=drawn)
        endpoints = [transform_points(p, q) for p, q in zip(joined.poses, joined.points, strict=True)]
        plot_sessions(map_msg, output / "sessions.png",
                      [[e for e, k in zip(endpoints, joined.session, strict=True) if k == s] for s in range(len(logs))],
                      [t.label for t in tracks], [t.colour for t in tracks], f"the map of {len(logs)} sessions")
        with writing_file(output / "slam.mcap") as tmp:
            write_log([(MAP_TOPIC, map_msg, end_ns), (PATH_TOPIC, m.Path(end_ns, "map", stamps[order], poses[order]),
                                                      end_ns)], tmp, metadata={"command": "slam", "source": str(log)})
        if joined.landmarks is not None:
            write_landmarks(output / "landmarks.csv", joined.landmarks)
        write_json(output / "report.json", report)
        write_bundle(output, joined, config, logs)
    return report
