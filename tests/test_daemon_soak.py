"""Soak: `trundle daemon` against the simulated robot's emulators with faults on: laser and CAN
adapter unplugged in turn, laser checksum errors, camera stalls. The daemon never dies, every
device recovers, the log has gaps only while a device is away, and SIGTERM leaves a clean file.

The short version runs in CI; the long one (`make soak`) unplugs every 30 s for 5 minutes.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from trundle.logs.reader import LogReader
from trundle.tools.config.toml_text import format_config
from trundle.tools.daemon.status import query_status
from trundle.tools.emulators.faults import FaultPlan
from trundle.tools.emulators.sim_devices import SimDevices
from trundle.tools.sim.robot import RobotSim
from trundle.tools.sim.world import load_world

REPO = Path(__file__).resolve().parents[1]
RECOVERY_S = 6.0  # reconnect back-off + handshake allowed after a device comes back
TOPICS = {"lrf": "/scan", "can": "/wheels", "camera": "/camera/image_raw/compressed"}


def status_or_none(path: Path):
    try:
        return query_status(path)
    except Exception:
        return None


def all_streaming(path: Path) -> bool:
    status = status_or_none(path)
    return status is not None and all(d["state"] == "streaming" and any(d["rates_hz"].values())
                                      for d in status["devices"])


def summary(path: Path) -> list:
    """Each device's state, rates, errors and last error (for failure messages)."""
    status = status_or_none(path)
    return status and [
        (d["name"], d["state"], d["rates_hz"], d["reconnects"], d["last_error"]) for d in status["devices"]
    ]


def soak(tmp_path: Path, duration_s: float, period_s: float, away_s: float) -> None:
    sim = RobotSim(load_world(), laps=max(1, math.ceil(duration_s / 55.0)))
    socket_path = tmp_path / "status.sock"
    faults = FaultPlan(rates={"checksum": 0.02}, seed=3)
    with SimDevices(sim, tmp_path / "dev", camera_fps=10.0, lrf_faults=faults) as devices:
        config = tmp_path / "robot.toml"
        tables = devices.device_tables()
        tables["lrf"]["timeout_s"] = 2.0  # a silent laser is declared lost after 2 s (not 0.5): shared CI hosts stall
        config.write_text(format_config({"robot": {"name": "soak"}, **tables,
                            "logger": {"folder": str(tmp_path / "logs"), "flush_period_s": 0.5},
                            "status": {"socket": str(socket_path), "diagnostics_period_s": 1.0},
                            "disk": {"min_free_mb": 1.0}}))
        proc = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "daemon", "--config", str(config)],
                                cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(REPO)},
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        windows: dict[str, list[tuple[int, int]]] = {name: [] for name in TOPICS}
        try:
            deadline = time.monotonic() + 120
            while not all_streaming(socket_path):
                assert proc.poll() is None and time.monotonic() < deadline, "daemon did not come up"
                time.sleep(0.2)
            started = time.monotonic()
            schedule = [(k * period_s + offset * period_s / 3, name) for k in range(int(duration_s // period_s))
                        for offset, name in enumerate(("lrf", "can", "camera"))]
            for at, name in schedule:
                while time.monotonic() < started + at:
                    assert proc.poll() is None, proc.stderr.read()
                    time.sleep(0.05)
                now = time.time_ns()
                windows[name].append((now, now + int(away_s * 1e9)))
                {"lrf": devices.unplug_lrf, "can": devices.unplug_can, "camera": devices.stall_camera}[name](away_s)
            while time.monotonic() < started + duration_s:
                assert proc.poll() is None, proc.stderr.read()
                time.sleep(0.2)
            deadline = time.monotonic() + 60
            while not all_streaming(socket_path):  # every device recovers
                assert proc.poll() is None and time.monotonic() < deadline, summary(socket_path)
                time.sleep(0.2)
            time.sleep(1.0)
            status = query_status(socket_path)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0, proc.stderr.read()
        finally:
            if proc.poll() is None:
                proc.kill()
        end_ns = time.time_ns()

        produced = {name: devices.produced(name) for name in TOPICS}
    faults_per_device = len(windows["lrf"])
    devices_status = {d["name"]: d for d in status["devices"]}
    assert devices_status["lrf"]["reconnects"] >= faults_per_device
    assert devices_status["can"]["reconnects"] >= faults_per_device
    assert devices_status["lrf"]["counters"].get("checksum_errors", 0) > 0
    assert all(d["crashes"] == 0 for d in devices_status.values())
    assert not list((tmp_path / "logs").glob("*.active"))  # SIGTERM: every file closed and renamed
    times: dict[str, list[int]] = {topic: [] for topic in TOPICS.values()}
    for path in sorted((tmp_path / "logs").glob("*.mcap")):
        with LogReader(path) as reader:
            for msg in reader.messages(topics=list(TOPICS.values())):
                times[msg.topic].append(msg.log_time_ns)
    for name, topic in TOPICS.items():
        stamps = np.array(sorted(times[topic]))
        assert stamps.size > 0 and stamps[-1] > end_ns - 10e9, f"{name} did not recover"
        gaps = np.flatnonzero(np.diff(stamps) > 1.0e9)
        for i in gaps:  # a gap of more than a second: the device was away, or its emulator starved
            begin, end = stamps[i], stamps[i + 1]
            away = any(begin < w_end and end > w_begin and end <= w_end + RECOVERY_S * 1e9
                       for w_begin, w_end in windows[name])
            inside = produced[name][(produced[name] > begin) & (produced[name] < end)]
            starved = np.diff(np.concatenate(([begin], inside, [end]))).max() > 0.5e9
            t00 = windows["lrf"][0][0]
            assert away or starved, (
                name,
                (begin - t00) / 1e9,
                (end - begin) / 1e9,
                "lost while the emulator was producing",
                {n: [(a - t00) / 1e9 for a, _ in w] for n, w in windows.items()},
                devices_status[name]["counters"],
                np.diff(inside).max() / 1e9 if inside.size > 1 else None,
                {
                    t: [((a - t00) / 1e9, (b - a) / 1e9) for a, b in pairwise(np.sort(v)) if b - a > 0.3e9]
                    for t, v in times.items()
                },
            )


# Real processes on emulated ptys, sharing 2 cores with the rest of the suite: seen failing
# once in ~10 suite runs under load (a device not back within 60 s); one rerun, and a report.
@pytest.mark.flaky(reruns=1)
def test_short_soak_with_unplugs_checksum_errors_and_camera_stall(tmp_path):
    soak(tmp_path, duration_s=15.0, period_s=15.0, away_s=2.5)


@pytest.mark.slow
def test_long_soak_unplugging_every_30_seconds(tmp_path):
    soak(tmp_path, duration_s=300.0, period_s=30.0, away_s=3.0)
