"""`trundle daemon` as a process: systemd notify, `trundle status`, SIGHUP, SIGTERM, SIGKILL, bad config.

The device is the real camera driver reading an MJPEG clip (``file://``, paced and looped), so
the daemon runs exactly as under systemd.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import pytest

from tests.cli_run import trundle
from trundle.logs.reader import LogReader
from trundle.tools.sim.camera_render import CameraPose, CameraRenderer
from trundle.tools.sim.world import load_world

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    path = tmp_path_factory.mktemp("clip") / "corridor.avi"
    renderer = CameraRenderer(load_world())
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 20, (640, 480))
    for i in range(20):
        writer.write(renderer.render(CameraPose(8.0 + 0.1 * i, 5.25, 0.45, 0.0)))
    writer.release()
    return path


def write_config(tmp_path: Path, clip: Path, extra: str = "") -> Path:
    path = tmp_path / "robot.toml"
    path.write_text(f"""
[robot]
name = "proc"
[camera]
url = "file://{clip}"
pace = true
loop = true
[logger]
folder = "{tmp_path / 'logs'}"
flush_period_s = 0.2
[status]
socket = "{tmp_path / 'status.sock'}"
diagnostics_period_s = 0.2
[disk]
min_free_mb = 1
{extra}
""")
    return path


class Notify:
    """A datagram socket standing in for systemd's NOTIFY_SOCKET, read continuously as systemd does."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self.cursor = 0
        self.closed = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self.closed.is_set():
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except (TimeoutError, OSError):
                continue

    def wait_for(self, prefix: str, timeout_s: float = 90.0) -> str:
        """The next message (after the last one returned) starting with ``prefix``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for i in range(self.cursor, len(self.messages)):
                if self.messages[i].startswith(prefix):
                    self.cursor = i + 1
                    return self.messages[i]
            time.sleep(0.02)
        raise AssertionError(f"no {prefix!r} from the daemon; got {self.messages[-5:]}")

    def close(self) -> None:
        self.closed.set()
        self.thread.join()
        self.sock.close()


def start(tmp_path: Path, config: Path, notify: Notify) -> subprocess.Popen:
    env = {**os.environ, "NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "200000",
           "WATCHDOG_PID": "", "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-m", "trundle.tools.cli", "daemon", "--config", str(config)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_until(condition, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_notify_status_sighup_and_sigterm(tmp_path, clip, capsys):
    notify = Notify(tmp_path / "notify.sock")
    proc = start(tmp_path, write_config(tmp_path, clip), notify)
    try:
        assert notify.wait_for("READY=1")
        notify.wait_for("WATCHDOG=1")
        notify.wait_for("WATCHDOG=1")
        wait_until(lambda: "camera streaming" in notify.wait_for("STATUS="), timeout_s=30)
        code, out, err = trundle(capsys, "status", "--socket", str(tmp_path / "status.sock"), "--json")
        assert code == 0, err
        status = json.loads(out)
        camera = status["devices"][0]
        assert camera["name"] == "camera" and camera["state"] == "streaming" and camera["crashes"] == 0
        assert status["logger"]["recording"] and status["daemon"]["pid"] == proc.pid
        code, out, _ = trundle(capsys, "status", "--config", str(tmp_path / "robot.toml"))
        assert code == 0 and "camera" in out and "recording" in out

        logs = tmp_path / "logs"
        proc.send_signal(signal.SIGHUP)
        wait_until(lambda: len(list(logs.glob("*.mcap"))) == 1 and len(list(logs.glob("*.mcap.active"))) == 1)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
        notify.wait_for("STOPPING=1")
    finally:
        if proc.poll() is None:
            proc.kill()
        notify.close()
    files = sorted(logs.glob("*.mcap"))
    assert len(files) == 2 and not list(logs.glob("*.active"))
    for path in files:
        with LogReader(path) as reader:
            topics = reader.info().topics
        assert topics["/camera/image_raw/compressed"].count > 0
        assert "/camera/camera_info" in topics and "/diagnostics" in topics
    assert not (tmp_path / "status.sock").exists()
    code, _, err = trundle(capsys, "status", "--socket", str(tmp_path / "status.sock"))
    assert code == 2 and "no trundle daemon" in err


def test_signals_in_quick_succession_still_stop_it(tmp_path, clip):
    """A second signal landing inside the first one's handler once deadlocked the daemon (the
    handler took the wake event's lock): SIGHUP then SIGTERM twice, as fast as they can be sent."""
    notify = Notify(tmp_path / "notify.sock")
    proc = start(tmp_path, write_config(tmp_path, clip), notify)
    try:
        assert notify.wait_for("READY=1")
        for sig in (signal.SIGHUP, signal.SIGTERM, signal.SIGTERM, signal.SIGINT):
            proc.send_signal(sig)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        notify.close()
    assert not list((tmp_path / "logs").glob("*.active"))


def test_the_signal_handlers_take_no_lock(tmp_path):
    """What made two quick SIGTERMs freeze the daemon: its handler called ``Event.set``, and the
    second handler waited for the lock the first held. Now a handler returns even while that lock is held."""
    from tests.test_daemon import ScriptedDriver, config
    from trundle.tools.daemon.service import Daemon

    daemon = Daemon(config(tmp_path), make_driver=lambda family, url, sink, options: ScriptedDriver(family, sink))
    for handler in (daemon._on_stop_signal, daemon._on_split_signal):
        with daemon._wake._cond:  # as when the first handler is inside Event.set
            caller = threading.Thread(target=handler, args=(signal.SIGTERM, None), daemon=True)
            caller.start()
            caller.join(2.0)
            assert not caller.is_alive(), f"{handler.__name__} waits for the wake event's lock"
    assert daemon._stop_requested and daemon._split_requested


def test_sigkill_leaves_a_log_that_recover_restores(tmp_path, clip, capsys):
    notify = Notify(tmp_path / "notify.sock")
    proc = start(tmp_path, write_config(tmp_path, clip), notify)
    try:
        notify.wait_for("READY=1")
        time.sleep(1.5)  # several flush periods
        proc.kill()
        proc.wait(10)
    finally:
        notify.close()
    active, = (tmp_path / "logs").glob("*.mcap.active")
    out = tmp_path / "restored.mcap"
    code, _, err = trundle(capsys, "recover", str(active), str(out))
    assert code == 0, err
    with LogReader(out) as reader:
        assert reader.info().topics["/camera/image_raw/compressed"].count >= 10


def test_bad_config_is_one_line_naming_the_key(tmp_path, clip, capsys):
    config = write_config(tmp_path, clip, "[processing]\nslam = 1\n")
    code, _, err = trundle(capsys, "daemon", "--config", str(config))
    assert code == 2 and err.count("\n") == 1 and "processing.slam = 1" in err
    config.write_text(config.read_text().replace("[processing]\nslam = 1\n", "").replace("pace = true", "pase = true"))
    code, _, err = trundle(capsys, "daemon", "--config", str(config))
    assert code == 2 and err.count("\n") == 1 and "camera.pase" in err  # the driver's model names the bad option
    config.write_text("[logger\n")
    code, _, err = trundle(capsys, "daemon", "--config", str(config))
    assert code == 2 and err.count("\n") == 1 and "not valid TOML" in err
    assert not (tmp_path / "logs").exists()
