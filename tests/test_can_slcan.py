"""Our SLCAN bus (``drivers/slcan.py``) against python-can's own slcan interface, each on one end
of a pty pair (two ptys with their masters joined): frames written by python-can's stock bus are
read by ours and the other way round, so the two implementations of the line protocol are held
to each other. Plus the codec's refusal of garbled lines and the adapter's ``Z1`` stamps."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.slcan import SlcanBus, format_frame, parse_frame, parse_received
from trundle.logs.errors import ProtocolError
from trundle.tools.emulators.pty_link import PtyLink

FRAMES = [
    can.Message(arbitration_id=0x069, data=bytes.fromhex("0000C03F000080BE"), is_extended_id=False),
    can.Message(arbitration_id=0x1B09, data=b"\x01\x02", is_extended_id=True),
    can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False),
    can.Message(arbitration_id=0x069, is_remote_frame=True, dlc=8, is_extended_id=False),
    can.Message(arbitration_id=0x1FFFFFFF, is_remote_frame=True, dlc=0, is_extended_id=True),
]


class PtyPair:
    """Two ptys whose masters a thread joins: what one slave's user writes, the other's reads."""

    def __init__(self, folder: Path) -> None:
        self.a, self.b = PtyLink(folder / "ttyA"), PtyLink(folder / "ttyB")
        self.sent: list[bytes] = []  # every chunk written into a (by the side opened on a), in order
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if data := self.a.read(65536, 0.002):
                self.sent.append(data)
                self.b.write(data)
            if data := self.b.read(65536, 0.002):
                self.a.write(data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.a.close()
        self.b.close()


@pytest.fixture
def buses(tmp_path) -> Iterator[tuple[can.BusABC, SlcanBus, PtyPair]]:
    """python-can's stock slcan bus on one end, ours on the other."""
    pair = PtyPair(tmp_path)
    ours = SlcanBus(str(pair.b.link_path), bitrate=500000)
    stock = can.Bus(interface="slcan", channel=str(pair.a.link_path), bitrate=500000, sleep_after_open=0)
    try:
        assert ours.recv(0.3) is None  # python-can's C, S6, O (and ours) are no frames
        yield stock, ours, pair
    finally:
        stock.shutdown()
        ours.shutdown()
        pair.close()


def same(a: can.Message, b: can.Message) -> bool:
    return a.equals(b, timestamp_delta=None, check_direction=False, check_channel=False)


def test_python_can_opens_its_side_with_the_commands_ours_sends(buses):
    stock, ours, pair = buses
    assert b"".join(pair.sent).startswith(b"C\rS6\r")  # python-can's open: close, bit rate, open
    assert b"O\r" in b"".join(pair.sent)


@pytest.mark.parametrize("msg", FRAMES)
def test_frames_written_by_python_can_are_read_by_ours_and_back(buses, msg):
    stock, ours, _ = buses
    stock.send(msg)
    got = ours.recv(1.0)
    assert got is not None and same(got, msg)
    ours.send(msg)
    back = stock.recv(1.0)
    assert back is not None and same(back, msg)


def test_a_burst_arrives_whole_and_in_order(buses):
    stock, ours, _ = buses
    sent = [can.Message(arbitration_id=0x100 + i % 0x80, data=i.to_bytes(2, "little"), is_extended_id=False)
            for i in range(500)]
    for msg in sent:
        stock.send(msg)
    got = [ours.recv(2.0) for _ in sent]
    assert all(g is not None and same(g, m) for g, m in zip(got, sent, strict=True))
    assert ours.recv(0.05) is None


def test_a_garbled_line_is_a_protocol_error_and_reading_goes_on(buses):
    _, ours, pair = buses
    pair.b.write(b"t1X3\rT1234\r" + format_frame(FRAMES[0]) + b"t0012AABB1234\r")  # last one with a Z1 stamp
    with pytest.raises(ProtocolError, match="t1X3"):
        ours.recv(1.0)
    with pytest.raises(ProtocolError, match="T1234"):
        ours.recv(1.0)
    assert same(ours.recv(1.0), FRAMES[0])
    stamped = ours.recv(1.0)
    assert (stamped.arbitration_id, bytes(stamped.data)) == (0x001, b"\xAA\xBB")


def test_frames_read_behind_replies_come_even_with_no_time_left(buses):
    """A frame, a reply (``z``) and a frame read in one burst: a poll with no time left (``recv(0)``) skips the
    reply already read and returns the frame behind it (it once gave up at the reply); then None."""
    _, ours, pair = buses
    pair.b.write(format_frame(FRAMES[0]) + b"z\r" + format_frame(FRAMES[1]))
    time.sleep(0.2)   # the whole burst waits in the pty: the first recv reads it in one go
    assert same(ours.recv(1.0), FRAMES[0])
    assert same(ours.recv(0), FRAMES[1])
    assert ours.recv(0) is None


def read_until(link: PtyLink, expected: bytes, timeout_s: float = 5.0) -> bytes:
    """What the host wrote, read until it is as long as ``expected`` (commands written one at a
    time reach the pty in as many reads on a loaded machine) or ``timeout_s`` passes."""
    got, deadline = b"", time.monotonic() + timeout_s
    while len(got) < len(expected) and time.monotonic() < deadline:
        got += link.read(64, 0.1)
    return got


def test_status_flags_keep_the_frames_that_arrive_meanwhile(tmp_path):
    link = PtyLink(tmp_path / "ttyACM0")
    ours = SlcanBus(str(link.link_path), bitrate=1000000)
    try:
        assert read_until(link, b"C\rS8\rO\r") == b"C\rS8\rO\r"
        done = threading.Event()

        def adapter() -> None:  # answers F after two frames
            while not done.is_set() and link.read(64, 0.05) != b"F\r":
                pass
            link.write(format_frame(FRAMES[0]) + format_frame(FRAMES[1]) + b"F0C\r")
        thread = threading.Thread(target=adapter, daemon=True)
        thread.start()
        assert ours.status_flags(2.0) == 0x0C
        done.set()
        thread.join(2.0)
        assert same(ours.recv(0.5), FRAMES[0]) and same(ours.recv(0.5), FRAMES[1])
        ours.restart()
        assert read_until(link, b"C\rO\r") == b"C\rO\r"
    finally:
        ours.shutdown()
        link.close()


def test_an_unplugged_adapter_is_a_can_operation_error(tmp_path):
    link = PtyLink(tmp_path / "ttyACM0")
    ours = SlcanBus(str(link.link_path))
    link.unplug()
    with pytest.raises(can.CanOperationError):
        ours.recv(0.5)
    ours.shutdown()  # its closing C fails; shutting down must not raise
    with pytest.raises(can.CanInitializationError):
        SlcanBus(str(link.link_path))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=30))
def test_any_received_line_parses_or_is_refused(line):
    line = line.replace(b"\r", b"")
    msg = parse_received(line)
    if msg is not None:
        text = format_frame(msg)[:-1].upper()
        assert text == line.upper() or text == line[:-4].upper()


@settings(max_examples=200, deadline=None)
@given(st.booleans(), st.integers(0, 0x7FF), st.binary(max_size=8), st.integers(0, 59999))
def test_a_stamped_frame_reads_as_the_frame(extended, ident, data, stamp_ms):
    msg = can.Message(arbitration_id=ident, data=data, is_extended_id=extended)
    assert same(parse_received(format_frame(msg, stamp_ms)[:-1]), msg)
    assert same(parse_frame(format_frame(msg)[:-1]), msg)
