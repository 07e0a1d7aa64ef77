"""ODrive firmware lines: Get_Version tells 0.6 (ODrive Pro / S1) from 0.5, the default ``auto``
reads each axis's heartbeat with its own layout, and an axis that gives no readings says why
(wrong node ids, an 0.6 heartbeat read as 0.5)."""

from __future__ import annotations

import math
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest

from trundle.drivers import odrive
from trundle.drivers.wheels import driver_from_url
from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.emulators.can_nodes import CanNodeRunner, VelocityScript, WheelMotion, odrive_nodes

ROOT = Path(__file__).resolve().parents[1]


def test_get_version_layout_from_the_protocol_table() -> None:
    # CAN Simple Get_Version: u8 protocol, hw major/minor/variant, fw major/minor/revision, unreleased
    version = odrive.decode_version(bytes([2, 4, 4, 58, 0, 6, 10, 0]))
    assert version == odrive.Version(2, (4, 4, 58), (0, 6, 10), False)
    assert version.firmware_text == "0.6.10" and version.line == "0.6"
    assert odrive.decode_version(bytes([1, 3, 6, 56, 0, 5, 6, 1])).line == "0.5"
    assert odrive.encode_version(version) == bytes([2, 4, 4, 58, 0, 6, 10, 0])
    with pytest.raises(ValueError):
        odrive.decode_version(b"\x02\x04")


class Bench:
    """Two emulated ODrive axes on a virtual bus and the wheels driver reading them."""

    def __init__(self, firmware: str, encoders: str, config: dict | None = None) -> None:
        channel = f"fw-{uuid.uuid4().hex}"
        self.device_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.nodes = odrive_nodes([0, 1], firmware=firmware)
        self.runner = CanNodeRunner(self.device_bus, self.nodes, WheelMotion(VelocityScript.parse("0:0.5,0.5")))
        self.log: list[tuple[str, m.Message]] = []
        options = {"encoders": encoders, "odrive": {"heartbeat_timeout_s": 3.0, "data_timeout_s": 3.0}}
        for key, value in (config or {}).items():
            options["odrive"].update(value) if key == "odrive" else options.update({key: value})
        self.driver = driver_from_url(f"virtual://{channel}", lambda topic, msg, t: self.log.append((topic, msg)),
                                      options)
        self.driver.silence_s = 0.5

    def __enter__(self) -> Bench:
        self.driver.start()
        deadline = time.monotonic() + 5
        while self.driver.state != "streaming" and time.monotonic() < deadline:
            time.sleep(0.01)
        self.runner.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.runner.stop()
        self.driver.stop()
        self.device_bus.shutdown()

    def good_wheels(self) -> list[m.JointState]:
        return [msg for topic, msg in list(self.log) if topic == "/wheels" and np.isfinite(msg.position).all()]

    def wait(self, predicate, timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not predicate():
            time.sleep(0.02)
        return predicate()

    def values(self) -> dict[str, str]:
        return dict(self.driver.diagnostics().values)


def test_auto_reads_firmware_0_6_axes_and_records_the_version() -> None:
    with Bench("0.6", "odrive:0,1") as bench:
        assert bench.wait(lambda: len(bench.good_wheels()) >= 20), bench.driver.diagnostics()
        values = bench.values()
    assert values["odrive.0.firmware"].startswith("0.6.10 (Get_Version") and "4.4.58" in values["odrive.0.firmware"]
    assert values["odrive.1.firmware"].startswith("0.6.10")


def test_auto_takes_axes_without_get_version_for_0_5_and_still_trusts_their_error_flag() -> None:
    with Bench("0.5", "odrive:0,1") as bench:
        assert bench.wait(lambda: bench.values()["odrive.0.firmware"].startswith("0.5 (no Get_Version")), \
            bench.values()
        assert bench.wait(lambda: len(bench.good_wheels()) >= 10)
        bench.nodes[1].encoder_error = True  # 0.5: heartbeat byte 6 = encoder error: wheel 1 not trusted
        assert bench.wait(lambda: bench.driver.diagnostics().level == m.WARN)
        assert "stale wheels: right" in bench.driver.diagnostics().message
        # with one wheel untrusted no reading has every wheel: past silence_s the silence is said, and why
        assert bench.wait(lambda: "no wheel readings" in bench.driver.diagnostics().message)
        assert "stale wheels: right" in bench.driver.diagnostics().message


def test_a_0_6_heartbeat_read_as_0_5_says_so() -> None:
    with Bench("0.6", "odrive:0,1", {"odrive": {"firmware": "0.5"}}) as bench:
        assert bench.wait(lambda: "no wheel readings" in bench.driver.diagnostics().message, 5.0)
        status = bench.driver.diagnostics()
        assert not bench.good_wheels()
    assert status.level == m.WARN and 'firmware = "auto"' in status.message and "encoder error" in status.message


def test_wrong_node_ids_name_the_ids_on_the_bus() -> None:
    with Bench("0.5", "odrive:2,3") as bench:
        assert bench.wait(lambda: "no wheel readings" in bench.driver.diagnostics().message, 5.0)
        message = bench.driver.diagnostics().message
    assert "no frames from ODrive node(s) 2,3" in message and "heard on the bus: 0,1" in message


def test_record_a_firmware_0_6_odrive_with_the_default_configuration(tmp_path: Path, capsys) -> None:
    """The acceptance case: `trundle emulate can --firmware 0.6` recorded with `--encoders odrive:0,1`
    and nothing else gives /wheels, and the detected firmware is in /diagnostics."""
    link = tmp_path / "ttyCAN0"
    emulator = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", "can", "--protocol", "odrive",
                                 "--firmware", "0.6", "--link", str(link), "--script", "0:0.5,0.5",
                                 "--duration", "30"],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not link.exists() and time.monotonic() < deadline and emulator.poll() is None:
            time.sleep(0.05)
        assert link.exists(), emulator.communicate()[1] if emulator.poll() is not None else "no link"
        out = tmp_path / "run.mcap"
        assert main(["record", "--can", f"slcan://{link}", "--encoders", "odrive:0,1", "--duration", "3",
                     "-o", str(out)]) == 0, capsys.readouterr().err
    finally:
        emulator.terminate()
        emulator.communicate(timeout=30)
    reader = LogReader(out)
    wheels = [x.msg for x in reader.messages(["/wheels"])]
    good = [w for w in wheels if np.isfinite(w.position).all()]
    assert len(good) > 50
    assert math.isclose(good[-1].position[0] - good[0].position[0],
                        2 * math.pi * 0.5 * (good[-1].stamp_ns - good[0].stamp_ns) * 1e-9, rel_tol=0.2)
    last = [x.msg for x in reader.messages(["/diagnostics"])][-1]
    values = dict(next(s for s in last.status if s.name == "can").values)
    assert values["odrive.0.firmware"].startswith("0.6.10 (Get_Version")
