"""The SLCAN adapter emulator against third-party clients: python-can's slcan interface and raw
pyserial, with the Lawicel protocol's own command/reply examples."""

from __future__ import annotations

import threading
import time

import can
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.slcan import format_frame, parse_frame
from trundle.tools.emulators.slcan_emulator import SlcanEmulator


@pytest.fixture
def adapter(tmp_path):
    with SlcanEmulator(str(tmp_path / "ttyACM0")) as emulator:
        yield emulator


@pytest.fixture
def host(adapter):
    bus = can.Bus(interface="slcan", channel=str(adapter.link.link_path), bitrate=500000, sleep_after_open=0)
    deadline = time.monotonic() + 2
    while not adapter.is_open and time.monotonic() < deadline:
        time.sleep(0.005)
    yield bus
    bus.shutdown()


def test_python_can_identifies_the_adapter(adapter, host):
    assert host.get_version(1.0) == (10, 13)
    assert host.get_serial_number(1.0) == "A123"
    assert adapter.bitrate == 500000 and adapter.is_open


@pytest.mark.parametrize("msg", [
    can.Message(arbitration_id=0x069, data=bytes.fromhex("0000C03F000080BE"), is_extended_id=False),
    can.Message(arbitration_id=0x1B09, data=b"\x01\x02", is_extended_id=True),
    can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False),
    can.Message(arbitration_id=0x069, is_remote_frame=True, dlc=8, is_extended_id=False),
    can.Message(arbitration_id=0x1FFFFFFF, is_remote_frame=True, dlc=0, is_extended_id=True),
])
def test_frames_both_ways(adapter, host, msg):
    adapter.bus.send(msg)
    got = host.recv(1.0)
    assert got.equals(msg, timestamp_delta=None, check_direction=False, check_channel=False)
    host.send(msg)
    echoed = adapter.bus.recv(1.0)
    assert echoed.equals(msg, timestamp_delta=None, check_direction=False, check_channel=False)


def test_adapter_time_stamps_are_dropped_by_python_can(adapter, host):
    # Z1 appends a 4-digit ms counter (0..59999): python-can keeps the data and stamps host time
    adapter.timestamps = True
    assert format_frame(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False), 0x1234) \
        == b"t181201021234\r"
    adapter.bus.send(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
    got = host.recv(1.0)
    assert bytes(got.data) == b"\x01\x02" and abs(got.timestamp - time.time()) < 1.0


def test_lawicel_command_replies_over_raw_serial(adapter):
    port = serial.Serial(str(adapter.link.link_path), timeout=0.5)

    def ask(command: bytes) -> bytes:
        port.write(command + b"\r")
        first = port.read(1)
        return first if first in (b"\x07", b"\r") else first + port.read_until(b"\r")

    try:
        assert ask(b"V") == b"V1013\r" and ask(b"N") == b"NA123\r"
        assert ask(b"F") == b"\x07"  # closed channel
        assert ask(b"t1230") == b"\x07"  # transmit while closed
        assert ask(b"S9") == b"\x07" and ask(b"S4") == b"\r" and adapter.bitrate == 125000
        assert ask(b"Z1") == b"\r" and adapter.timestamps
        assert ask(b"O") == b"\r" and ask(b"O") == b"\x07"  # already open
        assert ask(b"S6") == b"\x07"  # bit rate only while closed
        assert ask(b"F") == b"F00\r"
        assert ask(b"t12311") == b"\x07"  # one data byte short of the DLC
        assert ask(b"t8001AA") == b"\x07"  # 11-bit id out of range
        assert ask(b"t1231AA") == b"z\r" and ask(b"T000001231AA") == b"Z\r" and ask(b"r1238") == b"z\r"
        assert ask(b"?") == b"\x07"
        assert ask(b"C") == b"\r" and ask(b"C") == b"\x07"
        assert ask(b"L") == b"\r" and ask(b"t1230") == b"\x07"  # listen-only: no transmit
        received = [adapter.bus.recv(0.5) for _ in range(3)]
        assert [(m.arbitration_id, m.is_extended_id, m.is_remote_frame) for m in received] == [
            (0x123, False, False), (0x123, True, False), (0x123, False, True)]
        assert adapter.stats["bad_commands"] == 3
    finally:
        port.close()


def test_frames_arrive_in_order(adapter, host):
    # flow-controlled (at most two batches in flight): ordering and completeness, not throughput,
    # which tools/bench/bench_can.py measures
    n, batch = 3000, 100
    received = threading.Semaphore(2)

    def produce():
        for start in range(0, n, batch):
            received.acquire()
            adapter.bus.send_many([can.Message(arbitration_id=i & 0x7FF, data=i.to_bytes(4, "little"),
                                               is_extended_id=False) for i in range(start, start + batch)])

    thread = threading.Thread(target=produce)
    thread.start()
    got = []
    while len(got) < n and (msg := host.recv(5.0)) is not None:
        got.append(int.from_bytes(msg.data, "little"))
        if len(got) % batch == 0:
            received.release()
    thread.join()
    assert got == list(range(n)) and adapter.stats["dropped"] == 0


frames = st.builds(
    lambda ext, rtr, ident, data, dlc: can.Message(
        arbitration_id=ident & (0x1FFFFFFF if ext else 0x7FF), is_extended_id=ext, is_remote_frame=rtr,
        data=b"" if rtr else data, dlc=dlc if rtr else len(data)),
    st.booleans(), st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8), st.integers(0, 8))


@settings(max_examples=200, deadline=None)
@given(frames)
def test_frame_lines_round_trip(msg):
    line = format_frame(msg)
    assert line.endswith(b"\r")
    back = parse_frame(line[:-1])
    assert back.equals(msg, timestamp_delta=None, check_direction=False, check_channel=False)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=30))
def test_any_line_parses_or_is_refused(line):
    msg = parse_frame(line.replace(b"\r", b""))
    if msg is not None:
        assert format_frame(msg)[:-1].upper() == line.replace(b"\r", b"").upper()
