"""The landmark-SLAM job: a feature map from a log's odometry and landmark sightings.

Used by the slam job (:mod:`trundle.tools.jobs.slam`) for ``--estimator ekf`` and for logs with
landmark sightings but no laser. Sightings come from the log's LandmarkList topic (``/landmarks``:
markers from the daemon or ``trundle perceive``, an importer's barcodes); a log without them but
with scans gets anonymous laser corners (:mod:`trundle.perception.scan_features`) per scan, the
EKF associating them by JCBB. Odometry: the log's ``Odometry``, or its wheel ``JointState`` through
the wheel model (as for the grid SLAM).

Outputs beside the grid SLAM's: ``trajectory.csv`` (one pose per odometry reading, map frame),
``landmarks.csv`` (``id,x,y,sx,sy``), ``map.pgm``/``map.yaml``/``map.png`` (the laser map at the
estimated poses when the log has scans, else an unknown map spanning the run), ``trajectory.png``
(path and landmarks with their 3-sigma ellipses), ``report.json`` and ``slam.mcap`` with ``/map``,
``/path``, ``/tf`` (map -> odom at every sighting) and ``/landmarks/map`` (visualization_msgs/
MarkerArray: a cylinder per landmark, its id as text).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.geometry import compose, inverse, scan_to_points
from trundle.fusion.mapping.map_io import save_map, write_landmarks_csv, write_trajectory_csv
from trundle.fusion.mapping.map_plot import Track, plot_trajectory
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.estimators import ESTIMATORS, GRID, EstimatorInputs, make_estimator
from trundle.fusion.slam.landmark_slam import LandmarkMap
from trundle.logs import messages as m
from trundle.logs.errors import DataError, UsageError, UserError
from trundle.logs.frames import BASE_FRAME, FrameTree
from trundle.logs.importers import write_log
from trundle.logs.outputs import write_json, writing_file, writing_folder
from trundle.logs.paths import output_folder
from trundle.logs.reader import LogInfo, LogReader, damage_dict
from trundle.logs.topics import LANDMARK_MAP_TOPIC, LANDMARK_TOPIC, MAP_TOPIC, ODOM_TOPIC, PATH_TOPIC, TF_TOPIC
from trundle.perception.scan_features import corner_observations
from trundle.tools.jobs.config import JobConfig, laser_pose, make_odometry, odometry_source, robot_config
from trundle.tools.jobs.progress import NoProgress, ProgressFactory

LANDMARK_TYPE = "trundle_msgs/msg/LandmarkList"
MAX_MAP_CELLS = 2000  # per side of the map picture of a run without scans
PATH_PERIOD_NS = 100_000_000  # /path in slam.mcap: a pose every 0.1 s (trajectory.csv has every reading)


def landmark_topic(info: LogInfo, config: JobConfig) -> str | None:
    """The LandmarkList topic to use: ``[landmarks] topic``, else ``/landmarks``, else the log's only one."""
    wanted = robot_config(config).landmarks.get("topic")
    found = sorted(t for t, i in info.topics.items() if i.ros_type == LANDMARK_TYPE)
    if wanted is not None:
        if wanted not in found:
            raise UserError(f"[landmarks] topic {wanted!r} is not a LandmarkList topic of the log "
                            f"(LandmarkList topics: {', '.join(found) or 'none'})")
        return wanted
    if LANDMARK_TOPIC in found:
        return LANDMARK_TOPIC
    return found[0] if len(found) == 1 else None


def landmark_slam_log(log: Path, output: Path, config: JobConfig = None, estimator: str = "landmark-graph",
                      progress: ProgressFactory = NoProgress) -> dict[str, Any]:
    """Landmark SLAM over ``log`` by the ``estimator`` (``ekf`` or ``landmark-graph``, see
    :mod:`trundle.fusion.slam.estimators`); outputs into ``output`` (see the module docstring).
    Returns the report (also ``report.json``; ``log_damage``: what the log's damage skipped, None when intact)."""
    config = robot_config(config)
    landmark_estimators = [name for name in ESTIMATORS if name not in GRID]
    if estimator not in landmark_estimators:
        raise UsageError(f"unknown landmark estimator {estimator!r} (choose {' or '.join(landmark_estimators)})")
    reader = LogReader(log)
    info = reader.info()
    topic = landmark_topic(info, config)
    configured_scans = SlamConfig.from_mapping(config.slam).scan.topic
    scans_info = info.topics.get(configured_scans)
    scan_topic = configured_scans if scans_info is not None and scans_info.ros_type == "sensor_msgs/msg/LaserScan" \
        else None
    if topic is None and scan_topic is None:
        raise UserError(f"{log} has neither landmark sightings (trundle_msgs/msg/LandmarkList) nor laser scans on "
                        f"{configured_scans} "
                        f"(topics: {', '.join(sorted(info.topics)) or 'none'})")
    wheels = make_odometry(info, config)
    if wheels is None and not any(i.ros_type == "nav_msgs/msg/Odometry" for i in info.topics.values()):
        raise DataError(f"{log} has no odometry (nav_msgs/Odometry or wheel JointState): "
                        "landmark SLAM predicts with it")
    features = topic is None  # anonymous laser corners stand in for sightings
    slam = make_estimator(estimator, EstimatorInputs(landmark_topic=topic, landmarks=config.landmarks))
    mount_config = laser_pose(info, config)
    frames = FrameTree()
    scans: list[tuple[int, np.ndarray, np.ndarray]] = []  # stamp, points (robot frame), mount
    odometry: list[tuple[int, np.ndarray]] = []
    sighting_stamps: list[int] = []
    output_folder(output, create=False)  # checked before the work, made once there is a result
    bar = progress("slam", max(info.duration_s, 1e-9))
    t0 = info.start_ns or 0
    started, cpu_started = time.perf_counter(), time.process_time()
    for item in reader.messages():
        msg: m.Message | None = item.msg
        if frames.add(item.topic, item.msg):
            continue
        if isinstance(msg, m.JointState) and wheels is not None:
            msg = wheels.update(msg)
            if msg is None:
                continue
        if isinstance(msg, m.Odometry):
            if wheels is None or item.topic != ODOM_TOPIC:
                slam.process(ODOM_TOPIC, msg)
                odometry.append((msg.stamp_ns, np.array([msg.x, msg.y, msg.theta])))
        elif isinstance(msg, m.LandmarkList) and item.topic == topic:
            slam.process(item.topic, msg)
            sighting_stamps.append(msg.stamp_ns)
        elif isinstance(msg, m.LaserScan) and item.topic == scan_topic:
            mount = (np.asarray(mount_config, dtype=np.float64) if mount_config is not None
                     else frames.mount(msg.frame_id, unknown_is_base=True))
            scans.append((msg.stamp_ns, scan_to_points(msg, mount), mount))
            if features:
                corners = m.LandmarkList(msg.stamp_ns, BASE_FRAME, tuple(corner_observations(msg, mount)))
                slam.process(LANDMARK_TOPIC, corners)
                sighting_stamps.append(msg.stamp_ns)
        if sighting_stamps and sighting_stamps[-1] == item.log_time_ns:
            bar.update((item.log_time_ns - t0) * 1e-9, f"{len(sighting_stamps)} sightings")
    slam.finish()
    processing_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    bar.close()
    stamps, poses = slam.trajectory()
    if len(stamps) == 0:
        raise UserError(f"{log}: no odometry reading before the end of the log")
    landmarks = slam.landmarks()
    assert landmarks is not None
    grid = _map(scans, stamps, poses, landmarks)
    end_ns = int(stamps.max())
    map_msg = grid.to_message(end_ns, "map")
    items: list[tuple[str, m.Message, int]] = [(TF_TOPIC, tf, t)
                                               for tf, t in _map_to_odom(stamps, poses, odometry, sighting_stamps)]
    kept = _every(stamps, PATH_PERIOD_NS)
    items += [(MAP_TOPIC, map_msg, end_ns), (PATH_TOPIC, m.Path(end_ns, "map", stamps[kept], poses[kept]), end_ns),
              (LANDMARK_MAP_TOPIC, landmark_markers(landmarks, end_ns), end_ns)]
    duration = info.duration_s
    report = {
        "log": str(log), "log_damage": damage_dict(reader.last_damage),
        "estimator": estimator, "sightings": "laser corners" if features else topic,
        "odometry_source": odometry_source(info, config, wheels) or "none",
        "duration_s": duration, "processing_s": processing_s, "cpu_s": cpu_s,
        "real_time_factor": duration / processing_s if processing_s > 0 else None,
        "landmarks": len(landmarks.ids), "landmark_sightings_used": int(landmarks.sightings.sum()),
        "poses": len(stamps), "scans": len(scans), **slam.report(),
        "path_length_m": float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T))) if len(poses) > 1 else 0.0,
        "map": {"resolution": float(map_msg.resolution), "width": map_msg.width, "height": map_msg.height},
    }
    with writing_folder(output):  # every file or, on any failure, none
        save_map(map_msg, output / "map", f"{estimator} map of {log.name}")
        write_trajectory_csv(output / "trajectory.csv", stamps, poses)
        write_landmarks(output / "landmarks.csv", landmarks)
        plot_trajectory(map_msg, output / "trajectory.png", [Track(poses, f"{estimator} trajectory", "tab:red")],
                        f"{estimator} trajectory and landmarks of {log.name}",
                        landmarks=(landmarks.ids, landmarks.positions, landmarks.covariances))
        with writing_file(output / "slam.mcap") as tmp:
            write_log(items, tmp, metadata={"command": "slam", "source": str(log), "estimator": estimator})
        write_json(output / "report.json", report)
    return report


def _map(scans: list[tuple[int, np.ndarray, np.ndarray]], stamps: np.ndarray, poses: np.ndarray,
         landmarks: LandmarkMap) -> LogOddsGrid:
    """The laser map at the trajectory's poses (nearest in time), or an unknown map spanning the run."""
    if scans:
        grid = LogOddsGrid(0.05)
        for stamp, points, mount in scans:
            k = int(np.clip(np.searchsorted(stamps, stamp), 0, len(stamps) - 1))
            if k > 0 and abs(stamps[k - 1] - stamp) < abs(stamps[k] - stamp):
                k -= 1
            pose = poses[k]
            c, s = math.cos(pose[2]), math.sin(pose[2])
            grid.insert_rays(compose(pose, mount)[:2], points @ np.array([[c, s], [-s, c]]) + pose[:2])
        return grid
    extent = np.vstack([poses[:, :2], landmarks.positions.reshape(-1, 2)])
    low, high = extent.min(axis=0) - 1.0, extent.max(axis=0) + 1.0
    grid = LogOddsGrid(max(0.05, float((high - low).max()) / MAX_MAP_CELLS), origin_xy=tuple(low), grow_cells=0)
    grid.ensure_contains(low, high)
    return grid


def _every(stamps: np.ndarray, period_ns: int) -> np.ndarray:
    """Indices of the stamps kept when keeping one at least ``period_ns`` after the previous kept one (and the last)."""
    kept, last = [], None
    for k, t in enumerate(stamps.tolist()):
        if last is None or t - last >= period_ns:
            kept.append(k)
            last = t
    if len(stamps) and kept[-1] != len(stamps) - 1:
        kept.append(len(stamps) - 1)
    return np.array(kept, np.int64)


def _map_to_odom(stamps: np.ndarray, poses: np.ndarray, odometry: list[tuple[int, np.ndarray]],
                 sighting_stamps: list[int]) -> list[tuple[m.TFMessage, int]]:
    """map -> odom at each sighting (from the trajectory's pose and the odometry at the same reading)."""
    if not odometry:
        return []
    odom_stamps = np.array([t for t, _ in odometry], np.int64)
    odom_poses = np.array([p for _, p in odometry])
    out = []
    for t in sighting_stamps:
        k = int(np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, len(stamps) - 1))
        j = int(np.clip(np.searchsorted(odom_stamps, stamps[k]), 0, len(odom_stamps) - 1))
        x, y, yaw = (float(v) for v in compose(poses[k], inverse(odom_poses[j])))
        out.append((m.TFMessage((m.TransformStamped.planar(int(t), "map", "odom", x, y, yaw),)), int(t)))
    return out


def write_landmarks(path: Path, landmarks: LandmarkMap, replace: bool = False) -> None:
    """``landmarks.csv``: id, map position and the standard deviations of x and y (m) (``replace``: in a
    folder the command owns)."""
    sigmas = np.sqrt(np.maximum(np.nan_to_num(np.diagonal(landmarks.covariances, axis1=1, axis2=2)), 0.0))
    write_landmarks_csv(path, landmarks.ids, landmarks.positions, sigmas.reshape(-1, 2), replace)


def landmark_markers(landmarks: LandmarkMap, stamp_ns: int) -> m.SceneMarkers:
    """The landmark map as visualization markers: a cylinder per landmark (diameter: twice its larger
    3-sigma half-axis, at least 10 cm) and its id as text above it."""
    markers = []
    rows = zip(landmarks.ids, landmarks.positions, landmarks.covariances, strict=True)
    for k, (name, (x, y), cov) in enumerate(rows):
        sigma = math.sqrt(max(float(np.nan_to_num(np.linalg.eigvalsh(cov)).max()), 0.0))
        width = max(6.0 * sigma, 0.1)
        markers.append(m.SceneMarker(stamp_ns, "map", "landmarks", k, m.SceneMarker.CYLINDER, float(x), float(y), 0.25,
                                     0.0, np.array((width, width, 0.5)), (0.8, 0.1, 0.8, 0.8)))
        markers.append(m.SceneMarker(stamp_ns, "map", "landmark_ids", k, m.SceneMarker.TEXT_VIEW_FACING, float(x),
                                     float(y), 0.7, 0.0, np.array((0.3, 0.3, 0.3)), (1.0, 1.0, 1.0, 1.0), str(name)))
    return m.SceneMarkers(tuple(markers))
