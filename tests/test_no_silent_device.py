"""No silent device: a device that cannot be opened, or is connected but gives nothing usable, is
a WARN/ERROR diagnostic naming the likely cause, said once in one line by `record` and the
daemon, and its recovery is said too; `record` ends with exit code 1 when a device recorded
nothing; the daemon waits for missing devices of every kind and stays up."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from trundle.drivers.health import HealthReporter
from trundle.drivers.lrf import driver_from_url
from trundle.logs import messages as m
from trundle.tools.cli.main import main
from trundle.tools.config.toml_text import format_config
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import parse_faults
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import FLAGS, KINDS, MODELS, ScipDevice

ROOT = Path(__file__).resolve().parents[1]


def refused_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]  # closed again: nothing listens there


@pytest.mark.parametrize(
    "flags, cause",
    [
        (
            ["--lrf", "scip2:///dev/nonexistent"],
            "No such file or directory: '/dev/nonexistent' (not plugged in, or a wrong path)",
        ),
        (["--lrf", "scip2:///dev/null"], "(not a serial port)"),
        (["--lrf", "scip2://{regular}"], "(not a serial port)"),
        (["--lrf", "scip2+tcp://127.0.0.1:{port}"], "Connection refused (nothing listens at that address and port)"),
        (["--can", "slcan:///dev/nonexistent", "--encoders", "odrive:0,1"], "(not plugged in, or a wrong path)"),
        (["--can", "socketcan://nope0", "--encoders", "odrive:0,1"], "cannot open socketcan://nope0"),
    ],
)
def test_record_says_why_a_device_gives_nothing(flags, cause, tmp_path, capsys):
    regular = tmp_path / "notes.txt"
    regular.write_text("not a serial port")
    argv = ["record", *(f.format(regular=regular, port=refused_port()) for f in flags), "--duration", "4",
            "-o", str(tmp_path / "run.mcap")]
    assert main(argv) == 1
    err = capsys.readouterr().err.splitlines()
    family = flags[0].lstrip("-")
    assert len(err) == 3 and all(line.startswith(f"trundle record: {family}: ") for line in err[:2]), err
    assert "ERROR: " in err[0] and cause in err[0]  # said while recording
    assert "recorded no " in err[1] and cause in err[1]  # and at the end, with the exit code
    assert err[2] == (f"trundle record: no device recorded anything: no log was kept ({tmp_path / 'run.mcap'} "
                      "not written)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]  # a log of diagnostics alone is not kept


def test_replies_without_valid_scans_are_a_warning_naming_the_faults(tmp_path):
    model = MODELS["utm-30lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles), parse_faults("checksum=1.0", KINDS, FLAGS),
                        time.time_ns())
    said: list[str] = []
    reporter = HealthReporter(said.append, grace_s=0.5)
    with DeviceServer(device, link_path=tmp_path / "lrf"):
        driver = driver_from_url(f"scip2://{tmp_path / 'lrf'}", lambda *a: None)
        driver.silence_s = 1.0
        driver.start()
        deadline = time.monotonic() + 30
        while not said and time.monotonic() < deadline:
            reporter.update([driver.diagnostics()])
            time.sleep(0.1)
        driver.stop()
    assert said and said[0].startswith("lrf: WARN: connected, but no scans for ")
    assert "replies, but no valid scans (" in said[0] and "checksum errors" in said[0]


def test_the_reporter_says_bad_worse_and_recovered_once_each():
    said: list[str] = []
    reporter = HealthReporter(said.append, grace_s=2.0)
    status = lambda level, text: m.DiagnosticStatus(level, "lrf", text)  # noqa: E731
    reporter.update([status(m.WARN, "connecting")], now=0.0)
    reporter.update([status(m.OK, "streaming")], now=1.0)  # a start-up within the grace: nothing said
    for t in (10.0, 11.0, 12.5, 13.0):
        reporter.update([status(m.WARN, "no scans")], now=t)
    reporter.update([status(m.ERROR, "cannot open")], now=14.0)
    reporter.update([status(m.WARN, "connecting")], now=15.0)  # better, still bad: nothing new
    reporter.update([status(m.OK, "streaming")], now=16.0)
    reporter.update([status(m.STALE, "stopped")], now=17.0)
    assert said == ["lrf: WARN: no scans", "lrf: ERROR: cannot open", "lrf: recovered: streaming"]
    assert reporter.reported == {}


def test_the_daemon_waits_for_missing_devices_and_says_so(tmp_path):
    """The example robot without its hardware: no device exits the daemon (a missing camera did,
    and systemd restart-looped it); each missing device is said on stderr, and the daemon runs."""
    config = tmp_path / "robot.toml"
    config.write_text(format_config({
        "robot": {"name": "bare"},
        "lrf": {"url": "scip2:///dev/trundle-lrf-missing"},
        "can": {"url": "slcan:///dev/trundle-can-missing@1000000", "encoders": "odrive:0,1",
                "wheel_radius_m": 0.1, "track_m": 0.5},
        "camera": {"url": "v4l2:///dev/trundle-camera-missing?width=640&height=480&fps=30&fourcc=MJPG"},
        "logger": {"folder": str(tmp_path / "logs")}, "disk": {"min_free_mb": 1.0},
        "status": {"socket": str(tmp_path / "status.sock"), "diagnostics_period_s": 0.5}}))
    daemon = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "daemon", "--config", str(config)],
                              cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        lines: list[str] = []
        deadline = time.monotonic() + 60
        assert daemon.stderr is not None
        os.set_blocking(daemon.stderr.fileno(), False)
        while len(lines) < 3 and time.monotonic() < deadline and daemon.poll() is None:
            lines += [line for line in (daemon.stderr.readline() for _ in range(10)) if line]
            time.sleep(0.2)
        assert daemon.poll() is None, "the daemon exited: " + "".join(lines)
        status = subprocess.run([sys.executable, "-m", "trundle.tools.cli", "status", "--socket",
                                 str(tmp_path / "status.sock"), "--json"], cwd=ROOT, capture_output=True, text=True)
    finally:
        daemon.send_signal(signal.SIGTERM)
        rest = daemon.communicate(timeout=60)[1]
    said = "".join(lines)
    assert "bare/lrf: ERROR: " in said and "/dev/trundle-lrf-missing" in said
    assert "bare/can: ERROR: " in said and "/dev/trundle-can-missing" in said
    assert "bare/camera: ERROR: " in said and "no camera at /dev/trundle-camera-missing" in said
    assert daemon.returncode == 0 and "Traceback" not in said + rest
    assert '"state": "running"' in status.stdout


def test_a_camera_whose_every_frame_is_corrupt_says_so():
    from trundle.drivers.camera import driver_from_url as camera_from_url
    from trundle.tools.emulators.camera_emulator import CameraEmulator

    with CameraEmulator(fps=20, width=160, height=120, corrupt_every=1) as emulator:
        driver = camera_from_url(emulator.url, lambda *a: None, {})
        driver.silence_s = 1.0
        driver.start()
        deadline = time.monotonic() + 30
        while "no frames" not in driver.diagnostics().message and time.monotonic() < deadline:
            time.sleep(0.1)
        status = driver.diagnostics()
        driver.stop()
    assert status.level == m.WARN and "corrupt frames dropped (last: " in status.message, status.message
    assert driver.counters["frames"] == 0 and driver.counters["corrupt"] > 5
