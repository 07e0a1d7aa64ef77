"""The demo: the whole robot on emulated hardware in a simulated world, then its log turned into a
map, a trajectory and marker detections, each scored against the simulator's ground truth.

Stages (what ``trundle demo`` runs, one function each so tests can run them alone):

1. :func:`record`: ``trundle.tools.sim.robot.RobotSim`` drives the office route;
   ``trundle.tools.emulators.sim_devices.SimDevices`` serves its laser (SCIP 2.0 on a pty), wheel encoders (ODrive
   axes behind an SLCAN pty) and camera (MJPEG over HTTP); the real daemon (``python -m trundle.tools.cli
   daemon``, the code of ``trundle daemon``) records them and is stopped by SIGTERM. The robot
   stands at its start until every device streams. Each logged scan and frame then gets its ground
   truth from what the emulators made (``trundle.tools.demo.ground_truth``).
2. ``trundle.tools.demo.slam.run_slam``: the log replayed through SLAM with wheel odometry from
   ``/wheels`` (the wheel model of the daemon's config, stored in the log), the laser mount
   from ``/tf_static`` and the markers the daemon saw (``/landmarks``) as landmarks; and again
   without the markers, for the report to compare.
3. ``trundle.tools.demo.scoring.score_markers``: ArUco detection and pose on every logged frame,
   against the markers the simulator had in view and their known poses in the world file.
4. :func:`run_demo`: all of it, writing the log, map, plots and ``report.md`` / ``report.json``
   (``trundle.tools.demo.report``).

Long stages show their progress on the display a ``progress`` factory makes (none by default;
``trundle demo`` passes its progress bar), and say what they do through ``say``.
"""

from __future__ import annotations

import resource
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion.geometry import compose, inverse
from trundle.fusion.mapping.map_io import save_map, write_trajectory_csv
from trundle.logs.errors import UserError
from trundle.logs.outputs import write_text, writing_folder
from trundle.logs.paths import output_folder
from trundle.tools.config.toml_text import format_config
from trundle.tools.daemon.status import query_status
from trundle.tools.demo import daemon_process
from trundle.tools.demo.ground_truth import FrameTimes, Recording, frame_ground_truth, scan_ground_truth
from trundle.tools.demo.report import build_report, draw_detections, plot_run, write_report
from trundle.tools.demo.scoring import score_markers, sensor_mount
from trundle.tools.demo.slam import run_slam
from trundle.tools.emulators.sim_devices import SimDevices
from trundle.tools.jobs.landmark_slam import write_landmarks
from trundle.tools.jobs.progress import NoProgress, ProgressFactory
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import DEFAULT_WORLD, World, load_world

LOG_NAME = "demo.mcap"
DEMO_MARKER = ".trundle-demo"  # left in every folder the demo writes: it rewrites only those
PARTIAL_LOG = "demo.partial"  # an interrupted recording's log: demo.partial.mcap, demo.partial-1.mcap, ...
PARTIAL_LOGS = f"{PARTIAL_LOG}*"
STREAM_TIMEOUT_S = 90.0     # daemon start-up to every device streaming, on a loaded machine
STOP_TIMEOUT_S = 60.0       # SIGTERM to a closed log
LEAD_S = 1.0                # the robot stands this long in the log before it drives
LRF_TIMEOUT_S = 2.0         # laser silence before the driver reconnects: a busy machine delays the emulators ...
WHEEL_TIMEOUT_S = 1.5       # ... and wheel silence before a wheel counts as stale (its motion is then lost)
MARKERS_HZ = 10.0           # camera frames a second the daemon looks for markers in (every frame: landmarks for SLAM)


Say = Callable[[str], None]
"""Tells the user what the demo does, one line of text at a time."""


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

    def as_json(self) -> dict[str, Any]:
        """The settings as JSON values (paths as text), for the report."""
        return {k: str(v) if isinstance(v, Path) else v for k, v in asdict(self).items()}


# ---------------------------------------------------------------------------------- recording

def daemon_config(devices: SimDevices, folder: Path, socket_path: Path, calibration: Path) -> dict[str, Any]:
    """The daemon's configuration tables for the emulated robot (see ``tools/config/example.toml``)."""
    tables = devices.device_tables()
    tables["lrf"]["timeout_s"] = LRF_TIMEOUT_S
    tables["can"]["odrive"] = {"heartbeat_timeout_s": WHEEL_TIMEOUT_S, "data_timeout_s": WHEEL_TIMEOUT_S}
    tables["camera"] = {**tables["camera"], "calibration": str(calibration)}
    return {"robot": {"name": "trundle-demo"}, **tables,
            "logger": {"folder": str(folder), "compression": "zstd", "flush_period_s": 0.5},
            "disk": {"min_free_mb": 100.0, "action": "stop"},
            "processing": {"odometry": True, "slam": False, "markers": True, "markers_hz": MARKERS_HZ,
                           "marker_size_m": marker_size(devices.sim.world),
                           "aruco_dictionary": devices.sim.world.aruco_dictionary},
            "status": {"socket": str(socket_path), "diagnostics_period_s": 1.0}}


SAVED_CONFIG_NOTE = """\
# The configuration the demo's daemon ran with (trundle daemon --config robot.toml). Its device
# URLs were the demo's emulators and its logger folder and status socket were temporary: all are
# gone now (the log is demo.mcap). To run the daemon on a robot, give your devices' URLs
# (scip2:///dev/ttyACM0, slcan:///dev/ttyACM1@1000000, v4l2:///dev/video0) and a logger folder,
# or start from `trundle daemon --print-example-config`.
"""
GONE = "  # the demo's own, gone when it ends"


def saved_config(tables: dict[str, Any]) -> str:
    """``out/robot.toml`` (the daemon reads it; the user keeps it): the daemon's configuration with a note
    that its device URLs, logger folder and status socket are the run's own (temporary), and how to
    point it at a robot's devices."""
    temporary = ("url = ", "folder = ", "socket = ")
    lines = [line + GONE if line.startswith(temporary) else line for line in format_config(tables).splitlines()]
    return SAVED_CONFIG_NOTE + "\n".join(lines) + "\n"


def marker_size(world: World) -> float:
    """The side (m) of the world's ArUco markers, which the daemon needs to know (one size for all)."""
    sizes = {d.width for d in world.markers}
    if len(sizes) != 1:
        raise UserError(f"the {world.name} world has markers of sizes {sorted(sizes)}: the daemon knows one size")
    return sizes.pop()


def _status(socket_path: Path) -> dict[str, Any] | None:
    """The daemon's status from its socket; None while it does not answer (starting, busy)."""
    try:
        return query_status(socket_path, timeout_s=1.0)
    except UserError:
        return None


def _streaming(status: dict[str, Any] | None) -> bool:
    """Whether every device of the daemon's ``status`` streams (and has a nonzero rate)."""
    return status is not None and all(d["state"] == "streaming" and any(d["rates_hz"].values())
                                      for d in status["devices"])


def _rates(status: dict[str, Any] | None) -> str:
    """One line of the daemon's ``status``: each device's highest topic rate (Hz), the log's size (MB)."""
    if status is None:
        return ""
    parts = [f"{d['name']} {max(d['rates_hz'].values(), default=0.0):.0f} Hz" for d in status["devices"]]
    log = status["logger"]
    return ", ".join(parts) + f", log {log['size_bytes'] / 1e6:.1f} MB"


def _daemon_failed(proc: subprocess.Popen[bytes], daemon_log: Path, what: str) -> UserError:
    """The one-line error of a daemon that ``what``, with its exit code and last line of output."""
    tail = daemon_log.read_text(errors="replace").strip().splitlines()[-1:] if daemon_log.exists() else []
    code = proc.poll()
    return UserError(f"the daemon {what}" + (f" (exit code {code})" if code is not None else "")
                     + (f": {tail[0]}" if tail else "") + f"; see {daemon_log}")


def record(out: Path, sim: RobotSim, settings: DemoSettings = DemoSettings(), say: Say = print,
           progress: ProgressFactory = NoProgress) -> Recording:
    """Run the simulated robot's devices and the real daemon against them; return the log and truth.

    Shows the robot time recorded (s) on a ``progress`` display (if it shows nothing, ``say``
    tells it every 15 s). Writes ``out/robot.toml`` (the daemon's config), ``out/camera.yaml`` (the camera's
    calibration), ``out/daemon.log`` (its output) and ``out/demo.mcap`` (the log).
    """
    out = output_folder(out.resolve(), marker=DEMO_MARKER)  # the daemon runs in ``out``, reads the config by this path
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
            write_text(calibration, devices.camera.calibration_yaml("trundle_demo"), replace=True)
            config = out / "robot.toml"
            write_text(config, saved_config(daemon_config(devices, folder, socket_path, calibration)), replace=True)
            say(f"emulators up: laser {devices.urls['lrf']}, encoders {devices.urls['can']}, "
                f"camera {devices.urls['camera']}")
            daemon_log = out / "daemon.log"
            with open(daemon_log, "w") as log_file:
                # -P: the output folder (the daemon's cwd) is not put on sys.path, so nothing in it shadows
                # trundle; a session of its own: the terminal's signals are the demo's, which stops it cleanly
                proc = subprocess.Popen(daemon_process.command(["daemon", "--config", str(config)]),
                                        stdout=log_file, stderr=subprocess.STDOUT, cwd=out, start_new_session=True)
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
                bar = progress("recording", robot_time)
                next_line = time.monotonic() + 15.0
                while (now := devices.now()) < robot_time:
                    if proc.poll() is not None:
                        raise _daemon_failed(proc, daemon_log, "stopped while recording")
                    status = _status(socket_path) or status
                    bar.update(max(now, 0.0), f"robot time {max(now, 0.0):4.0f} s; {_rates(status)}")
                    if not bar.enabled and time.monotonic() >= next_line:
                        next_line += 15.0
                        say(f"  robot time {now:.0f}/{robot_time:.0f} s; {_rates(status)}")
                    time.sleep(min(0.5, max(robot_time - now, 0.01)))
                bar.close()
                say("stopping the daemon (SIGTERM) ...")
                proc.send_signal(signal.SIGTERM)
                try:
                    code = proc.wait(STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    raise _daemon_failed(proc, daemon_log,
                                         f"did not stop within {STOP_TIMEOUT_S:.0f} s of SIGTERM") from None
                if code != 0:
                    raise _daemon_failed(proc, daemon_log, "did not stop cleanly")
            except BaseException:  # Ctrl-C, SIGTERM, SIGHUP (see cli/demo.py) or a failure: keep what was logged
                _stop(proc)
                _keep_partial_log(folder, out, say)
                raise
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


def _keep_partial_log(folder: Path, out: Path, say: Say) -> None:
    """After an interrupted recording: the daemon's (closed) log moved out of its hidden folder to
    ``out/demo.partial.mcap`` (numbered if several), said to the user; the folder removed."""
    logs = sorted(folder.glob("*.mcap")) + sorted(folder.glob("*.mcap.active"))
    for i, path in enumerate(logs):
        suffix = ".mcap.active" if path.name.endswith(".active") else ".mcap"
        target = out / (f"{PARTIAL_LOG}{'' if i == 0 else f'-{i}'}{suffix}")
        path.replace(target)
        say(f"the recording was interrupted; its log so far is {target}"
            + (" (trundle recover it)" if suffix.endswith(".active") else ""))
    shutil.rmtree(folder, ignore_errors=True)


def _longest_pause_ms(times_ns: np.ndarray, since_ns: int, period_s: float) -> float | None:
    """The longest gap between an emulator's outputs after ``since_ns`` beyond its period (ms)."""
    times = np.sort(times_ns[times_ns >= since_ns])
    return max(0.0, float(np.diff(times).max() / 1e6 - period_s * 1e3)) if times.size > 1 else None


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """After a failure or Ctrl-C: SIGTERM (a clean log), SIGKILL if that does not end it."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _children_cpu_s() -> float:
    """CPU time (s, user + system) of this process's ended and waited-for children (the daemon)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


# ---------------------------------------------------------------------------------- the whole demo

def run_demo(out: Path, settings: DemoSettings = DemoSettings(), say: Say = print,
             progress: ProgressFactory = NoProgress) -> dict[str, Any]:
    """Record the simulated robot with the real daemon, then map, detect, score and write ``out``;
    return the report. ``say`` tells each stage, ``progress`` makes each long stage's display."""
    started = time.monotonic()
    output_folder(out, create=False, marker=DEMO_MARKER)  # made once the world is read
    world = load_world(settings.world)
    sim = RobotSim(world, seed=settings.seed)
    # a failure (a full disk, Ctrl-C) takes back what this run added; only a partial recording stays
    with writing_folder(out.resolve(), marker=DEMO_MARKER, keep=(PARTIAL_LOGS,)):
        return _record_and_report(out, world, sim, settings, say, progress, started)


def _record_and_report(out: Path, world: World, sim: RobotSim, settings: DemoSettings, say: Say,
                       progress: ProgressFactory, started: float) -> dict[str, Any]:
    """:func:`run_demo`'s work in its folder ``out`` (``started``: its monotonic start time, s)."""
    say("[1/4] recording: world simulator -> device emulators -> trundle daemon -> log")
    recording = record(out, sim, settings, say, progress)
    write_trajectory_csv(out / "ground_truth.csv", recording.scans.stamps_ns, recording.scans.poses, replace=True)
    write_trajectory_csv(out / "frames_ground_truth.csv", recording.frames.stamps_ns, recording.frames.poses,
                         replace=True)
    seconds = {"record": time.monotonic() - started}
    say(f"[2/4] SLAM: replaying {len(recording.scans)} scans, the wheel encoders and the daemon's marker sightings "
        f"of {recording.log.name}, and again without the markers")
    run = run_slam(recording.log, progress=progress, markers=True)
    plain = run_slam(recording.log, progress=progress)
    seconds["slam"] = run.processing_s
    seconds["slam_without_markers"] = plain.processing_s
    mapped = run.slam.landmarks()
    assert mapped is not None, "the demo's SLAM runs with its markers"
    say(f"      {run.slam.stats.keyframes} keyframes, {run.slam.stats.loop_closures} loop closures, "
        f"{len(mapped.ids)} marker{'' if len(mapped.ids) == 1 else 's'} mapped in {run.processing_s:.0f} s")
    say(f"[3/4] perception: ArUco markers in {len(recording.frames)} camera frames")
    t = time.monotonic()
    mount = sensor_mount(recording.log, "camera")
    score = score_markers(recording.log, recording.frames, world, mount, progress)
    seconds["markers"] = time.monotonic() - t
    say("[4/4] report")
    report = build_report(settings.as_json(), recording, run, score, world, seconds, plain)
    save_map(run.grid, out / "map", "demo: SLAM map of the simulated world", replace=True)
    write_trajectory_csv(out / "trajectory.csv", run.trajectory.stamps_ns, run.trajectory.poses, replace=True)
    map_from_world = inverse(np.array(report["trajectory"]["ate"]["alignment_xyt"]))
    keyframes = run.slam.keyframe_poses()
    write_landmarks(out / "landmarks.csv", mapped, replace=True)
    plot_run(run.grid, out / "trajectory.png", compose(map_from_world, recording.scans.poses), run.trajectory.poses,
             run.odometry.poses, [(keyframes[i], keyframes[j]) for i, j in run.slam.loop_edges()],
             (mapped.ids, mapped.positions, mapped.covariances))
    draw_detections(recording.log, score, recording.frames, world, mount, out / "camera_detections.png")
    seconds["total"] = time.monotonic() - started
    write_report(out, report)
    return report
