"""`trundle demo` ended by a signal leaves nothing running and nothing hidden: SIGHUP (the terminal
closed) and SIGTERM stop its daemon cleanly, remove its temporary folder and keep the partial
log where the user is told; a demo killed outright (SIGKILL) takes its daemon with it."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from trundle.logs.reader import LogReader

ROOT = Path(__file__).resolve().parents[1]


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting for its reaper does not count)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False
    return state != "Z"


@pytest.fixture()
def short_tmp():
    """A temporary folder with a short path for the demo's TMPDIR: its status socket lives there,
    and a UNIX socket path may not exceed 107 bytes (pytest's own folders under xdist can)."""
    folder = Path(tempfile.mkdtemp(prefix="tds-", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def start_demo(tmp_path: Path, short_tmp: Path) -> tuple[subprocess.Popen[str], int, list[str]]:
    """A demo in its own process, run as ``trundle demo -o demo`` in a folder that holds packages of
    its own named ``tools`` and ``trundle`` (they must shadow nothing: the daemon once started as
    ``python -m tools.cli``), temporary files under ``short_tmp``; once its robot drives,
    returns the process, its daemon's pid and the output lines so far."""
    env = {**os.environ, "TMPDIR": str(short_tmp)}
    out = tmp_path / "out"
    for package in ("tools", "tools/cli", "trundle"):
        (out / package).mkdir(parents=True)
        (out / package / "__init__.py").write_text("raise ImportError('a user package, not trundle')\n")
    (out / "tools" / "cli" / "__main__.py").write_text("raise SystemExit(3)\n")
    demo = subprocess.Popen([sys.executable, "-P", "-m", "trundle.tools.cli", "demo", "-o", "demo",
                             "--duration", "60", "--camera-fps", "5"], cwd=out, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    daemon = 0
    deadline = time.monotonic() + 180
    assert demo.stdout is not None
    while time.monotonic() < deadline:
        line = demo.stdout.readline()
        if not line:
            break
        lines.append(line)
        if found := re.search(r"daemon started \(pid (\d+)\)", line):
            daemon = int(found.group(1))
        if "the robot drives" in line:
            time.sleep(1.5)  # a second of driving in the log
            return demo, daemon, lines
    demo.kill()
    pytest.fail("the demo did not start driving:\n" + "".join(lines))


def wait_gone(pid: int, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not alive(pid)


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGTERM])
def test_a_signal_stops_the_daemon_and_keeps_the_partial_log(tmp_path: Path, short_tmp: Path,
                                                            sig: signal.Signals) -> None:
    demo, daemon, lines = start_demo(tmp_path, short_tmp)
    assert alive(daemon)
    demo.send_signal(sig)
    rest, _ = demo.communicate(timeout=120)
    output = "".join(lines) + rest
    assert demo.returncode != 0 and "Traceback" not in output
    assert wait_gone(daemon), "the daemon outlived the demo"
    assert not list(short_tmp.glob("trundle-demo-*")), "temporary folder left behind"
    out = tmp_path / "out" / "demo"
    assert not list(out.glob(".daemon-logs-*"))
    partial = out.resolve() / "demo.partial.mcap"
    assert f"its log so far is {partial}" in output
    info = LogReader(partial).info()
    assert info.complete and info.topics["/scan"].count > 10  # closed cleanly by the daemon's SIGTERM


def test_a_killed_demo_takes_its_daemon_with_it(tmp_path: Path, short_tmp: Path) -> None:
    demo, daemon, _ = start_demo(tmp_path, short_tmp)
    demo.kill()
    demo.communicate(timeout=30)
    assert wait_gone(daemon), "the daemon outlived a killed demo"
