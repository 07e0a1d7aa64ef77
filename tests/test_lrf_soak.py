"""Soak: a minute of every fault kind at once, each laser driver against its emulator (slow).

The short, exact versions are in test_scip2_driver.py and test_rplidar_driver.py; here the
faults overlap (line faults, stalls, clock resets, abnormal states, unplugs) and the checks are
that the driver keeps going and never logs a scan the device did not send intact.
"""

from __future__ import annotations

import time

import pytest

from tests.lrf_harness import inject, running, wait_until
from tests.test_rplidar_driver import make as make_rplidar
from tests.test_rplidar_driver import match as match_rplidar
from tests.test_scip2_driver import make as make_scip2
from tests.test_scip2_driver import match as match_scip2
from trundle.tools.emulators.faults import FaultPlan

SOAK_S = 60.0


@pytest.mark.slow
def test_scip2_soak(tmp_path):
    plan = FaultPlan({"checksum": 0.03, "truncate": 0.03, "garbage": 0.03, "unstable": 0.02, "stall": 0.01},
                     stall_s=0.2, unplug_s=0.5, reboot_s=0.4, seed=11)
    device, server, driver, sink = make_scip2(tmp_path, "utm-30lx", faults=plan, angle_min=-1.0, angle_max=1.0)
    with running(server, driver):
        end = time.monotonic() + SOAK_S
        while time.monotonic() < end:
            for kind in ("reboot", "abnormal", "unplug"):
                wait_until(lambda: driver.state == "streaming" and driver.counters["scans"] > 0, "streaming")
                inject(server, kind)
                time.sleep(SOAK_S / 12)
    c = driver.counters
    assert c["scans"] > 8 * SOAK_S and c["abnormal"] >= 1 and c["reboots"] >= 1 and c["clock_resets"] >= 1
    match_scip2(device, sink, device.params.angle_step(-1.0))


@pytest.mark.slow
def test_rplidar_soak(tmp_path):
    plan = FaultPlan({"checksum": 0.1, "truncate": 0.05, "garbage": 0.05, "stall": 0.02}, stall_s=0.2,
                     unplug_s=0.5, seed=12)
    device, server, driver, sink = make_rplidar(tmp_path, "a2", "Standard", faults=plan)
    with running(server, driver):
        end = time.monotonic() + SOAK_S
        while time.monotonic() < end:
            wait_until(lambda: driver.state == "streaming", "streaming")
            inject(server, "unplug")
            time.sleep(SOAK_S / 6)
    assert driver.counters["scans"] > 3 * SOAK_S and driver.counters["reconnects"] >= 3
    match_rplidar(device, driver, sink.scans(), stamps=False)
