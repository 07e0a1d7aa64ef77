"""Two programs on one serial port: the first keeps it, the second ends at once in one line naming
the port and who holds it (issue 23, item 1). Without the lock both read the same tty and each
gets half the bytes: the daemon lost ~4.5 s of scans while a second ``record`` exited 0."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import can
import pytest

from tests.lrf_harness import Recorder, running, wait_until
from trundle.drivers import lrf
from trundle.drivers.slcan import SlcanBus
from trundle.logs import messages as m
from trundle.logs.errors import PortBusyError
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import MODELS, ScipDevice
from trundle.tools.emulators.slcan_emulator import SlcanEmulator


@pytest.fixture
def scip_port(tmp_path):
    """An emulated URG behind the pty link ``tmp_path/lrf``, served (not yet opened by anyone)."""
    model = MODELS["urg-04lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles, seed=3), now_ns=time.time_ns())
    return DeviceServer(device, link_path=tmp_path / "lrf"), tmp_path / "lrf"


def test_second_record_on_a_held_laser_port_ends_at_once_and_the_first_keeps_scanning(tmp_path, scip_port):
    server, link = scip_port
    first = Recorder()
    with running(server, lrf.driver_from_url(f"scip2://{link}", first)) as (_, driver):
        wait_until(lambda: len(first.scans()) >= 3, "the first opener's scans")
        out = tmp_path / "second.mcap"
        second = subprocess.run([sys.executable, "-m", "trundle.tools.cli", "record", "--lrf", f"scip2://{link}",
                                 "--duration", "1", "-o", str(out)], capture_output=True, text=True, timeout=60)
        assert second.returncode != 0
        (line,) = second.stderr.splitlines()
        assert str(link) in line and f"in use by pid {os.getpid()}" in line, line
        assert not list(tmp_path.glob("second*")), "a log was written"
        before = len(first.scans())
        wait_until(lambda: len(first.scans()) >= before + 5, "the first opener's scans to go on")
        assert driver.counters["errors"] == 0 and driver.counters["reconnects"] == 0
        assert driver.counters["missed_scans"] == 0


def test_a_driver_on_a_held_port_says_so_and_takes_it_when_it_is_let_go(scip_port):
    # the daemon's case: it says who holds the port, and keeps trying, since the other program may let go
    server, link = scip_port
    server.start()
    first, waiting = Recorder(), Recorder()
    first_driver = lrf.driver_from_url(f"scip2://{link}", first)
    first_driver.start()
    try:
        wait_until(lambda: len(first.scans()) >= 2, "the first opener's scans")
        with running(server, lrf.driver_from_url(f"scip2://{link}", waiting)) as (_, driver):
            wait_until(lambda: driver.port_busy is not None, "the second driver to meet the held port")
            level, message = driver.health_status()
            assert level == m.ERROR and str(link) in message and f"pid {os.getpid()}" in message
            assert len(message.splitlines()) == 1
            first_driver.stop()
            wait_until(lambda: len(waiting.scans()) >= 2, "the second driver's scans once the port is free")
            assert driver.port_busy is None
    finally:
        first_driver.stop()


def test_second_slcan_bus_on_a_held_adapter_is_refused_in_one_line(tmp_path):
    with SlcanEmulator(str(tmp_path / "ttyACM0")) as adapter:
        port = str(adapter.link.link_path)
        first = SlcanBus(port, bitrate=500000)
        try:
            with pytest.raises(PortBusyError) as refused:
                SlcanBus(port, bitrate=500000)
            assert port in str(refused.value) and f"pid {os.getpid()}" in str(refused.value)
            assert len(str(refused.value).splitlines()) == 1
            msg = can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False)
            adapter.bus.send(msg)
            got = first.recv(2.0)
            assert got is not None and bytes(got.data) == b"\x01\x02"
            assert adapter.is_open and adapter.bitrate == 500000
        finally:
            first.shutdown()
