"""The localize job: localise one log's scans on a saved map, from an unknown start.

The map (``map.yaml`` + ``map.pgm`` as ``trundle slam`` or ROS's map_saver writes them) is only
read. Odometry comes from the log's ``Odometry`` messages or its wheel ``JointState`` (wheel model
from the log's ``robot`` metadata or the config's ``[odometry]`` table, as for the slam job);
without either, the localizer runs on the scans alone. The laser mount comes from the config's
``[laser]`` table, else the log's ``/tf_static`` chained to base_link (:mod:`trundle.logs.frames`).
When the map folder has ``landmarks.csv`` (``trundle slam`` of a log with markers) and the log has
landmark sightings (``/landmarks``), sightings of two mapped landmarks give absolute fixes
(:mod:`trundle.fusion.localization.landmark_localization`): global localisation at once, and kidnap
recovery when the fixes keep disagreeing with the track.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.geometry import compose, relative, scan_to_points, voxel_filter
from trundle.fusion.localization.grid_localization import TRACKING, Localizer, grid_from_map
from trundle.fusion.localization.landmark_localization import LandmarkFixer
from trundle.fusion.mapping.map_io import load_map, read_landmarks_csv, write_trajectory_csv
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.frames import FrameTree
from trundle.logs.reader import LogReader, damage_dict
from trundle.logs.topics import LANDMARK_TOPIC, SCAN_TOPIC
from trundle.tools.jobs.config import JobConfig, laser_pose, make_odometry, robot_config
from trundle.tools.jobs.progress import NoProgress, ProgressFactory


def _landmark_fixer(map_path: Path, info) -> LandmarkFixer | None:
    """Landmark fixes when the map folder has ``landmarks.csv`` and the log has sightings on ``/landmarks``."""
    folder = map_path if map_path.is_dir() else map_path.parent
    if not (folder / "landmarks.csv").is_file() or LANDMARK_TOPIC not in info.topics:
        return None
    ids, positions, sigmas = read_landmarks_csv(folder / "landmarks.csv")
    return LandmarkFixer(ids, positions, sigmas) if ids else None


def localize_log(log: Path, map_path: Path, config: JobConfig = None, scan_topic: str = SCAN_TOPIC,
                 max_range_m: float = 30.0, use_odometry: bool = True, trajectory_csv: Path | None = None,
                 progress: ProgressFactory = NoProgress) -> dict[str, Any]:
    """Localise the scans of ``log`` on the map at ``map_path`` (a folder with ``map.yaml``, or the YAML).

    ``config`` is the robot config (``[odometry]``, ``[laser]`` tables); returns farther than
    ``max_range_m`` (m) are ignored; ``use_odometry=False`` ignores the log's odometry (scans
    alone). The tracked poses go to ``trajectory_csv`` (``t_ns,x,y,theta``) if given; ``progress``
    shows the log seconds done. Returns the report: what the log's damage skipped (``log_damage``, None
    when intact), scans at which the pose converged and
    kidnappings were detected (0-based), searches, false alarms, final pose (m, m, rad), match
    scores and timings (s).
    """
    config = robot_config(config)
    yaml_path = map_path / "map.yaml" if map_path.is_dir() else map_path
    grid = grid_from_map(load_map(yaml_path))
    reader = LogReader(log)
    info = reader.info()
    info.require(scan_topic, "sensor_msgs/msg/LaserScan")
    wheels = make_odometry(info, config) if use_odometry else None
    fixer = _landmark_fixer(map_path, info)
    configured_mount = laser_pose(info, config)
    frames = FrameTree()
    localizer = Localizer(grid)
    odometry: np.ndarray | None = None
    previous_odometry: np.ndarray | None = None
    stamps, poses, scores = [], [], []
    fixes = 0
    bar = progress("localize", max(info.duration_s, 1e-9))
    start_ns = info.start_ns or 0
    started = time.perf_counter()
    for item in reader.messages():
        msg = item.msg
        if frames.add(item.topic, msg):
            continue
        if isinstance(msg, m.JointState) and wheels is not None:
            odom = wheels.update(msg)
            if odom is not None:
                odometry = np.array([odom.x, odom.y, odom.theta])
                if fixer is not None:
                    fixer.odometry(odometry)
        elif isinstance(msg, m.Odometry) and wheels is None and use_odometry:
            odometry = np.array([msg.x, msg.y, msg.theta])
            if fixer is not None:
                fixer.odometry(odometry)
        elif isinstance(msg, m.LandmarkList) and fixer is not None and item.topic == LANDMARK_TOPIC:
            fix = fixer.add(msg)
            if fix is not None and odometry is not None and previous_odometry is not None:
                # the fix is of the robot now; the localizer's pose is that of the last scan
                back = relative(odometry, previous_odometry)
                fixes += 1
                localizer.fix(compose(fix.pose, back), fix.covariance)
        elif isinstance(msg, m.LaserScan) and item.topic == scan_topic:
            mount = (np.asarray(configured_mount, dtype=np.float64) if configured_mount is not None
                     else frames.mount(msg.frame_id, unknown_is_base=True))
            points = voxel_filter(scan_to_points(msg, mount, range_max=min(max_range_m, msg.range_max)),
                                  grid.resolution)
            delta = None if odometry is None or previous_odometry is None else relative(previous_odometry, odometry)
            previous_odometry = odometry
            update = localizer.update(points, delta)
            if update.status == TRACKING:
                stamps.append(msg.stamp_ns)
                poses.append(update.pose)
                scores.append(update.score)
            bar.update((item.log_time_ns - start_ns) * 1e-9, f"{localizer.stats.scans} scans {update.status}")
    processing_s = time.perf_counter() - started
    bar.close()
    st = localizer.stats
    if st.scans == 0:
        raise UserError(f"{log}: no scans on {scan_topic}")
    if trajectory_csv is not None:
        write_trajectory_csv(trajectory_csv, np.array(stamps, np.int64), np.array(poses).reshape(-1, 3))
    return {
        "log": str(log), "log_damage": damage_dict(reader.last_damage), "map": str(yaml_path),
        "scans": st.scans, "odometry": odometry is not None,
        "converged_at_scans": st.converged_at, "kidnaps_detected_at_scans": st.kidnaps_at,
        "false_alarms": st.false_alarms, "global_searches": st.global_searches, "tracked_scans": len(stamps),
        "landmark_fixes": fixes, "landmark_fixes_rejected": st.fixes_rejected,
        "landmarks_in_map": len(fixer.map) if fixer is not None else 0,
        "final_status": localizer.status, "final_pose": [float(v) for v in poses[-1]] if poses else None,
        "match_score_tracking": {"mean": float(np.mean(scores)), "min": float(np.min(scores))} if scores else None,
        "duration_s": info.duration_s, "processing_s": processing_s,
        "real_time_factor": info.duration_s / processing_s if processing_s > 0 else None,
    }
