"""The drivers' serial transport on a pty: batched reads, whole bursts, empty reads of a busy pty."""

from __future__ import annotations

import os

import pytest
import serial

from trundle.drivers import serial_link
from trundle.drivers.serial_link import TTY_BUFFER, SerialLink
from trundle.tools.emulators.pty_link import PtyLink


def test_batched_reads_take_everything_that_arrived_meanwhile(tmp_path):
    with PtyLink(tmp_path / "tty") as pty:
        link = SerialLink(str(tmp_path / "tty"), 115200, batch_s=0.2)
        pty.write(b"first")
        assert link.read() == b"first"
        for piece in (b"a", b"bb", b"ccc"):  # within the batch period: one read takes them all
            pty.write(piece)
        assert link.read() == b"abbccc"
        link.close()


def test_a_burst_larger_than_the_tty_buffer_comes_in_one_read(tmp_path):
    burst = bytes(range(256)) * 40  # 10 kB, as two and a half tty buffers
    with PtyLink(tmp_path / "tty") as pty:
        link = SerialLink(str(tmp_path / "tty"), 115200, batch_s=0.5)
        pty.write(burst)  # the pty takes the rest as the reader drains it
        data = link.read()
        assert len(burst) > 2 * TTY_BUFFER and data == burst
        link.close()


def test_a_ready_tty_that_reads_nothing_is_gone_only_if_it_stays_so(tmp_path, monkeypatch):
    with PtyLink(tmp_path / "tty") as pty:
        link = SerialLink(str(tmp_path / "tty"), 115200)
        real = os.read
        empties = [b"", b""]
        monkeypatch.setattr(serial_link.os, "read", lambda fd, n: empties.pop() if empties else real(fd, n))
        pty.write(b"x")
        assert link.read() == b"" and link.read() == b""  # a busy pty: nothing yet
        assert link.read() == b"x"
        monkeypatch.setattr(serial_link.os, "read", lambda fd, n: b"")
        pty.write(b"y")
        monkeypatch.setattr(serial_link, "EMPTY_READS_S", 0.0)
        with pytest.raises(serial.SerialException, match="returned no data"):  # the pty stays "ready"
            for _ in range(3):
                link.read()
        link.close()


def test_an_unplugged_device_is_seen_at_once(tmp_path):
    pty = PtyLink(tmp_path / "tty")
    link = SerialLink(str(tmp_path / "tty"), 115200)
    pty.write(b"x")
    assert link.read() == b"x"
    pty.unplug()  # the link disappears with the pty, as /dev/ttyUSB0 with its cable
    with pytest.raises(serial.SerialException):
        for _ in range(3):
            link.read()
    link.close()


def test_close_never_raises_on_a_line_that_died(tmp_path):
    pty = PtyLink(tmp_path / "tty")
    link = SerialLink(str(tmp_path / "tty"), 115200)
    pty.unplug()
    link.close(lambda port: None)  # the flush after the last words: tcdrain fails with EIO (termios.error)
    assert not link.port.is_open
