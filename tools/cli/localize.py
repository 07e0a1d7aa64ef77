"""`trundle localize LOG --map DIR`: localise a log's scans on a saved map, from an unknown start.

DIR holds ``map.yaml`` + ``map.pgm`` as ``trundle slam`` (or ROS's map_saver) writes them; the map
is only read. Odometry comes from the log's ``Odometry`` messages or its wheel ``JointState``
(wheel model from the log's ``robot`` metadata or the config's ``[odometry]`` table, as for
``trundle slam``); without either, the localizer runs on the scans alone. The laser mount comes
from ``/tf_static`` or the config's ``[laser]`` table. Prints when the pose converged, each
kidnapping detected (and the recovery), and writes the tracked poses with ``-o``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from trundle.fusion.geometry import relative, scan_to_points, voxel_filter
from trundle.fusion.localization import TRACKING, Localizer, grid_from_map
from trundle.fusion.map_io import load_map, write_trajectory_csv
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.reader import LogReader
from trundle.tools.cli.slam import laser_pose, load_config, make_odometry
from trundle.tools.cli.progress import Progress


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("log", type=Path, help="MCAP log with LaserScan (and Odometry or wheel JointState)")
    p.add_argument("--map", type=Path, required=True, help="folder with map.yaml + map.pgm, or the map YAML itself")
    p.add_argument("--config", type=Path, help="TOML with [odometry] and [laser] tables (as for trundle slam)")
    p.add_argument("--scan-topic", default="/scan", help="LaserScan topic (default /scan)")
    p.add_argument("--max-range", type=float, default=30.0, help="ignore returns farther than this (m, default 30)")
    p.add_argument("--no-odometry", action="store_true", help="ignore the log's odometry (scans alone)")
    p.add_argument("-o", "--output", type=Path, help="write the tracked poses as t_ns,x,y,theta CSV")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    yaml_path = args.map / "map.yaml" if args.map.is_dir() else args.map
    grid = grid_from_map(load_map(yaml_path))
    reader = LogReader(args.log)
    info = reader.info()
    topic = info.topics.get(args.scan_topic)
    if topic is None or topic.ros_type != "sensor_msgs/msg/LaserScan":
        raise UserError(f"{args.log} has no LaserScan topic {args.scan_topic} "
                        f"(topics: {', '.join(sorted(info.topics)) or 'none'})")
    config = load_config(args.config)
    wheels = None if args.no_odometry else make_odometry(info, config)
    configured_mount = laser_pose(info, config)
    mounts: dict[str, np.ndarray] = {}
    localizer = Localizer(grid)
    odometry: np.ndarray | None = None
    previous_odometry: np.ndarray | None = None
    stamps, poses, scores = [], [], []
    progress = Progress("localize", max(info.duration_s, 1e-9))
    start_ns = info.start_ns or 0
    started = time.perf_counter()
    for item in reader.messages():
        msg = item.msg
        if isinstance(msg, m.TFMessage) and item.topic == "/tf_static":
            for t in msg.transforms:
                mounts[t.child_frame_id] = np.array([t.translation[0], t.translation[1], t.yaw])
        elif isinstance(msg, m.JointState) and wheels is not None:
            odom = wheels.update(msg)
            if odom is not None:
                odometry = np.array([odom.x, odom.y, odom.theta])
        elif isinstance(msg, m.Odometry) and wheels is None and not args.no_odometry:
            odometry = np.array([msg.x, msg.y, msg.theta])
        elif isinstance(msg, m.LaserScan) and item.topic == args.scan_topic:
            mount = np.asarray(configured_mount if configured_mount is not None
                               else mounts.get(msg.frame_id, np.zeros(3)), dtype=np.float64)
            points = voxel_filter(scan_to_points(msg, mount, range_max=min(args.max_range, msg.range_max)),
                                  grid.resolution)
            delta = None if odometry is None or previous_odometry is None else relative(previous_odometry, odometry)
            previous_odometry = odometry
            update = localizer.update(points, delta)
            if update.status == TRACKING:
                stamps.append(msg.stamp_ns)
                poses.append(update.pose)
                scores.append(update.score)
            progress.update((item.log_time_ns - start_ns) * 1e-9, f"{localizer.stats.scans} scans {update.status}")
    processing_s = time.perf_counter() - started
    progress.close()
    st = localizer.stats
    if st.scans == 0:
        raise UserError(f"{args.log}: no scans on {args.scan_topic}")
    if args.output is not None:
        write_trajectory_csv(args.output, np.array(stamps, np.int64), np.array(poses).reshape(-1, 3))
    report = {
        "log": str(args.log), "map": str(yaml_path), "scans": st.scans, "odometry": odometry is not None,
        "converged_at_scans": st.converged_at, "kidnaps_detected_at_scans": st.kidnaps_at,
        "false_alarms": st.false_alarms, "global_searches": st.global_searches, "tracked_scans": len(stamps),
        "final_status": localizer.status, "final_pose": [float(v) for v in poses[-1]] if poses else None,
        "match_score_tracking": {"mean": float(np.mean(scores)), "min": float(np.min(scores))} if scores else None,
        "duration_s": info.duration_s, "processing_s": processing_s,
        "real_time_factor": info.duration_s / processing_s if processing_s > 0 else None,
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    first = f"converged at scan {st.converged_at[0] + 1}" if st.converged_at else "never converged"
    print(f"{st.scans} scans ({'with' if report['odometry'] else 'without'} odometry): {first}; "
          f"{len(st.kidnaps_at)} kidnapping(s) detected at scan(s) {[k + 1 for k in st.kidnaps_at]}, "
          f"{len(st.converged_at) - 1 if st.converged_at else 0} recovery(ies); {st.global_searches} global search(es), "
          f"{st.false_alarms} false alarm(s); {len(stamps)} scans tracked"
          + (f", mean match score {report['match_score_tracking']['mean']:.2f}" if scores else ""))
    if poses:
        x, y, theta = poses[-1]
        print(f"final pose x {x:.3f} m, y {y:.3f} m, theta {np.degrees(theta):.1f} deg; "
              f"{processing_s:.1f} s for {info.duration_s:.1f} s of log")
    if args.output is not None:
        print(f"wrote {args.output}")
    return 0 if st.converged_at else 1
