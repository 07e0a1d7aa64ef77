"""CPU of `trundle daemon` on a full emulated robot, against `trundle record` of the same devices.

Devices (the world simulator driving the real emulators, in this process): a UTM-30LX laser at
40 Hz with 1081 beams (SCIP 2.0 pty), four ODrive axes sending encoder estimates at 100 Hz over
an SLCAN pty, and a 1280x720 MJPEG camera at 30 fps (frames rendered once into a clip, then
served byte for byte so the emulator costs little). Each configuration runs as its own process
and its CPU (user + system, all threads, from /proc) is measured over the same window:

1. baseline: ``trundle record`` of the three devices (drivers + logger, nothing else);
2. ``trundle daemon``, logging only (goal < 15 % of one core);
3. ``trundle daemon`` with online wheel odometry and SLAM (goal < 20 % of one core with no scan skipped:
   the scans its SLAM processed and skipped over the window, from its status socket, are printed).

Run: python tools/bench/bench_daemon.py [--duration 30]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

import trundle
from trundle.logs.reader import LogReader
from trundle.logs.topics import CAN_RX_TOPIC, IMAGE_TOPIC, SCAN_TOPIC, WHEELS_TOPIC
from trundle.tools.bench import report
from trundle.tools.config.toml_text import format_config
from trundle.tools.daemon.status import query_status
from trundle.tools.emulators.sim_devices import SimDevices
from trundle.tools.sim.camera_render import CameraRenderer
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import load_world

# the folder holding the `trundle` this bench imports, so the measured commands run the same code (the
# repository root is the package itself: on PYTHONPATH it would leave them to whatever trundle is installed)
PACKAGE_PARENT = Path(trundle.__file__).absolute().parents[1]
WIDTH, HEIGHT, FPS = 1280, 720, 30.0
TOPICS = {SCAN_TOPIC: "scan", WHEELS_TOPIC: "wheels", CAN_RX_TOPIC: "can_frames", IMAGE_TOPIC: "camera"}


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def render_clip(sim: RobotSim, path: Path, seconds: float = 4.0) -> Path:
    """An MJPEG clip of what the camera sees along the route (the emulator serves its packets)."""
    renderer = CameraRenderer(sim.world, sim.camera.scaled(WIDTH, HEIGHT))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    for i in range(int(seconds * FPS)):
        writer.write(renderer.render(sim.camera_pose_at(10.0 + i / FPS)))
    writer.release()
    return path


def measure(command: list[str], folder: Path, logs: Path, warmup_s: float, duration_s: float,
            socket_path: Path | None) -> dict[str, float]:
    """Start ``command``, let it warm up, and return its CPU share over ``duration_s``."""
    process = subprocess.Popen(command, cwd=folder, env={**os.environ, "PYTHONPATH": str(PACKAGE_PARENT)},
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while socket_path is not None:
            try:
                status = query_status(socket_path)
                if all(d["state"] == "streaming" for d in status["devices"]):
                    break
            except Exception:
                pass
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"daemon did not come up: {process.stderr.read() if process.stderr else ''}")
            time.sleep(0.2)
        time.sleep(warmup_s)
        scans0 = scan_counts(socket_path)
        cpu0, wall0 = cpu_seconds(process.pid), time.monotonic()
        time.sleep(duration_s)
        cpu1, wall1 = cpu_seconds(process.pid), time.monotonic()
        scans = {key: value - scans0[key] for key, value in scan_counts(socket_path).items()}
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
    return {"cpu_percent": 100.0 * (cpu1 - cpu0) / (wall1 - wall0), **scans, **logged_rates(logs, wall0, wall1)}


def scan_counts(socket_path: Path | None) -> dict[str, float]:
    """Scans the daemon's SLAM has processed and skipped (behind real time, it takes the newest) so far;
    none without SLAM or a status socket."""
    if socket_path is None:
        return {}
    processing = query_status(socket_path).get("processing") or {}
    if "slam" not in processing:
        return {}
    return {"slam_scans_processed": float(processing["slam"]["scans"]),
            "slam_scans_skipped": float(processing["skipped_scans"])}


def logged_rates(logs: Path, start_s: float, end_s: float) -> dict[str, float]:
    """Messages per second of the main topics in the logs between two monotonic times (what was
    really recorded, so every configuration is seen to do the same work)."""
    offset = time.time() - time.monotonic()
    window = ((start_s + offset) * 1e9, (end_s + offset) * 1e9)
    counts = dict.fromkeys(TOPICS, 0)
    for path in sorted(logs.glob("*.mcap")):
        with LogReader(path) as reader:
            for msg in reader.raw_messages(topics=list(TOPICS), start_ns=int(window[0]), end_ns=int(window[1])):
                counts[msg.topic] += 1
    return {f"{name}_hz": counts[topic] / (end_s - start_s) for topic, name in TOPICS.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0, help="seconds measured per configuration")
    parser.add_argument("--warmup", type=float, default=5.0)
    args = parser.parse_args()
    sim = RobotSim(load_world(), laps=4)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        clip = render_clip(sim, folder / "camera.avi")
        figures: dict[str, float] = {}
        runs = {"record": None, "daemon_logging": {"odometry": False, "slam": False},
                "daemon_odometry_slam": {"odometry": True, "slam": True}}
        for name, processing in runs.items():
            with SimDevices(sim, folder / f"dev-{name}", wheels=4, camera_size=(WIDTH, HEIGHT), camera_fps=FPS,
                            camera_clip=clip) as devices:
                tables = devices.device_tables()
                logs = folder / f"logs-{name}"
                logs.mkdir()
                if processing is None:
                    config = folder / "record.toml"
                    config.write_text(format_config({k: tables[k] for k in ("lrf", "can", "camera")}))
                    command = [sys.executable, "-m", "trundle.tools.cli", "record", "--config", str(config),
                               "--duration", str(args.duration + args.warmup + 30), "-o", str(logs / "run.mcap")]
                    result = measure(command, folder, logs, args.warmup + 5.0, args.duration, None)
                else:
                    socket_path = folder / f"{name}.sock"
                    config = folder / f"{name}.toml"
                    config.write_text(format_config({
                        "robot": {"name": "bench"}, **tables,
                        "logger": {"folder": str(logs)}, "status": {"socket": str(socket_path)},
                        "disk": {"min_free_mb": 100.0}, "processing": processing}))
                    command = [sys.executable, "-m", "trundle.tools.cli", "daemon", "--config", str(config)]
                    result = measure(command, folder, logs, args.warmup, args.duration, socket_path)
            for key, value in result.items():
                figures[f"{name}_{key}"] = value
        base = figures["record_cpu_percent"]
        figures["daemon_logging_vs_record_ratio"] = figures["daemon_logging_cpu_percent"] / base
        figures["daemon_slam_vs_record_ratio"] = figures["daemon_odometry_slam_cpu_percent"] / base
        figures["goal_daemon_logging_below_15_percent"] = figures["daemon_logging_cpu_percent"] < 15.0
        figures["goal_daemon_slam_below_20_percent"] = figures["daemon_odometry_slam_cpu_percent"] < 20.0
        figures["goal_no_scan_skipped"] = figures["daemon_odometry_slam_slam_scans_skipped"] == 0
    report.write("daemon", figures)


if __name__ == "__main__":
    main()
