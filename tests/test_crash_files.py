"""Crash files (``X.mcap.active`` of a recorder that died) are recovered once, said in one line, and a
file a live recorder still writes is left to it (issue 23, item 7)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import pytest
from mcap.writer import Writer

from tests.test_daemon import Running, config
from tests.test_logger_crash import start_child
from trundle.logs.reader import LogReader, log_origin
from trundle.tools.cli.main import main


def killed_recorder(folder: Path) -> Path:
    """A recorder subprocess writing ``folder/run.mcap``, killed with SIGKILL after its first flush;
    its crash file."""
    folder.mkdir(exist_ok=True)
    proc = start_child(folder / "run.mcap")
    active = folder / "run.mcap.active"
    try:
        proc.wait(timeout=1.5)  # the recorder runs for two minutes: this only waits past its first flush
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL and active.exists()
    return active


def daemon_lines(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> list[str]:
    """Start and stop the daemon on ``tmp_path/logs``; the lines it said about recovering."""
    with Running(config(tmp_path)):
        pass
    return [line for line in capfd.readouterr().err.splitlines() if line.startswith("trundle daemon: recovered")]


def summary(log: Path) -> tuple[int, float]:
    """Messages in ``log`` and their span (s), as the recovery line gives them."""
    info = LogReader(log).info()
    return info.message_count, round(info.duration_s, 1)


def recovery_line(messages: int, seconds: float, recovered: Path) -> str:
    """The recovery line (a regular expression): a killed file's torn tail is named, as the reader says it."""
    return (rf"recovered {messages} messages \({seconds:.1f} s\) from run\.mcap\.active into "
            rf"{re.escape(str(recovered))}; stopped by [^;]+; removed the crash file run\.mcap\.active")


def test_recover_then_daemon_start_writes_no_duplicate(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    active = killed_recorder(tmp_path / "logs")
    size, mtime = active.stat().st_size, active.stat().st_mtime_ns
    assert main(["recover", str(active)]) == 0
    recovered = tmp_path / "logs" / "run.mcap"
    messages, seconds = summary(recovered)
    said, = capfd.readouterr().out.splitlines()
    assert re.fullmatch(recovery_line(messages, seconds, recovered), said), said
    assert not active.exists() and messages > 0
    _, metadata = log_origin(recovered)
    assert metadata.fields["recovered_from"] == {"name": "run.mcap.active", "size_bytes": size, "mtime_ns": mtime}
    assert metadata.command == ""  # the recorder child's own metadata is kept: trundle_version, host
    assert "trundle_version" in metadata.fields

    assert daemon_lines(tmp_path, capfd) == []
    logs = sorted(p.name for p in (tmp_path / "logs").iterdir())
    assert len(logs) == 2 and "run.mcap" in logs and not any("recovered" in name for name in logs), logs


def test_daemon_start_recovers_a_killed_recorders_crash_file_once_and_says_so(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    killed_recorder(tmp_path / "logs")
    lines = daemon_lines(tmp_path, capfd)
    recovered = tmp_path / "logs" / "run.mcap"
    messages, seconds = summary(recovered)
    said, = lines
    assert re.fullmatch("trundle daemon: " + recovery_line(messages, seconds, recovered), said), said
    assert messages > 0 and not (tmp_path / "logs" / "run.mcap.active").exists()
    assert daemon_lines(tmp_path, capfd) == []  # the next start: nothing left to recover
    assert len(list((tmp_path / "logs").glob("run*"))) == 1


def test_a_crash_file_recovered_but_not_removed_is_not_recovered_again(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A recovery that wrote its log and died before removing the crash file: the log's recovered_from
    names the crash file, so the daemon leaves it (no run.recovered.mcap)."""
    active = killed_recorder(tmp_path / "logs")
    kept, st = active.read_bytes(), active.stat()
    assert main(["recover", str(active)]) == 0
    active.write_bytes(kept)  # as it was: name, size and time
    os.utime(active, ns=(st.st_atime_ns, st.st_mtime_ns))
    capfd.readouterr()
    assert daemon_lines(tmp_path, capfd) == []
    assert active.exists() and not (tmp_path / "logs" / "run.recovered.mcap").exists()


def test_an_active_file_another_program_wrote_is_left_alone(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Not trundle's crash file (its MCAP header names another writer): the daemon neither recovers nor
    removes it, and `trundle recover` copies it but keeps it."""
    (tmp_path / "logs").mkdir()
    foreign = tmp_path / "logs" / "theirs.mcap.active"
    with open(foreign, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="someone else")
        channel = writer.register_channel("/chatter", "cdr", 0)
        writer.add_message(channel, 1, b"\x00\x01\x00\x00", 1)
        writer.finish()
    kept = foreign.read_bytes()
    assert daemon_lines(tmp_path, capfd) == []
    assert foreign.read_bytes() == kept and not (tmp_path / "logs" / "theirs.mcap").exists()
    assert main(["recover", str(foreign)]) == 0
    assert capfd.readouterr().out.endswith(f"into {tmp_path / 'logs' / 'theirs.mcap'}\n")  # no "removed"
    assert foreign.read_bytes() == kept


def test_info_and_recover_on_a_live_recorders_file_say_so_and_write_nothing(
        tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "logs").mkdir()
    out = tmp_path / "logs" / "run.mcap"
    proc = start_child(out)
    try:
        active = out.with_name("run.mcap.active")
        who = f"pid {proc.pid} ({Path(f'/proc/{proc.pid}/comm').read_text().strip()})"
        assert main(["info", str(active)]) == 0
        said = capfd.readouterr().out
        assert f"State:             being written by {who} (what it has flushed so far)\n" in said
        assert "recover" not in said

        assert main(["recover", str(active)]) == 2
        assert capfd.readouterr().err == (
            f"trundle recover: {active} is still being written by {who}: it becomes run.mcap when that "
            "process closes it, there is nothing to recover (nothing written)\n")
        assert sorted(p.name for p in (tmp_path / "logs").iterdir()) == ["run.mcap.active"]

        with Running(config(tmp_path)) as run:  # the daemon leaves it alone too
            run.daemon.stop()
        assert [line for line in capfd.readouterr().err.splitlines() if "run.mcap" in line] == []
        assert active.exists() and not out.exists()
    finally:
        proc.send_signal(signal.SIGTERM)  # the recorder closes its log normally
        proc.wait(timeout=30)
    assert proc.returncode == 0 and not active.exists()
    assert LogReader(out).info().complete and not list((tmp_path / "logs").glob("run.*recovered*"))
