"""The demo: the whole robot on emulated hardware in a simulated world, then its log turned into a
map, a trajectory and marker detections, each scored against the simulator's ground truth.

Stages (what ``trundle demo`` runs, one function each so tests can run them alone):

1. :func:`record`: ``trundle.tools.sim.robot.RobotSim`` drives the office route;
   ``trundle.tools.emulators.sim_devices.SimDevices`` serves its laser (SCIP 2.0 on a pty), wheel encoders (ODrive
   axes behind an SLCAN pty) and camera (MJPEG over HTTP); the real daemon (``python -m trundle.tools.cli
   daemon``, the code of ``trundle daemon``) records them and is stopped by SIGTERM. The robot
   stands at its start until every device streams. Ground truth comes from the emulators: each
   logged scan is matched by content to the scan the laser emulator cast (hence its true time and
   the robot's true pose), each logged camera frame by its JPEG bytes to the frame the camera
   emulator rendered.
2. :func:`run_slam`: the log replayed through ``trundle.fusion.slam.Slam`` with wheel odometry from
   ``/wheels`` (the wheel model of the daemon's config, stored in the log) and the laser mount
   from ``/tf_static``.
3. :func:`score_markers`: ArUco detection and pose on every logged frame, against the markers the
   simulator had in view and their known poses in the world file.
4. :func:`run_demo`: all of it, writing the log, map, plots and ``report.md`` / ``report.json``.
"""

from __future__ import annotations

import collections
import hashlib
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from trundle.fusion.evaluation import Trajectory, absolute_trajectory_error, poses_at, relative_pose_error
from trundle.fusion.geometry import compose, inverse, transform_points
from trundle.fusion.map_io import OCCUPIED_THRESH, plot_trajectory, save_map, write_trajectory_csv
from trundle.fusion.odometry import DiffDriveOdometry, odometry_from_config
from trundle.fusion.slam import Slam, SlamConfig
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.reader import LogInfo, LogReader
from trundle.logs.replay import replay
from trundle.perception.images import decode_image, to_gray
from trundle.perception.markers import MarkerDetector, marker_pose
from trundle.tools.sim.camera_render import CameraRenderer, CameraPose, PinholeCamera, optical_rotation
from trundle.tools.daemon.service import query_status
from trundle.tools.daemon.config import format_config
from trundle.tools.cli.progress import Progress
from trundle.tools.sim.robot import Mount, RobotSim
from trundle.tools.emulators.sim_devices import SimDevices
from trundle.tools.sim.world import DEFAULT_WORLD, World, load_world

SCAN_TOPIC, WHEELS_TOPIC, IMAGE_TOPIC = "/scan", "/wheels", "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
LOG_NAME = "demo.mcap"
STREAM_TIMEOUT_S = 90.0     # daemon start-up to every device streaming, on a loaded machine
STOP_TIMEOUT_S = 60.0       # SIGTERM to a closed log
LEAD_S = 1.0                # the robot stands this long in the log before it drives
LRF_TIMEOUT_S = 2.0         # laser silence before the driver reconnects: a busy machine delays the emulators ...
WHEEL_TIMEOUT_S = 1.5       # ... and wheel silence before a wheel counts as stale (its motion is then lost)
# SLAM options of the demo (the [slam] table of its robot.toml), each for a property of the emulated robot:
SLAM_OPTIONS: dict[str, Any] = {
    # heading noise floor per scan step (rad): the wheel odometry jumps by degrees between two scans when
    # the left and right wheel readings come from different instants (bunched when the machine is busy)
    "odom_sigma_theta_rad": 0.05,
    # the simulated laser casts a whole scan from one pose (it does not sweep): there is nothing to de-skew
    "deskew": False,
}
ATE_LIMIT_M = 0.05          # acceptance: SLAM trajectory error against ground truth ...
LOOP_MIN_M = 50.0           # ... over a loop (the whole route) at least this long


Say = Callable[[str], None]


@dataclass(frozen=True)
class DemoSettings:
    """What the demo simulates and records.

    ``duration_s`` is the robot time recorded from when it starts to drive (None: the whole
    route, about a minute). The camera streams ``camera_size`` frames at ``camera_fps``, JPEG
    ``camera_quality``. ``seed`` seeds wheel slip and every sensor's noise.
    """

    world: Path = DEFAULT_WORLD
    duration_s: float | None = None
    camera_fps: float = 10.0
    camera_size: tuple[int, int] = (640, 480)
    camera_quality: int = 85
    lrf_model: str = "utm-30lx"
    seed: int = 0


@dataclass(eq=False)
class Recording:
    """A recorded run: the log and its ground truth (base_link poses in the world frame).

    ``scans`` holds, at each logged scan's stamp, the pose the robot had when the laser emulator
    cast that scan, and ``scan_true_ns`` that true time (host clock); ``frames`` and
    ``frame_true_ns`` the same for each logged camera frame. ``unmatched`` counts logged messages
    no emulator record explained (0 expected). ``cpu_s``: CPU time of the emulators (this
    process) and of the daemon process while recording; ``emulator_late_ms`` how late each
    emulator was at most while the robot drove (a busy machine starves them: timing suffers).
    """

    log: Path
    scans: Trajectory
    frames: Trajectory
    scan_true_ns: np.ndarray
    frame_true_ns: np.ndarray
    unmatched: dict[str, int]
    robot_time_s: float
    cpu_s: dict[str, float]
    emulator_late_ms: dict[str, float | None]


# ---------------------------------------------------------------------------------- recording

class FrameTimes:
    """When the camera emulator rendered each frame (host ns), by the SHA-1 of the frame's JPEG.

    Wraps the emulator's ``frame_at``: the time is the one ``SimDevices`` rendered at (the last
    entry of its camera activity), the JPEG is encoded as the emulator encodes it (same quality,
    deterministic), so a logged frame's bytes name the instant it shows.
    """

    def __init__(self, devices: SimDevices) -> None:
        emulator = devices.camera_emulator
        assert emulator is not None, "start the devices first"
        self.activity, self.quality = devices.activity["camera"], emulator.quality
        self.times: dict[bytes, list[int]] = collections.defaultdict(list)
        self._render = emulator.frame_at
        emulator.frame_at = self._frame_at

    def _frame_at(self, t_s: float) -> np.ndarray:
        image = self._render(t_s)
        ok, jpeg = cv2.imencode(".jpg", image, (cv2.IMWRITE_JPEG_QUALITY, self.quality))
        if ok:
            self.times[hashlib.sha1(jpeg.tobytes()).digest()].append(self.activity[-1])
        return image


def daemon_config(devices: SimDevices, folder: Path, socket_path: Path, calibration: Path) -> dict[str, Any]:
    """The daemon's configuration tables for the emulated robot (see ``tools/daemon/example.toml``)."""
    tables = devices.device_tables()
    tables["lrf"]["timeout_s"] = LRF_TIMEOUT_S
    tables["can"]["odrive"] = {"heartbeat_timeout_s": WHEEL_TIMEOUT_S, "data_timeout_s": WHEEL_TIMEOUT_S}
    tables["camera"] = {**tables["camera"], "calibration": str(calibration)}
    return {"robot": {"name": "trundle-demo"}, **tables,
            "logger": {"folder": str(folder), "compression": "zstd", "flush_period_s": 0.5},
            "disk": {"min_free_mb": 100.0, "action": "stop"},
            "processing": {"odometry": True, "slam": False, "markers": False}, "slam": SLAM_OPTIONS,
            "status": {"socket": str(socket_path), "diagnostics_period_s": 1.0}}


def _status(socket_path: Path) -> dict[str, Any] | None:
    try:
        return query_status(socket_path, timeout_s=1.0)
    except UserError:
        return None


def _streaming(status: dict[str, Any] | None) -> bool:
    return status is not None and all(d["state"] == "streaming" and any(d["rates_hz"].values())
                                      for d in status["devices"])


def _rates(status: dict[str, Any] | None) -> str:
    if status is None:
        return ""
    parts = [f"{d['name']} {max(d['rates_hz'].values(), default=0.0):.0f} Hz" for d in status["devices"]]
    log = status["logger"]
    return ", ".join(parts) + f", log {log['size_bytes'] / 1e6:.1f} MB"


def _daemon_failed(proc: subprocess.Popen, daemon_log: Path, what: str) -> UserError:
    tail = daemon_log.read_text(errors="replace").strip().splitlines()[-1:] if daemon_log.exists() else []
    code = proc.poll()
    return UserError(f"the daemon {what}" + (f" (exit code {code})" if code is not None else "")
                     + (f": {tail[0]}" if tail else "") + f"; see {daemon_log}")


def record(out: Path, sim: RobotSim, settings: DemoSettings = DemoSettings(), say: Say = print) -> Recording:
    """Run the simulated robot's devices and the real daemon against them; return the log and truth.

    Writes ``out/robot.toml`` (the daemon's config), ``out/camera.yaml`` (the camera's
    calibration), ``out/daemon.log`` (its output) and ``out/demo.mcap`` (the log).
    """
    out = out.resolve()  # the daemon runs in ``out`` and reads the config by this path
    out.mkdir(parents=True, exist_ok=True)
    robot_time = sim.duration_s if settings.duration_s is None else min(float(settings.duration_s), sim.duration_s)
    say(f"simulated robot: {sim.world.name} world, route of {sim.path_length_m():.1f} m in {sim.duration_s:.0f} s; "
        f"recording {robot_time:.0f} s of it")
    cpu_before, daemon_cpu_before = time.process_time(), _children_cpu_s()
    with tempfile.TemporaryDirectory(prefix="trundle-demo-") as tmp:
        tmp_path = Path(tmp)
        devices = SimDevices(sim, tmp_path / "dev", lrf_model=settings.lrf_model, camera_fps=settings.camera_fps,
                             camera_size=settings.camera_size, camera_quality=settings.camera_quality)
        folder = Path(tempfile.mkdtemp(prefix=".daemon-logs-", dir=out))  # the daemon owns (and guards) it
        socket_path = tmp_path / "status.sock"
        with devices:
            devices.t0_ns = time.time_ns() + int(3600e9)  # the robot waits at its start for the daemon
            frame_times = FrameTimes(devices)
            calibration = out / "camera.yaml"
            calibration.write_text(devices.camera.calibration_yaml("trundle_demo"))
            config = out / "robot.toml"
            config.write_text(format_config(daemon_config(devices, folder, socket_path, calibration)))
            say(f"emulators up: laser {devices.urls['lrf']}, encoders {devices.urls['can']}, "
                f"camera {devices.urls['camera']}")
            daemon_log = out / "daemon.log"
            with open(daemon_log, "w") as log_file:
                # -P: the output folder (the daemon's cwd) is not put on sys.path, so nothing in it shadows trundle
                proc = subprocess.Popen([sys.executable, "-P", "-m", "trundle.tools.cli", "daemon", "--config",
                                         str(config)], stdout=log_file, stderr=subprocess.STDOUT, cwd=out)
            try:
                say(f"daemon started (pid {proc.pid}): trundle daemon --config {config}")
                deadline = time.monotonic() + STREAM_TIMEOUT_S
                status = _status(socket_path)
                while not _streaming(status):
                    if proc.poll() is not None:
                        raise _daemon_failed(proc, daemon_log, "stopped before every device streamed")
                    if time.monotonic() > deadline:
                        states = ", ".join(f"{d['name']} {d['state']}" for d in (status or {}).get("devices", []))
                        raise _daemon_failed(proc, daemon_log, f"did not get every device streaming in "
                                             f"{STREAM_TIMEOUT_S:.0f} s ({states or 'no status'})")
                    time.sleep(0.2)
                    status = _status(socket_path)
                say(f"every device streaming: {_rates(status)}; the robot drives")
                devices.t0_ns = time.time_ns() + int(LEAD_S * 1e9)
                progress = Progress("recording", robot_time)
                next_line = time.monotonic() + 15.0
                while (now := devices.now()) < robot_time:
                    if proc.poll() is not None:
                        raise _daemon_failed(proc, daemon_log, "stopped while recording")
                    status = _status(socket_path) or status
                    progress.update(max(now, 0.0), f"robot time {max(now, 0.0):4.0f} s; {_rates(status)}")
                    if not progress.enabled and time.monotonic() >= next_line:
                        next_line += 15.0
                        say(f"  robot time {now:.0f}/{robot_time:.0f} s; {_rates(status)}")
                    time.sleep(min(0.5, max(robot_time - now, 0.01)))
                progress.close()
                say("stopping the daemon (SIGTERM) ...")
                proc.send_signal(signal.SIGTERM)
                try:
                    code = proc.wait(STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    raise _daemon_failed(proc, daemon_log,
                                         f"did not stop within {STOP_TIMEOUT_S:.0f} s of SIGTERM") from None
                if code != 0:
                    raise _daemon_failed(proc, daemon_log, "did not stop cleanly")
            finally:
                _stop(proc)
        cpu = {"emulators": time.process_time() - cpu_before, "daemon": _children_cpu_s() - daemon_cpu_before}
        assert devices.can_nodes is not None
        periods = {"lrf": devices.laser_model.scan_time, "can": devices.can_nodes.tick_s,
                   "camera": 1.0 / settings.camera_fps}
        late = {name: _longest_pause_ms(devices.produced(name), devices.t0_ns, period)
                for name, period in periods.items()}
    logs = sorted(folder.glob("*.mcap"))
    if len(logs) != 1 or list(folder.glob("*.active")):
        raise UserError(f"expected one closed log in {folder}, found {[p.name for p in folder.iterdir()]}")
    log = out / LOG_NAME
    logs[0].replace(log)
    folder.rmdir()
    scans, scan_ns, unmatched_scans = scan_ground_truth(log, sim, devices)
    frames, frame_ns, unmatched_frames = frame_ground_truth(log, sim, devices, frame_times)
    return Recording(log, scans, frames, scan_ns, frame_ns, {"scans": unmatched_scans, "frames": unmatched_frames},
                     robot_time, cpu, late)


def _longest_pause_ms(times_ns: np.ndarray, since_ns: int, period_s: float) -> float | None:
    """The longest gap between an emulator's outputs after ``since_ns`` beyond its period (ms)."""
    times = np.sort(times_ns[times_ns >= since_ns])
    return max(0.0, float(np.diff(times).max() / 1e6 - period_s * 1e3)) if times.size > 1 else None


def _stop(proc: subprocess.Popen) -> None:
    """After a failure or Ctrl-C: SIGTERM (a clean log), SIGKILL if that does not end it."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def scan_ground_truth(log: Path, sim: RobotSim, devices: SimDevices) -> tuple[Trajectory, np.ndarray, int]:
    """The robot's true pose for every logged scan, found by the scan's content among those the
    laser emulator cast: the trajectory (at the logged stamps), the true host time (ns) of each
    scan, and how many logged scans matched none."""
    assert devices.lrf_device is not None
    dmin = devices.scip_model.params.dmin
    cast: dict[bytes, list[int]] = collections.defaultdict(list)
    for sent in devices.lrf_device.sent:
        cast[np.where(sent.distances >= dmin, sent.distances, -1).astype(np.int64).tobytes()].append(sent.rear_ns)

    def true_ns(msg: m.LaserScan) -> int | None:
        ranges = msg.ranges.astype(np.float64)
        key = np.where(np.isfinite(ranges), np.round(ranges * 1000.0), -1).astype(np.int64).tobytes()
        return _nearest(cast.get(key), msg.stamp_ns)

    return _ground_truth(log, SCAN_TOPIC, true_ns, sim, devices)


def frame_ground_truth(log: Path, sim: RobotSim, devices: SimDevices, frame_times: FrameTimes
                       ) -> tuple[Trajectory, np.ndarray, int]:
    """The robot's true pose for every logged camera frame, found by its JPEG bytes among the
    frames the camera emulator rendered: the trajectory (at the logged stamps), the true host
    time (ns) of each frame, and how many logged frames matched none."""
    def true_ns(msg: m.CompressedImage) -> int | None:
        return _nearest(frame_times.times.get(hashlib.sha1(bytes(msg.data)).digest()), msg.stamp_ns)

    return _ground_truth(log, IMAGE_TOPIC, true_ns, sim, devices)


def _nearest(times: list[int] | None, stamp_ns: int) -> int | None:
    """Of the times an identical output was made (a robot standing still makes many), the one nearest the stamp."""
    return min(times, key=lambda t: abs(t - stamp_ns)) if times else None


def _ground_truth(log: Path, topic: str, true_ns: Callable[[Any], int | None], sim: RobotSim, devices: SimDevices
                  ) -> tuple[Trajectory, np.ndarray, int]:
    """Poses at the true times ``true_ns(msg)`` of ``topic``'s messages, stamped as logged."""
    stamps, times, unmatched = [], [], 0
    with LogReader(log) as reader:
        for item in reader.messages(topics=[topic]):
            t = true_ns(item.msg)
            if t is None:
                unmatched += 1
                continue
            stamps.append(item.msg.stamp_ns)
            times.append(t)
    poses = [sim.pose_at(devices.sim_time(t)) for t in times]
    return (Trajectory(np.array(stamps, np.int64), np.array(poses).reshape(-1, 3)), np.array(times, np.int64),
            unmatched)


# ---------------------------------------------------------------------------------- SLAM

@dataclass(eq=False)
class SlamRun:
    """SLAM over a log: the optimised trajectory (one pose per scan, map frame), the wheel
    odometry at the same stamps (odom frame), the map and the SLAM object (stats, keyframes)."""

    slam: Slam
    trajectory: Trajectory
    odometry: Trajectory
    grid: m.OccupancyGrid
    processing_s: float


def wheel_odometry(info: LogInfo) -> DiffDriveOdometry:
    """Wheel odometry with the wheel model of the ``[can]`` table the daemon ran with (log metadata)."""
    devices = json.loads(info.metadata.get("trundle", {}).get("devices", "{}"))
    can = next((d for d in devices.values() if d.get("family") == "can"), None)
    odometry = odometry_from_config(can) if can is not None else None
    if odometry is None:
        raise UserError(f"{info.path}: no wheel model (wheel_radius_m, track_m) in the log's device metadata")
    return odometry


def run_slam(log: Path, config: SlamConfig | None = None, say: Say = print) -> SlamRun:
    """Replay ``log`` (as fast as possible) through SLAM with wheel odometry from ``/wheels``
    (``config`` default: ``SLAM_OPTIONS``)."""
    with LogReader(log) as reader:
        info = reader.info()
    if SCAN_TOPIC not in info.topics:
        raise UserError(f"{log}: no {SCAN_TOPIC} topic")
    odometry = wheel_odometry(info)
    slam = Slam(config or SlamConfig.from_mapping(SLAM_OPTIONS), odometry)
    odom_stamps: list[int] = []
    odom_poses: list[np.ndarray] = []
    progress = Progress("slam", info.topics[SCAN_TOPIC].count)

    def feed(item: Any) -> None:
        result = slam.process(item.topic, item.msg)
        if item.topic == WHEELS_TOPIC and not odometry.stale:
            odom_stamps.append(item.msg.stamp_ns)
            odom_poses.append(odometry.pose.copy())
        elif result is not None:
            progress.update(slam.stats.scans, f"{slam.stats.scans} scans, {slam.stats.loop_closures} loop closures")

    started = time.perf_counter()
    replay(log, feed, rate=0.0, topics=["/tf_static", WHEELS_TOPIC, SCAN_TOPIC])
    slam.finish()
    progress.close()
    if slam.stats.scans == 0:
        raise UserError(f"{log}: no scans on {SCAN_TOPIC}")
    stamps, poses = slam.trajectory()
    grid = slam.build_map().to_message(int(stamps[-1]), "map")
    processing_s = time.perf_counter() - started
    odom = Trajectory(np.array(odom_stamps, np.int64), np.array(odom_poses).reshape(-1, 3))
    return SlamRun(slam, Trajectory(stamps, poses), interpolate(odom, stamps), grid, processing_s)


def interpolate(trajectory: Trajectory, stamps_ns: np.ndarray) -> Trajectory:
    """``trajectory`` at ``stamps_ns`` (linear in x, y and unwrapped heading; clamped at the ends)."""
    t = trajectory.stamps_ns - trajectory.stamps_ns[0]
    q = np.asarray(stamps_ns, np.int64) - trajectory.stamps_ns[0]
    poses = np.stack([np.interp(q, t, trajectory.poses[:, 0]), np.interp(q, t, trajectory.poses[:, 1]),
                      np.interp(q, t, np.unwrap(trajectory.poses[:, 2]))], axis=1)
    return Trajectory(stamps_ns, poses)


def path_length(poses: np.ndarray) -> float:
    """Length (m) of the polyline through the poses' positions."""
    return float(np.hypot(*np.diff(np.asarray(poses)[:, :2], axis=0).T).sum()) if len(poses) > 1 else 0.0


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance (m) from each point (N, 2) to the nearest of the segments (S, 4) ``x1 y1 x2 y2``."""
    a, b = segments[None, :, :2], segments[None, :, 2:]
    p = np.asarray(points, np.float64)[:, None, :]
    e = b - a
    u = np.clip(((p - a) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-18), 0.0, 1.0)
    return np.hypot(*np.moveaxis(p - (a + u[..., None] * e), -1, 0)).min(axis=1)


def map_wall_distances(grid: m.OccupancyGrid, world: World, map_to_world: np.ndarray) -> np.ndarray:
    """Distance (m) of every occupied map cell's centre to the nearest wall of ``world``, with the map
    placed in the world by ``map_to_world`` (x, y, theta)."""
    rows, cols = np.nonzero(grid.data >= OCCUPIED_THRESH * 100)
    cells = np.stack([cols + 0.5, rows + 0.5], axis=1) * grid.resolution
    map_points = transform_points(np.array([grid.origin_x, grid.origin_y, grid.origin_theta]), cells)
    return segment_distances(transform_points(map_to_world, map_points), world.segments)


# ---------------------------------------------------------------------------------- markers

@dataclass(eq=False)
class MarkerSighting:
    """One detected marker in one frame, scored against the world: ``in_view`` is whether the
    simulator had it in view (``CameraRenderer.visible_decals``: facing the camera within 60 deg,
    sides of 24 px or more, unoccluded), ``in_image`` whether it was in the image at all (any size
    or angle; a detection that is not is false); errors are of the detected pose in the camera's
    optical frame against the marker's known pose seen from the true camera."""

    stamp_ns: int
    id: int
    corners: np.ndarray
    in_view: bool
    in_image: bool
    known: bool
    distance_m: float = math.nan
    position_error_m: float = math.nan
    angle_error_deg: float = math.nan
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None


@dataclass(eq=False)
class MarkerScore:
    """ArUco detection over a log's frames: ``in_view`` counts, per marker id, the frames in which
    the simulator had it in view; ``sightings`` are every detection; ``missed`` the (stamp, id)
    pairs in view but not detected. ``frames`` had ground truth, ``unmatched`` had none."""

    frames: int = 0
    unmatched: int = 0
    in_view: collections.Counter[int] = field(default_factory=collections.Counter)
    sightings: list[MarkerSighting] = field(default_factory=list)
    missed: list[tuple[int, int]] = field(default_factory=list)
    camera_info: m.CameraInfo | None = None
    best_stamp_ns: int | None = None

    def detected_ids(self) -> list[int]:
        return sorted({s.id for s in self.sightings if s.in_view})

    def summary(self, world: World) -> list[dict[str, Any]]:
        """Per detected id: frames detected and in view, and pose errors (m, deg) over its sightings."""
        rows = []
        for marker_id in sorted({s.id for s in self.sightings}):
            mine = [s for s in self.sightings if s.id == marker_id]
            scored = [s for s in mine if np.isfinite(s.position_error_m)]
            row: dict[str, Any] = {"id": marker_id, "frames_detected": len(mine),
                                   "frames_in_view": self.in_view[marker_id], "in_world": mine[0].known,
                                   "false_detections": sum(not s.in_image for s in mine)}
            if scored:
                pos = np.array([s.position_error_m for s in scored])
                ang = np.array([s.angle_error_deg for s in scored])
                dist = np.array([s.distance_m for s in scored])
                row.update(distance_m={"min": float(dist.min()), "max": float(dist.max())},
                           position_error_m={"median": float(np.median(pos)), "rms": float(np.sqrt(np.mean(pos ** 2))),
                                             "max": float(pos.max())},
                           angle_error_deg={"median": float(np.median(ang)), "rms": float(np.sqrt(np.mean(ang ** 2))),
                                            "max": float(ang.max())})
            if marker_id in {d.marker_id for d in world.markers}:
                d = world.marker(marker_id)
                row["world_pose"] = {"x": d.x, "y": d.y, "z": d.z, "yaw": d.yaw, "size_m": d.width}
            rows.append(row)
        return rows


def camera_from_info(info: m.CameraInfo) -> PinholeCamera:
    """The pinhole intrinsics of a calibrated CameraInfo."""
    k = np.asarray(info.k, np.float64).reshape(3, 3)
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise UserError(f"camera info of {info.frame_id!r} is not calibrated (K is zero): marker poses need it")
    return PinholeCamera(int(info.width), int(info.height), float(k[0, 0]), float(k[1, 1]), float(k[0, 2]),
                         float(k[1, 2]))


def camera_pose(base: np.ndarray, mount: Mount) -> CameraPose:
    """The level camera's pose in the world for a base_link pose and the camera's mount."""
    x, y, yaw = compose(np.asarray(base, np.float64), np.array([mount.x, mount.y, mount.yaw]))
    return CameraPose(float(x), float(y), mount.z, float(yaw))


def marker_truth(world: World, marker_id: int, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3x3) and translation (m) of a world marker in the optical frame of a camera at ``pose``
    (marker frame as ``trundle.perception.markers``: x right, y up, z out of the marker)."""
    decal = world.marker(marker_id)
    camera_axes = optical_rotation(pose.yaw)                      # optical axes as columns, in the map
    right = np.array([-math.sin(decal.yaw), math.cos(decal.yaw), 0.0])
    axes = np.column_stack([right, [0.0, 0.0, 1.0], [*decal.normal, 0.0]])
    translation = (np.array([decal.x, decal.y, decal.z]) - np.array([pose.x, pose.y, pose.z])) @ camera_axes
    return camera_axes.T @ axes, translation


def score_markers(log: Path, frames: Trajectory, world: World, mount: Mount, say: Say = print) -> MarkerScore:
    """Detect ArUco markers (ids, corners, poses) in every logged frame and score them against the
    simulator: which markers a frame had in view (from the true camera pose at that frame) and the
    known marker poses of the world file. Marker sizes are the world's."""
    detector = MarkerDetector(world.aruco_dictionary)
    score = MarkerScore()
    renderer: CameraRenderer | None = None
    best: tuple[int, float] = (0, 0.0)
    with LogReader(log) as reader:
        info = reader.info()
        total = info.topics[IMAGE_TOPIC].count if IMAGE_TOPIC in info.topics else 0
        progress = Progress("markers", total)
        for item in reader.messages(topics=[CAMERA_INFO_TOPIC, IMAGE_TOPIC]):
            msg = item.msg
            if isinstance(msg, m.CameraInfo):
                score.camera_info = msg
                renderer = CameraRenderer(world, camera_from_info(msg))
                continue
            base, found = poses_at(frames, np.array([msg.stamp_ns]), tolerance_ns=0)
            if renderer is None or not found[0]:
                score.unmatched += 1
                continue
            score.frames += 1
            pose = camera_pose(base[0], mount)
            visible = {d.marker_id for d, _ in renderer.visible_decals(pose) if d.kind == "marker"}
            present = {d.marker_id for d, _ in renderer.visible_decals(pose, min_side_px=1.0, max_incidence_deg=89.9,
                                                                       border_px=0.0) if d.kind == "marker"}
            score.in_view.update(visible)
            detections = detector.detect(to_gray(decode_image(msg)))
            world_ids = {d.marker_id for d in world.markers}
            for marker in detections:
                sighting = MarkerSighting(msg.stamp_ns, marker.id, marker.corners, marker.id in visible,
                                          marker.id in present, marker.id in world_ids)
                if sighting.known:
                    estimate = marker_pose(marker, score.camera_info, world.marker(marker.id).width)
                    rotation, translation = marker_truth(world, marker.id, pose)
                    cos_angle = (np.trace(estimate.rotation.T @ rotation) - 1.0) / 2.0
                    sighting.distance_m = float(np.linalg.norm(translation))
                    sighting.position_error_m = float(np.linalg.norm(estimate.translation - translation))
                    sighting.angle_error_deg = math.degrees(math.acos(float(np.clip(cos_angle, -1.0, 1.0))))
                    sighting.rvec, sighting.tvec = estimate.rvec, estimate.translation
                score.sightings.append(sighting)
            seen = {k.id for k in detections}
            score.missed += [(msg.stamp_ns, i) for i in sorted(visible - seen)]
            shown = (len(visible & seen), sum(_perimeter(k.corners) for k in detections if k.id in visible))
            if shown > best:
                best, score.best_stamp_ns = shown, msg.stamp_ns
            progress.update(score.frames + score.unmatched, f"{len(score.sightings)} markers detected")
        progress.close()
    return score


def _perimeter(corners: np.ndarray) -> float:
    return float(np.hypot(*(np.roll(corners, -1, axis=0) - corners).T).sum())


def sensor_mount(log: Path, child_frame: str, parent_frame: str = "base_link") -> Mount:
    """A sensor's mount on the robot from the log's ``/tf_static`` (``parent_frame -> child_frame``)."""
    with LogReader(log) as reader:
        for item in reader.messages(topics=["/tf_static"]):
            for t in item.msg.transforms:
                if t.child_frame_id == child_frame and t.frame_id == parent_frame:
                    x, y, z = (float(v) for v in t.translation)
                    return Mount(x, y, z, t.yaw)
    raise UserError(f"{log}: no static transform {parent_frame} -> {child_frame} on /tf_static")


def driver_diagnostics(log: Path) -> dict[str, dict[str, Any]]:
    """The last ``/diagnostics`` status of every component in the log (drivers, logger, disk, ...):
    level, message and values (numbers where they are numbers)."""
    last: dict[str, m.DiagnosticStatus] = {}
    with LogReader(log) as reader:
        for item in reader.messages(topics=["/diagnostics"]):
            for status in item.msg.status:
                last[status.name] = status
    levels = {m.OK: "OK", m.WARN: "WARN", m.ERROR: "ERROR", m.STALE: "STALE"}
    return {name: {"level": levels.get(s.level, str(s.level)), "message": s.message,
                   "values": {k: _number(v) for k, v in s.values}} for name, s in sorted(last.items())}


def _number(text: str) -> Any:
    for kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            continue
        return value if math.isfinite(value) else text
    return text


# ---------------------------------------------------------------------------------- outputs

TRUTH_BGR, SLAM_BGR, ODOMETRY_BGR = (200, 90, 0), (0, 0, 230), (0, 140, 255)


def plot_run(grid: m.OccupancyGrid, path: Path, truth: np.ndarray, estimate: np.ndarray, odometry: np.ndarray,
             loops: list[tuple[np.ndarray, np.ndarray]]) -> Path:
    """The trajectory-over-map plot (map frame): ground truth, SLAM estimate, wheel odometry, with a legend."""
    plot_trajectory(grid, path, [truth, odometry, estimate], colours=[TRUTH_BGR, ODOMETRY_BGR, SLAM_BGR], loops=loops)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    scale = max(1.0, image.shape[1] / 1000.0)
    entries = [("ground truth (simulator)", TRUTH_BGR), ("wheel odometry", ODOMETRY_BGR), ("SLAM estimate", SLAM_BGR),
               ("loop closure", (0, 200, 0))]
    for k, (text, colour) in enumerate(entries):
        y = int((24 + 22 * k) * scale)
        mid = y - int(5 * scale)
        cv2.line(image, (int(10 * scale), mid), (int(40 * scale), mid), colour, max(2, int(2 * scale)))
        cv2.putText(image, text, (int(48 * scale), y), cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, (40, 40, 40),
                    max(1, int(scale)), cv2.LINE_AA)
    if not cv2.imwrite(str(path), image):
        raise UserError(f"cannot write {path}")
    return path


def draw_detections(log: Path, score: MarkerScore, frames: Trajectory, world: World, mount: Mount, path: Path
                    ) -> Path | None:
    """The frame with the most markers in view and detected, annotated: detected outlines and ids
    (green), each pose's axes, and where the world says each marker in view is (red, thin)."""
    if score.best_stamp_ns is None or score.camera_info is None:
        return None
    camera = camera_from_info(score.camera_info)
    with LogReader(log) as reader:
        msg = next(i.msg for i in reader.messages(topics=[IMAGE_TOPIC]) if i.msg.stamp_ns == score.best_stamp_ns)
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
    if not cv2.imwrite(str(path), image):
        raise UserError(f"cannot write {path}")
    return path


def _stats(values: np.ndarray) -> dict[str, float]:
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return {}
    return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95)), "max": float(values.max())}


STARVED_MS = 100.0   # an emulator later than this could not keep real time


def starved(recording: Recording) -> list[str]:
    """The emulators that were more than ``STARVED_MS`` late while the robot drove."""
    return [name for name, late in recording.emulator_late_ms.items() if late is not None and late > STARVED_MS]


def build_report(settings: DemoSettings, recording: Recording, run: SlamRun, score: MarkerScore, world: World,
                 seconds: dict[str, float]) -> dict[str, Any]:
    """Every figure of the run, computed from the log, the SLAM output and the simulator's truth."""
    truth = recording.scans
    ate = absolute_trajectory_error(run.trajectory, truth)
    odometry_ate = absolute_trajectory_error(run.odometry, truth)
    scan_period = float(np.median(np.diff(truth.stamps_ns))) if len(truth) > 1 else 0.0
    rpe_step = max(1, int(round(1e9 / scan_period))) if scan_period > 0 else 1
    rpe = relative_pose_error(run.trajectory, truth, step=rpe_step) if len(truth) > rpe_step else None
    walls = map_wall_distances(run.grid, world, np.array(ate.alignment_xyt))
    with LogReader(recording.log) as reader:
        info = reader.info()
    expected = sorted(score.in_view)
    detected_rows = score.summary(world)
    detected = {row["id"] for row in detected_rows if row["frames_detected"] > row["false_detections"]}
    in_view_pairs = sum(score.in_view.values())
    stats = run.slam.stats
    report: dict[str, Any] = {
        "ate_rmse_m": ate.rmse_m,
        "path_length_m": path_length(truth.poses),
        "markers_expected": expected,
        "markers_detected": detected_rows,
        "checks": {
            f"ate_rmse_m <= {ATE_LIMIT_M}": ate.rmse_m <= ATE_LIMIT_M,
            "every marker in view detected": set(expected) <= detected,
            "no false marker ids": all(row["false_detections"] == 0 for row in detected_rows),
            "every logged scan and frame has ground truth": not any(recording.unmatched.values()),
            **({f"a loop of at least {LOOP_MIN_M:.0f} m": path_length(truth.poses) >= LOOP_MIN_M
                and float(np.hypot(*(truth.poses[-1, :2] - truth.poses[0, :2]))) < 1.0}
               if settings.duration_s is None else {}),
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
        "map": {"resolution_m": float(run.grid.resolution), "width": run.grid.width, "height": run.grid.height,
                "occupied_cells": int(walls.size), "wall_distance_m": _stats(walls),
                "occupied_within_0.1_m_of_a_wall": float(np.mean(walls <= 0.1)) if walls.size else 0.0},
        "markers": {"frames": score.frames, "frames_without_truth": score.unmatched,
                    "in_view": {str(k): v for k, v in sorted(score.in_view.items())},
                    "in_view_detected": in_view_pairs - len(score.missed), "in_view_total": in_view_pairs,
                    "detected_ids": sorted({s.id for s in score.sightings})},
        "timing": {"scan_stamp_error_ms": _stats((truth.stamps_ns - recording.scan_true_ns) / 1e6),
                   "frame_stamp_latency_ms": _stats((recording.frames.stamps_ns - recording.frame_true_ns) / 1e6)},
        "drivers": driver_diagnostics(recording.log),
        "log": {"file": recording.log.name, "size_bytes": recording.log.stat().st_size, "duration_s": info.duration_s,
                "topics": {t: i.count for t, i in sorted(info.topics.items())}},
        "ground_truth_unmatched": recording.unmatched,
        "robot_time_s": recording.robot_time_s,
        "cpu_s": recording.cpu_s,
        "emulator_late_ms": recording.emulator_late_ms,
        "starved": starved(recording),
        "load_average": list(os.getloadavg()),
        "seconds": seconds,
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(settings).items()},
        "slam_options": SLAM_OPTIONS,
    }
    return report


def report_markdown(report: dict[str, Any]) -> str:
    """``report.md``: the report's figures for a reader, with the pictures and files."""
    tr, mp, mk = report["trajectory"], report["map"], report["markers"]
    scan_ms, frame_ms = report["timing"]["scan_stamp_error_ms"], report["timing"]["frame_stamp_latency_ms"]
    ate, odo = tr["ate"], tr["odometry_ate"]
    checks = "\n".join(f"- {'PASS' if ok else 'FAIL'}: {name}" for name, ok in report["checks"].items())
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
        f"{mk['frames']} frames; markers in view per the simulator: "
        f"{', '.join(map(str, report['markers_expected'])) or 'none'}; detected in {mk['in_view_detected']} of "
        f"{mk['in_view_total']} (frame, marker) pairs in view.",
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


def run_demo(out: Path, settings: DemoSettings = DemoSettings(), say: Say = print) -> dict[str, Any]:
    """Record the simulated robot with the real daemon, then map, detect, score and write ``out``."""
    started = time.monotonic()
    world = load_world(settings.world)
    sim = RobotSim(world, seed=settings.seed)
    say("[1/4] recording: world simulator -> device emulators -> trundle daemon -> log")
    recording = record(out, sim, settings, say)
    write_trajectory_csv(out / "ground_truth.csv", recording.scans.stamps_ns, recording.scans.poses)
    write_trajectory_csv(out / "frames_ground_truth.csv", recording.frames.stamps_ns, recording.frames.poses)
    seconds = {"record": time.monotonic() - started}
    say(f"[2/4] SLAM: replaying {len(recording.scans)} scans and the wheel encoders of {recording.log.name}")
    run = run_slam(recording.log, say=say)
    seconds["slam"] = run.processing_s
    say(f"      {run.slam.stats.keyframes} keyframes, {run.slam.stats.loop_closures} loop closures "
        f"in {run.processing_s:.0f} s")
    say(f"[3/4] perception: ArUco markers in {len(recording.frames)} camera frames")
    t = time.monotonic()
    mount = sensor_mount(recording.log, "camera")
    score = score_markers(recording.log, recording.frames, world, mount, say=say)
    seconds["markers"] = time.monotonic() - t
    say("[4/4] report")
    report = build_report(settings, recording, run, score, world, seconds)
    save_map(run.grid, out / "map")
    write_trajectory_csv(out / "trajectory.csv", run.trajectory.stamps_ns, run.trajectory.poses)
    map_from_world = inverse(np.array(report["trajectory"]["ate"]["alignment_xyt"]))
    keyframes = run.slam.keyframe_poses()
    plot_run(run.grid, out / "trajectory.png", compose(map_from_world, recording.scans.poses), run.trajectory.poses,
             run.odometry.poses, [(keyframes[i], keyframes[j]) for i, j in run.slam.loop_edges()])
    draw_detections(recording.log, score, recording.frames, world, mount, out / "camera_detections.png")
    seconds["total"] = time.monotonic() - started
    (out / "report.json").write_text(json.dumps(report, indent=1, default=_json_default) + "\n")
    (out / "report.md").write_text(report_markdown(report))
    return report


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")
