"""The CAN bus layer: URLs, receive stamps, error frames, send retries, SLCAN status and unplug,
and a SocketCAN (vcan) test where the kernel has it."""

from __future__ import annotations

import errno
import socket
import time
import uuid

import can
import pytest

from trundle.drivers.can_bus import CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_PROT, CAN_ERR_RESTARTED, CanBus, parse_url
from trundle.logs.errors import DeviceError, UserError
from trundle.tools.emulators.slcan_emulator import SlcanEmulator


def test_urls():
    spec = parse_url("slcan:///dev/ttyACM0@1000000")
    assert (spec.interface, spec.channel, spec.bitrate, spec.device_stamps) == ("slcan", "/dev/ttyACM0", 1000000, False)
    assert parse_url("slcan:///dev/ttyACM0").bitrate == 500000
    assert parse_url("slcan:///dev/ttyUSB0@250000?tty_baudrate=115200").options == {"tty_baudrate": "115200"}
    spec = parse_url("socketcan://can0")
    assert (spec.interface, spec.channel, spec.device_stamps) == ("socketcan", "can0", True)
    assert parse_url("virtual://bench?timestamps=device").device_stamps
    for bad in ("can0", "pcan://PCAN_USBBUS1", "slcan:///dev/x@123", "slcan:///dev/x@fast", "virtual://",
                "virtual://a?timestamps=gps", "slcan:///dev/x?reader=fast"):
        with pytest.raises(UserError):
            parse_url(bad)


def wait_for(predicate, timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.005)
    return predicate()


@pytest.fixture
def channel():
    return f"test-{uuid.uuid4().hex}"


def test_host_stamps_are_monotonic_mapped_to_wall_time(channel):
    bus = CanBus(f"virtual://{channel}")
    bus.open()
    sender = can.Bus(interface="virtual", channel=channel)
    try:
        stamps = []
        for i in range(20):
            sender.send(can.Message(arbitration_id=i, data=b"\1", is_extended_id=False, timestamp=123.456))
            got = bus.recv(1.0)
            assert got is not None and got.device_ns is None
            stamps.append(got.stamp_ns)
        assert stamps == sorted(stamps) and abs(stamps[-1] - time.time_ns()) < 1e9
        assert bus.counters["frames"] == 20
    finally:
        sender.shutdown()
        bus.close()


def test_device_stamps_are_kept_when_asked(channel):
    bus = CanBus(f"virtual://{channel}?timestamps=device")
    bus.open()
    sender = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        sender.send(can.Message(arbitration_id=1, data=b"\1", is_extended_id=False, timestamp=123.456))
        got = bus.recv(1.0)
        assert got.device_ns == 123_456_000_000 and got.stamp_ns == got.device_ns
        assert abs(got.host_ns - time.time_ns()) < 1e9
    finally:
        sender.shutdown()
        bus.close()


def test_error_frames_are_counted_by_class(channel):
    bus = CanBus(f"virtual://{channel}")
    bus.open()
    sender = can.Bus(interface="virtual", channel=channel)
    frames = [(CAN_ERR_CRTL | CAN_ERR_PROT, bytes((0, 0x04, 0, 0, 0, 0, 0, 0))),  # warning
              (CAN_ERR_CRTL, bytes((0, 0x10, 0, 0, 0, 0, 0, 0))),  # passive
              (CAN_ERR_CRTL, bytes((0, 0x01, 0, 0, 0, 0, 0, 0))),  # RX overflow
              (CAN_ERR_BUSOFF, bytes(8)), (CAN_ERR_RESTARTED, bytes(8))]
    try:
        states = []
        for cls, data in frames:
            sender.send(can.Message(arbitration_id=cls, data=data, is_error_frame=True, is_extended_id=False))
            assert bus.recv(1.0).msg.is_error_frame
            states.append(bus.state)
        assert states == ["warning", "passive", "passive", "bus-off", "active"]
        assert {k: bus.counters[k] for k in ("error_frames", "error_warnings", "error_passive", "overruns", "bus_off",
                                              "restarts", "bus_errors")} == {
            "error_frames": 5, "error_warnings": 1, "error_passive": 1, "overruns": 1, "bus_off": 1, "restarts": 1,
            "bus_errors": 1}
    finally:
        sender.shutdown()
        bus.close()


class FlakyBus(can.BusABC):
    """A bus whose transmit queue is full (ENOBUFS) ``full_times`` times, then fails with ``then``."""

    def __init__(self, full_times: int, then: Exception | None = None) -> None:
        super().__init__(channel="flaky")
        self.full_times, self.then, self.sent = full_times, then, []

    def send(self, msg, timeout=None):
        if self.full_times:
            self.full_times -= 1
            raise can.CanOperationError("No buffer space available", error_code=errno.ENOBUFS)
        if self.then is not None:
            raise self.then
        self.sent.append(msg)

    def _recv_internal(self, timeout):
        return None, False


def test_send_retries_a_full_queue_then_drops_and_counts():
    msg = can.Message(arbitration_id=1, data=b"", is_extended_id=False)
    bus = CanBus("virtual://unused", tx_backoff_s=0.0)
    bus.bus = FlakyBus(2)
    assert bus.send(msg) and (bus.counters["tx_retries"], bus.counters["tx_frames"]) == (2, 1)
    bus.bus.shutdown()
    bus.bus = FlakyBus(100)
    assert not bus.send(msg) and bus.counters["tx_dropped"] == 1
    bus.bus.shutdown()
    bus.bus = FlakyBus(0, can.CanOperationError("Could not write to serial device"))
    with pytest.raises(DeviceError):
        bus.send(msg)
    bus.bus.shutdown()
    bus.bus = None
    with pytest.raises(DeviceError):
        bus.send(msg)


def test_slcan_unplug_raises_device_error_and_reopens(tmp_path):
    link = tmp_path / "ttyACM0"
    with SlcanEmulator(str(link)) as adapter:
        bus = CanBus(f"slcan://{link}@1000000")
        bus.open()
        assert wait_for(lambda: adapter.is_open) and adapter.bitrate == 1000000
        adapter.unplug()
        with pytest.raises(DeviceError):
            bus.recv(0.5)
        bus.close()  # the closing "C" fails on a pulled adapter; close must not raise
        with pytest.raises(DeviceError, match="cannot open"):
            bus.open()
        adapter.replug()
        bus.open()
        assert wait_for(lambda: adapter.is_open)
        adapter.bus.send(can.Message(arbitration_id=0x123, data=b"\xAA", is_extended_id=False))
        got = bus.recv(1.0)
        assert got.msg.arbitration_id == 0x123 and got.msg.data == b"\xAA"
        bus.close()


def test_slcan_status_flags_and_bus_off_recovery(tmp_path):
    link = tmp_path / "ttyACM0"
    with SlcanEmulator(str(link)) as adapter:
        bus = CanBus(f"slcan://{link}", status_poll_s=0.0)
        bus.open()
        assert bus.slcan_status(2.0) == 0
        adapter.raise_flags(0x04 | 0x08)
        assert bus.slcan_status(2.0) == 0x0C and bus.slcan_status(2.0) == 0  # shown once
        adapter.raise_flags(0x08)
        bus.maybe_poll_status()
        assert bus.counters["overruns"] == 1 and bus.state == "active"
        adapter.bus_off()
        assert adapter.bus.send(can.Message(arbitration_id=1, data=b"", is_extended_id=False)) is None
        assert adapter.stats["dropped"] == 1
        bus.maybe_poll_status()  # sees the bus error flag, sends C then O
        assert bus.counters["bus_off"] == 1 and bus.counters["restarts"] == 1 and bus.state == "active"
        assert wait_for(lambda: adapter.passing)
        adapter.bus.send_many([can.Message(arbitration_id=i, data=bytes([i]), is_extended_id=False) for i in range(50)])
        assert [bus.recv(1.0).msg.arbitration_id for _ in range(50)] == list(range(50))
        bus.close()


def test_python_cans_own_slcan_reader_receives_and_counts_garbled_lines(tmp_path):
    link = tmp_path / "ttyACM0"
    with SlcanEmulator(str(link)) as adapter:
        bus = CanBus(f"slcan://{link}?reader=python-can", status_poll_s=0.0)
        bus.open()
        assert wait_for(lambda: adapter.is_open) and bus.slcan_status(0.2) is None  # it has no F call
        adapter.inject_noise()
        adapter.bus.send(can.Message(arbitration_id=0x123, data=b"\xAA", is_extended_id=False))
        got = [bus.recv(1.0) for _ in range(4)]
        assert got[:3] == [None] * 3 and bus.counters["corrupt_frames"] == 3
        assert (got[3].msg.arbitration_id, got[3].msg.data) == (0x123, b"\xAA")
        bus.close()


def _has_socketcan(interface: str) -> str | None:
    """None if SocketCAN ``interface`` can be opened here, else why not."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (AttributeError, OSError) as error:
        return f"no SocketCAN in this kernel/sandbox ({error})"
    try:
        sock.bind((interface,))
    except OSError as error:
        return (f"no {interface} interface ({error}); create it with: "
                f"ip link add dev {interface} type vcan && ip link set up {interface}")
    finally:
        sock.close()
    return None


def test_vcan_round_trip_with_kernel_stamps():
    reason = _has_socketcan("vcan0")
    if reason:
        pytest.skip(reason)
    bus = CanBus("socketcan://vcan0")
    bus.open()
    sender = can.Bus(interface="socketcan", channel="vcan0")
    try:
        sender.send(can.Message(arbitration_id=0x069, data=bytes.fromhex("0000C03F000080BE"), is_extended_id=False))
        got = bus.recv(1.0)
        assert got.msg.arbitration_id == 0x069 and got.device_ns is not None
        assert abs(got.device_ns - got.host_ns) < 1e9
    finally:
        sender.shutdown()
        bus.close()
