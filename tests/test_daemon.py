"""The daemon in-process with scripted drivers: supervision, status socket, disk guard, splits."""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from trundle.drivers.lifecycle import Backoff, Driver
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError
from trundle.logs.reader import LogReader
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main
from trundle.tools.config.robot import DiskConfig, LoggerConfig, parse_config
from trundle.tools.daemon.disk_guard import DiskGuard
from trundle.tools.daemon.service import Daemon
from trundle.tools.daemon.status import StatusServer, format_status, query_status

Usage = namedtuple("Usage", "total used free")


class ScriptedDriver(Driver):
    """Publishes a small scan every ``period_s``; can be told to crash (a bug) or fail (a device fault)."""

    def __init__(self, name, sink, period_s=0.01):
        super().__init__(name, sink, hardware_id=f"scripted:{name}", backoff=Backoff(0.05, 0.2))
        self.period_s = period_s
        self.crash_next = threading.Event()
        self.fault_next = threading.Event()
        self.opened = 0

    def open(self):
        self.opened += 1

    def read_once(self):
        if self.crash_next.is_set():
            self.crash_next.clear()
            raise ValueError("scripted bug")  # a bug, not a device fault: no reconnect
        if self.fault_next.is_set():
            self.fault_next.clear()
            raise DeviceError("scripted unplug")
        time.sleep(self.period_s)
        self.counters["scans"] += 1
        self.publish("/scan", m.LaserScan(self.clock(), "laser", -1.0, 1.0, 0.5, 0.0, 0.1, 0.02, 30.0,
                                          np.ones(5, np.float32)))

    def close(self):
        pass

    def static_messages(self):
        return [("/tf_static", m.TFMessage((m.TransformStamped.planar(0, "base_link", "laser", 0.2, 0.0, 0.0),)))]


def config(tmp_path, **tables):
    data = {"robot": {"name": "testbot"},
            "lrf": {"url": "scip2:///dev/scripted-a"},  # a real URL (checked); the test makes its own driver
            "logger": {"folder": str(tmp_path / "logs"), "flush_period_s": 0.1},
            "status": {"socket": str(tmp_path / "status.sock"), "diagnostics_period_s": 0.2},
            "supervision": {"restart_delay_s": 0.1, "stop_timeout_s": 2.0},
            "disk": {"check_period_s": 0.1, "min_free_mb": 100.0},
            "transforms": [{"parent": "base_link", "child": "camera", "xyz": [0.25, 0.0, 0.45]}]}
    for name, table in tables.items():
        data[name] = {**data.get(name, {}), **table}
    return parse_config(data, "test.toml")


class Running:
    """A daemon on a thread, its drivers kept for the test to poke."""

    def __init__(self, cfg):
        self.drivers: dict[str, ScriptedDriver] = {}
        self.daemon = Daemon(cfg, make_driver=self._make)
        self.thread = threading.Thread(target=self.daemon.run, kwargs={"install_signals": False})

    def _make(self, family, url, sink, options):
        driver = ScriptedDriver(family, sink)
        self.drivers[family] = driver
        return driver

    def __enter__(self):
        self.thread.start()
        wait_for(lambda: self.daemon.state == "running")
        return self

    def __exit__(self, *exc):
        self.daemon.stop()
        self.thread.join(10)
        assert not self.thread.is_alive()


def wait_for(condition, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def read_log(folder: Path):
    files = sorted(folder.glob("*.mcap"))
    out = []
    for path in files:
        with LogReader(path) as reader:
            out.append((path, list(reader.messages())))
    return out


def test_status_socket_reports_devices_logger_and_disk(tmp_path):
    with Running(config(tmp_path)) as run:
        wait_for(lambda: run.daemon.supervised[0].rates.rates.get("/scan", 0) > 20)
        status = query_status(tmp_path / "status.sock")
        device = status["devices"][0]
        assert device["name"] == "lrf" and device["state"] == "streaming"
        assert 20 < device["rates_hz"]["/scan"] <= 110
        assert device["counters"]["scans"] > 0 and device["crashes"] == 0
        log = status["logger"]
        assert log["recording"] and log["file"].endswith(".mcap.active") and Path(log["file"]).exists()
        assert log["dropped"] == 0 and log["written"] > 0
        assert status["disk"]["free_bytes"] > 0 and status["disk"]["action"] == "delete_oldest"
        text = format_status(status)
        assert "lrf" in text and "/scan" in text and "recording" in text
    assert not (tmp_path / "status.sock").exists()
    (path, messages), = read_log(tmp_path / "logs")
    topics = {msg.topic for msg in messages}
    assert {"/scan", "/diagnostics", "/tf_static"} <= topics
    static = [msg.msg for msg in messages if msg.topic == "/tf_static"][-1]
    assert {t.child_frame_id for t in static.transforms} == {"laser", "camera"}  # config + driver, merged
    assert not list((tmp_path / "logs").glob("*.active"))


def test_crashed_driver_thread_is_restarted_and_reported(tmp_path, capfd):
    with Running(config(tmp_path)) as run:
        driver = run.drivers["lrf"]
        wait_for(lambda: driver.counters["scans"] > 5)
        driver.crash_next.set()
        wait_for(lambda: run.daemon.supervised[0].crashes == 1)
        crashed = query_status(tmp_path / "status.sock")["devices"][0]
        assert crashed["last_crash"].startswith("ValueError: scripted bug at test_daemon.py:")
        assert crashed["reconnects"] == 0 and crashed["errors"] == 0  # crashed, not reconnected
        err = capfd.readouterr().err  # the daemon's log: one line, then the traceback
        assert "trundle daemon: driver lrf crashed (ValueError: scripted bug at test_daemon.py:" in err
        assert "Traceback (most recent call last):" in err and "in read_once" in err
        assert 'raise ValueError("scripted bug")' in err and "\nValueError: scripted bug\n" in err
        before = driver.counters["scans"]
        wait_for(lambda: driver.counters["scans"] > before + 5)  # running again
        assert driver.opened == 2
        wait_for(lambda: query_status(tmp_path / "status.sock")["devices"][0]["state"] == "streaming")
        driver.fault_next.set()  # a device fault is the driver's own reconnect, not a crash
        wait_for(lambda: driver.counters["reconnects"] >= 2)
        assert run.daemon.supervised[0].crashes == 1
        time.sleep(0.3)
    (_, messages), = read_log(tmp_path / "logs")
    reports = [s for msg in messages if msg.topic == "/diagnostics" for s in msg.msg.status if s.name == "testbot/lrf"]
    assert any(s.level == m.ERROR and "scripted bug" in s.message for s in reports)
    assert reports[-1].level != m.ERROR


def test_split_request_starts_a_new_file_with_the_static_transforms(tmp_path):
    with Running(config(tmp_path)) as run:
        wait_for(lambda: run.drivers["lrf"].counters["scans"] > 5)
        run.daemon.request_split()
        wait_for(lambda: len(run.daemon.logger.files) == 1)
        wait_for(lambda: run.drivers["lrf"].counters["scans"] > 30)
    logs = read_log(tmp_path / "logs")
    assert [p.name.rsplit("_", 1)[1] for p, _ in logs] == ["0.mcap", "1.mcap"]
    for _, messages in logs:
        topics = [msg.topic for msg in messages]
        assert "/tf_static" in topics and topics.count("/scan") > 0


def scan_message():
    return m.LaserScan(1, "laser", -1.0, 1.0, 0.5, 0.0, 0.1, 0.02, 30.0, np.ones(5, np.float32))


def log_folder_of_several_owners(folder: Path) -> dict[str, Path]:
    """A log folder as a user met it: ``aaa_precious.mcap`` put there by hand (a valid MCAP without
    trundle's metadata, the oldest file), another robot's log, a damaged log of this robot, a text
    file and two logs this robot's daemon wrote (its logger, its metadata), each with its own age."""
    folder.mkdir()
    files = {name: folder / name for name in ("aaa_precious.mcap", "otherbot_20240101-000000.mcap",
                                              "testbot_torn.mcap", "notes.txt", "testbot_20240102-000000.mcap",
                                              "testbot_20240103-000000.mcap")}
    with open(files["aaa_precious.mcap"], "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="my own tool")
        writer.add_metadata("notes", {"keep": "forever"})
        writer.finish()
    for name, robot in (("otherbot_20240101-000000.mcap", "otherbot"), ("testbot_20240102-000000.mcap", "testbot"),
                        ("testbot_20240103-000000.mcap", "testbot")):
        with Logger(files[name], metadata={"command": "daemon", "robot": {"name": robot}}) as logger:
            logger.write("/scan", scan_message())
    whole = files["testbot_20240103-000000.mcap"].read_bytes()
    files["testbot_torn.mcap"].write_bytes(whole[: len(whole) - 100])  # its summary torn off
    files["notes.txt"].write_text("field notes\n")
    for age, path in enumerate(files.values()):
        os.utime(path, (1000 + age, 1000 + age))
    return files


def test_disk_guard_deletes_only_this_robots_logs_oldest_first(tmp_path, monkeypatch, capfd):
    files = log_folder_of_several_owners(tmp_path / "logs")
    free = {"bytes": 50e6}
    real = shutil.disk_usage

    def usage(path):
        total = real(path).total
        return Usage(total, total - free["bytes"], free["bytes"])

    monkeypatch.setattr(shutil, "disk_usage", usage)
    original_unlink = Path.unlink
    unlinked = []

    def unlink(self, missing_ok=False):
        original_unlink(self, missing_ok=missing_ok)
        unlinked.append(self.name)
        free["bytes"] += 30e6  # each deleted log frees 30 MB

    monkeypatch.setattr(Path, "unlink", unlink)
    with Running(config(tmp_path)) as run:
        wait_for(lambda: run.daemon.logger is not None and run.drivers["lrf"].counters["scans"] > 5)
        own = ["testbot_20240102-000000.mcap", "testbot_20240103-000000.mcap"]
        assert unlinked == own  # 50 + 2 x 30 MB >= the 100 MB floor, the older first
        assert run.daemon.disk_guard.status["deleted"] == own
        kept = ["aaa_precious.mcap", "otherbot_20240101-000000.mcap", "testbot_torn.mcap", "notes.txt"]
        assert [name for name, path in files.items() if path.exists()] == kept
        assert run.daemon.logger.current_path.exists()
    said = [line for line in capfd.readouterr().err.splitlines() if "disk low" in line]
    assert said == [f"trundle daemon: disk low: deleted 2 of this robot's logs ({', '.join(own)}) in "
                    f"{tmp_path / 'logs'}; 3 other .mcap files kept"]


def test_daemon_check_names_the_mcap_files_it_did_not_write(tmp_path, capsys):
    log_folder_of_several_owners(tmp_path / "logs")
    robot_toml = tmp_path / "robot.toml"
    robot_toml.write_text(f'[robot]\nname = "testbot"\n[lrf]\nurl = "scip2:///dev/scripted-a"\n'
                          f'[logger]\nfolder = "{tmp_path / "logs"}"\n')
    assert main(["daemon", "--config", str(robot_toml), "--check"]) == 0  # a notice, not an error
    out, err = capsys.readouterr()
    assert err == "" and out.startswith(f"{robot_toml}: ok; devices: lrf")
    notice, = out.splitlines()[1:]
    assert notice == (f"note: {tmp_path / 'logs'} holds 3 .mcap files the daemon of robot 'testbot' did not write "
                      "(aaa_precious.mcap, otherbot_20240101-000000.mcap, testbot_torn.mcap): "
                      "the disk guard never deletes them")


def test_the_disk_status_says_low_before_recording_stops_and_not_before_it_resumes(tmp_path, monkeypatch, capsys):
    """The guard stops and resumes recording from its checking thread while the status socket answers from
    another: at each transition the status must already say why (a status read between the two said
    "stopped for disk low" with "low": false)."""
    free = {"bytes": 10e6}
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(real(p).total, 0, free["bytes"]))
    seen: list[tuple[str, bool]] = []
    guard = DiskGuard(DiskConfig(min_free_mb=100.0, action="stop"), LoggerConfig(folder=tmp_path), "testbot",
                      current_log=lambda: None, stop_recording=lambda why: seen.append(("stop", guard.status["low"])),
                      resume_recording=lambda: seen.append(("resume", guard.status["low"])))
    guard.check()
    free["bytes"] = 500e6
    guard.check()
    assert seen == [("stop", True), ("resume", False)]
    assert "recording stopped: disk low" in capsys.readouterr().err


def test_disk_guard_stops_recording_and_resumes(tmp_path, monkeypatch):
    free = {"bytes": 500e6}
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: Usage(real(p).total, 0, free["bytes"]))
    with Running(config(tmp_path, disk={"action": "stop"})) as run:
        wait_for(lambda: run.drivers["lrf"].counters["scans"] > 5)
        free["bytes"] = 10e6
        wait_for(lambda: run.daemon.logger is None)
        status = query_status(tmp_path / "status.sock")
        assert not status["logger"]["recording"] and status["logger"]["paused"].startswith("disk low")
        assert status["disk"]["low"]
        first = list((tmp_path / "logs").glob("*.mcap"))
        assert len(first) == 1 and not list((tmp_path / "logs").glob("*.active"))  # closed cleanly
        unrecorded = run.daemon.unrecorded
        wait_for(lambda: run.daemon.unrecorded > unrecorded + 5)  # drivers keep running
        free["bytes"] = 105e6  # above the floor but inside the 10 % resume margin: still stopped
        time.sleep(0.4)
        assert run.daemon.logger is None
        free["bytes"] = 500e6
        wait_for(lambda: run.daemon.logger is not None)
        wait_for(lambda: run.drivers["lrf"].counters["scans"] > 60)
    logs = read_log(tmp_path / "logs")
    assert len(logs) == 2 and all("/tf_static" in {msg.topic for msg in msgs} for _, msgs in logs)


def test_second_daemon_on_the_same_socket_is_refused(tmp_path):
    from trundle.logs.errors import UserError
    with Running(config(tmp_path)):
        other = Daemon(config(tmp_path), make_driver=lambda f, u, s, o: ScriptedDriver(f, s))
        with pytest.raises(UserError, match="another trundle daemon"):
            StatusServer(other.config.status.socket, other.status)


def test_the_daemon_says_when_it_starts_and_stops(tmp_path, capfd):
    """One line each on stderr (journald, the demo's daemon.log): what runs where, and what was written."""
    with Running(config(tmp_path)) as run:
        wait_for(lambda: run.daemon.logger is not None and run.daemon.logger.stats_dict())
    lines = capfd.readouterr().err.splitlines()
    started = [line for line in lines if " started " in line]
    assert started == [f"trundle daemon: started (pid {os.getpid()}, robot testbot): lrf (scip2:///dev/scripted-a); "
                       f"recording to {run.daemon.logger_files[0]}.active; status socket {tmp_path / 'status.sock'}"]
    (stopped,) = [line for line in lines if " stopped " in line]
    written = sum(c["written"] for c in run.daemon._stop_counts.values())
    assert stopped.startswith("trundle daemon: stopped after ") and stopped.endswith(
        f" s: {written} messages in {run.daemon.logger_files[0]}")
