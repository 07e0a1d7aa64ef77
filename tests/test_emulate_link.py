"""`trundle emulate lrf|can --link PATH` never deletes or replaces what is at PATH: a file, a
device node, a folder or someone else's link is refused; only a stale link left by a killed
emulator is taken over, and only the emulator's own link is removed when it stops."""

from __future__ import annotations

import os
import pty
import signal
import stat
import subprocess
import sys
import time

import pytest

from trundle.logs.errors import UserError
from trundle.tools.cli.main import main
from trundle.tools.emulators.pty_link import PtyLink


def occupants(tmp_path):
    """Things a user may have at the path: each must survive untouched."""
    regular = tmp_path / "notes.txt"
    regular.write_text("keep me")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    folder = tmp_path / "folder"
    folder.mkdir()
    master, slave = pty.openpty()  # a live pty (another emulator's, a terminal)
    live = tmp_path / "live-link"
    os.symlink(os.ttyname(slave), live)
    return [regular, fifo, folder, live], (master, slave)


def snapshot(path):
    info = os.lstat(path)
    return stat.S_IFMT(info.st_mode), info.st_ino, os.readlink(path) if path.is_symlink() else None


def test_an_existing_path_is_refused_and_left_as_it_was(tmp_path):
    paths, fds = occupants(tmp_path)
    try:
        for path in paths:
            before = snapshot(path)
            with pytest.raises(UserError) as error:
                PtyLink(path)
            assert str(path) in str(error.value) and "\n" not in str(error.value)
            assert snapshot(path) == before
        assert (tmp_path / "notes.txt").read_text() == "keep me"
    finally:
        for fd in fds:
            os.close(fd)


def test_a_device_node_is_refused(tmp_path):
    node = tmp_path / "ttyACM0"
    try:
        os.mknod(node, stat.S_IFCHR | 0o600, os.makedev(1, 3))  # the /dev/null device: needs CAP_MKNOD
    except PermissionError:
        node = tmp_path / "null-link"
        os.symlink("/dev/null", node)  # without the privilege: a link to a real device node
    with pytest.raises(UserError, match="exists|in use"):
        PtyLink(node)
    assert node.exists() or node.is_symlink()


def test_a_stale_link_of_a_killed_emulator_is_taken_over_and_only_our_link_is_removed(tmp_path):
    link = tmp_path / "lrf"
    os.symlink("/dev/pts/999999", link)  # a pty slave that no longer exists
    emulator = PtyLink(link)
    assert os.readlink(link).startswith("/dev/pts/") and os.path.exists(os.readlink(link))
    emulator.unplug()
    assert not link.exists() and not link.is_symlink()
    emulator.replug()
    os.unlink(link)
    link.write_text("a user's file, put there while the emulator was unplugged")
    emulator.close()  # not our link any more: left alone
    assert link.read_text().startswith("a user's file")
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("family", [["lrf"], ["can", "--protocol", "odrive"]])
def test_the_emulate_command_refuses_an_existing_file(tmp_path, capsys, family):
    target = tmp_path / "ttyUSB0"
    target.write_text("precious")
    assert main(["emulate", *family, "--link", str(target), "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists and is a file" in err
    assert target.read_text() == "precious"


@pytest.mark.parametrize("family", [["lrf"], ["can", "--protocol", "odrive"]])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stopped_emulator_removes_its_link_on_sigterm_as_on_ctrl_c(tmp_path, family, sig):
    """systemd, ``kill`` and test harnesses stop an emulator with SIGTERM: its link goes as on Ctrl-C,
    so the next emulator on that path starts without a leftover (issue: ``emulate lrf`` left it dangling)."""
    link = tmp_path / "dev"
    emulator = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", *family, "--link", str(link)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not link.is_symlink() and time.monotonic() < deadline and emulator.poll() is None:
            time.sleep(0.05)
        assert link.is_symlink() and os.path.exists(os.readlink(link)), emulator.stderr
        emulator.send_signal(sig)
        _, err = emulator.communicate(timeout=30)
    finally:
        emulator.kill()
    assert emulator.returncode == 0, err
    assert not link.exists() and not link.is_symlink()
    assert not list(tmp_path.iterdir())
