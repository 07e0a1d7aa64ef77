"""`trundle slam LOG -o DIR [--config F]`: map a log; write map files, trajectory, report and an MCAP.

Outputs in DIR: ``map.pgm`` + ``map.yaml`` (map_server), ``map.png``, ``trajectory.png`` (the
path and loop closures over the map), ``trajectory.csv`` (``t_ns,x,y,theta`` of every scan in
the map frame), ``report.json`` and ``slam.mcap`` with ``/map``, ``/tf`` (map -> odom per scan)
and ``/path``. The wheel model comes from the config's ``[odometry]`` table (``wheel_radius_m``,
``track_m``, ``wheels = [left, right]``, ``wheel_variance_per_m``) or the log's metadata (see
:func:`make_odometry`); ``[slam]`` holds :class:`trundle.fusion.slam.SlamConfig`; ``[laser]`` (``x_m``,
``y_m``, ``yaw_rad``) overrides the laser mount of the log's ``/tf_static``.
"""

from __future__ import annotations

import argparse
import json
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.map_io import plot_trajectory, save_map, write_trajectory_csv
from trundle.fusion.odometry import DiffDriveOdometry, odometry_from_config
from trundle.fusion.slam import Slam, SlamConfig
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.importers import write_log
from trundle.logs.reader import LogInfo, LogReader
from trundle.tools.cli.progress import Progress

ODOMETRY_KEYS = {"wheel_radius_m", "track_m", "wheels", "wheel_variance_per_m"}
LASER_KEYS = {"x_m", "y_m", "yaw_rad"}


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", type=Path, help="MCAP log with LaserScan and JointState or Odometry")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (created)")
    p.add_argument("--config", type=Path, help="TOML with [slam], [odometry] and [laser] tables")
    p.add_argument("--no-loop-closure", action="store_true", help="local SLAM only (no pose-graph loops)")
    p.set_defaults(func=run)


def load_config(path: Path | None) -> dict[str, Any]:
    """The TOML config as a dict ({} without a path); unreadable or invalid files are a UserError."""
    if path is None:
        return {}
    if not path.is_file():
        raise UserError(f"no such config file: {path}")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path}: invalid TOML ({error})") from None


def _table(config: dict[str, Any], name: str, keys: set[str]) -> dict[str, Any]:
    table = config.get(name, {})
    if not isinstance(table, dict):
        raise UserError(f"[{name}] must be a table")
    unknown = set(table) - keys
    if unknown:
        raise UserError(f"unknown [{name}] option(s) {sorted(unknown)} (known: {sorted(keys)})")
    return table


def make_odometry(info: LogInfo, config: dict[str, Any]) -> DiffDriveOdometry | None:
    """Wheel odometry for a log with wheel joint states; None if it has none (or only ``Odometry``).

    The wheel model comes from the first of: the config's ``[odometry]`` table, the log's
    ``robot`` metadata (written by the importers), the ``[can]`` device table the recorder or
    daemon ran with (``devices`` metadata).
    """
    if not any(t.ros_type == "sensor_msgs/msg/JointState" for t in info.topics.values()):
        return None
    metadata = info.metadata.get("trundle", {})
    devices = json.loads(metadata.get("devices", "{}") or "{}")
    sources = [_table(config, "odometry", ODOMETRY_KEYS), json.loads(metadata.get("robot", "{}") or "{}"),
               next((d for d in devices.values() if isinstance(d, dict) and d.get("family") == "can"), {})]
    for source in sources:
        odometry = odometry_from_config(source) if source else None
        if odometry is not None:
            return odometry
    if any(t.ros_type == "nav_msgs/msg/Odometry" for t in info.topics.values()):
        return None
    raise UserError("the log has wheel joint states but no wheel model: give wheel_radius_m and track_m "
                    "in the [odometry] table of --config")


def laser_pose(info: LogInfo, config: dict[str, Any]) -> tuple[float, float, float] | None:
    """The laser mount: the ``[laser]`` table, else the log's ``robot`` metadata (``laser_x_m``,
    ``laser_y_m``, ``laser_yaw_rad``), else None (then the log's /tf_static, or the identity)."""
    table = _table(config, "laser", LASER_KEYS)
    if table:
        return (float(table.get("x_m", 0.0)), float(table.get("y_m", 0.0)), float(table.get("yaw_rad", 0.0)))
    robot = json.loads(info.metadata.get("trundle", {}).get("robot", "{}") or "{}")
    if any(k in robot for k in ("laser_x_m", "laser_y_m", "laser_yaw_rad")):
        return (float(robot.get("laser_x_m", 0.0)), float(robot.get("laser_y_m", 0.0)),
                float(robot.get("laser_yaw_rad", 0.0)))
    return None


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    return {"mean": float(a.mean()), "median": float(np.median(a)), "min": float(a.min()),
            "p05": float(np.percentile(a, 5)), "max": float(a.max())} if a.size else {}


def run(args: argparse.Namespace) -> int:
    reader = LogReader(args.log)
    info = reader.info()
    config = load_config(args.config)
    slam_config = SlamConfig.from_mapping(_table(config, "slam", set(SlamConfig.__dataclass_fields__)))
    if args.no_loop_closure:
        slam_config.loop_closure = False
    scan_topic = info.topics.get(slam_config.scan_topic)
    if scan_topic is None or scan_topic.ros_type != "sensor_msgs/msg/LaserScan":
        raise UserError(f"{args.log} has no LaserScan topic {slam_config.scan_topic} "
                        f"(topics: {', '.join(sorted(info.topics)) or 'none'})")
    slam = Slam(slam_config, make_odometry(info, config), laser_pose(info, config))
    args.output.mkdir(parents=True, exist_ok=True)

    progress = Progress("slam", max(info.duration_s, 1e-9))
    t0 = info.start_ns or 0
    transforms: list[tuple[str, m.Message, int]] = []
    started, cpu_started = time.perf_counter(), time.process_time()
    for item in reader.messages():
        result = slam.process(item.topic, item.msg)
        if result is not None:
            transforms.append(("/tf", m.TFMessage((m.TransformStamped.planar(
                result.stamp_ns, "map", "odom", *(float(v) for v in slam.map_to_odom)),)), item.log_time_ns))
            progress.update((item.log_time_ns - t0) * 1e-9, f"{slam.stats.scans} scans {slam.stats.loop_closures} loops")
    slam.finish()
    grid = slam.build_map()
    processing_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    progress.close()
    if slam.stats.scans == 0:
        raise UserError(f"{args.log}: no scans on {slam_config.scan_topic}")

    stamps, poses = slam.trajectory()
    end_ns = int(stamps.max())
    map_msg = grid.to_message(end_ns, "map")
    save_map(map_msg, args.output / "map")
    write_trajectory_csv(args.output / "trajectory.csv", stamps, poses)
    keyframes = slam.keyframe_poses()
    loops = [(keyframes[i], keyframes[j]) for i, j in slam.loop_edges()]
    plot_trajectory(map_msg, args.output / "trajectory.png", [poses], loops=loops)
    path_msg = m.Path(end_ns, "map", stamps, poses)
    write_log(transforms + [("/map", map_msg, end_ns), ("/path", path_msg, end_ns)], args.output / "slam.mcap",
              metadata={"command": "slam", "source": str(args.log)})

    st = slam.stats
    duration = info.duration_s
    report = {
        "log": str(args.log), "scans": st.scans, "keyframes": st.keyframes, "duration_s": duration,
        "processing_s": processing_s, "cpu_s": cpu_s,
        "real_time_factor": duration / processing_s if processing_s > 0 else None,
        "loop_closures": st.loop_closures, "loop_attempts": st.loop_attempts, "loop_rejected": st.loop_rejected,
        "loop_unverified": st.loop_unverified,
        "optimizations": st.optimizations, "matched": st.matched, "searched": st.searched,
        "gated_out": st.gated_out, "odometry_only": st.odometry_only,
        "match_score": _stats(st.scores), "scan_to_submap_residual_m": _stats(st.residuals),
        "scan_to_map_residual_m": _stats(list(slam.map_residuals(grid))),
        "path_length_m": float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T))) if len(poses) > 1 else 0.0,
        "map": {"resolution": float(map_msg.resolution), "width": map_msg.width, "height": map_msg.height},
        "config": {k: v for k, v in vars(slam_config).items()},
    }
    (args.output / "report.json").write_text(json.dumps(report, indent=2, default=float))
    print(f"{st.scans} scans ({st.keyframes} keyframes) of {duration:.1f} s in {processing_s:.1f} s "
          f"({report['real_time_factor']:.1f}x real time); {st.loop_closures} loop closures; "
          f"mean scan-to-map residual {report['scan_to_map_residual_m'].get('mean', float('nan')) * 100:.1f} cm")
    print(f"wrote {args.output}/map.pgm, map.yaml, map.png, trajectory.png, trajectory.csv, report.json, slam.mcap")
    return 0
