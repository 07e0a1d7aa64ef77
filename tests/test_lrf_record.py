"""`trundle record --lrf` and `trundle emulate lrf` end to end: emulator -> driver -> MCAP -> reader."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from tests.lrf_harness import wait_until
from trundle.drivers.rplidar_driver import Revolution, revolution_scan
from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.faults import parse_faults
from trundle.tools.emulators.rplidar_emulator import FLAGS, KINDS, RplidarDevice
from trundle.tools.emulators.rplidar_emulator import MODELS as RPLIDAR_MODELS
from trundle.tools.emulators.scene import DEFAULT_SCENE, load_scene
from trundle.tools.emulators.scip2_emulator import MODELS, ScipDevice


def test_record_scip2_to_mcap(tmp_path):
    model = MODELS["urg-04lx"]
    device = ScipDevice(model, load_scene().range_source(model.angles, seed=9), now_ns=time.time_ns())
    config = tmp_path / "robot.toml"
    config.write_text('[lrf]\nframe_id = "front_laser"\nx = 0.2\nyaw = 0.1\n')
    out = tmp_path / "run.mcap"
    with DeviceServer(device, link_path=tmp_path / "lrf"):
        code = main(["record", "--lrf", f"scip2://{tmp_path / 'lrf'}", "--config", str(config),
                         "-o", str(out), "--duration", "2"])
    assert code == 0
    with LogReader(out) as reader:
        messages = list(reader.messages())
    scans = [x.msg for x in messages if x.topic == "/scan"]
    assert len(scans) >= 5 and all(s.frame_id == "front_laser" for s in scans)
    sent = {s.timestamp: s for s in device.sent}
    timing = [x.msg for x in messages if x.topic == "/scan/timing"]
    assert len(timing) == len(scans)
    for scan, info in zip(scans, timing, strict=True):
        raw = int(dict(info.status[0].values)["raw_ms"])
        want = sent[raw].distances / 1000.0
        want = np.where(sent[raw].distances == 0, np.inf, np.where(sent[raw].distances < 20, np.nan, want))
        np.testing.assert_array_equal(scan.ranges, want.astype(np.float32))
    (tf,) = [x.msg for x in messages if x.topic == "/tf_static"][0].transforms
    assert (tf.frame_id, tf.child_frame_id, tf.translation[0]) == ("base_link", "front_laser", 0.2)
    diagnostics = [x.msg for x in messages if x.topic == "/diagnostics"][-1]
    values = dict(diagnostics.status[0].values)
    assert values["scans"] == str(len(scans)) and values["serial"] == "H0614967"


def record_rplidar(tmp_path, model: str, mode: str, faults: str = "", seconds: float = 1.5):
    """``trundle record --lrf rplidar://...?model=M&mode=X`` against the emulated model: the
    logged scans and diagnostics, the device and the driver options used."""
    spec = RPLIDAR_MODELS[model]
    device = RplidarDevice(spec, load_scene().range_source(spec.angles), parse_faults(faults, KINDS, FLAGS),
                           now_ns=time.time_ns())
    out = tmp_path / f"{model}-{mode}.mcap"
    query = f"model={model}" + (f"&mode={mode}" if mode else "")
    with DeviceServer(device, link_path=tmp_path / "ttyUSB0", backlog=1 << 24):
        code = main(["record", "--lrf", f"rplidar://{tmp_path / 'ttyUSB0'}?{query}", "-o", str(out),
                     "--duration", str(seconds)])
    assert code == 0
    with LogReader(out) as reader:
        messages = list(reader.messages(["/scan", "/diagnostics"]))
    scans = [x.msg for x in messages if x.topic == "/scan"]
    values = dict(next(s for s in [x.msg for x in messages if x.topic == "/diagnostics"][-1].status
                       if s.name == "lrf").values)
    return scans, values, device


def logged_revolutions(scans: list[m.LaserScan], device: RplidarDevice) -> list:
    """Every logged scan is a whole revolution the device sent intact: its ranges equal that
    revolution binned onto the scan's grid (angles from each sample's measurement angle)."""
    mode = device.mode or device.model.standard
    limits = (device.model.range_min, mode.mode.max_distance)
    found = []
    for scan in scans:
        n = scan.ranges.size
        want = [r for r in device.sent if np.array_equal(scan.ranges, revolution_scan(
            Revolution(r.angle_q6, r.distance_q2, r.quality, 0, 1), n, *limits).ranges, equal_nan=True)]
        assert len(want) == 1 and set(want[0].faults) <= {"stall"}
        found.append(want[0])
    assert [r.index for r in found] == sorted({r.index for r in found})  # in order, none twice
    return found


@pytest.mark.parametrize("model, mode", [(name, mode.mode.name) for name in ("s2", "c1", "a3")
                                         for mode in RPLIDAR_MODELS[name].modes])
def test_record_rplidar_every_mode_of_s2_c1_a3(tmp_path, model, mode):
    scans, values, device = record_rplidar(tmp_path, model, mode)
    found = logged_revolutions(scans, device)
    spec = RPLIDAR_MODELS[model].mode(mode)
    assert len(found) >= 5 and scans[0].ranges.size == spec.samples
    assert values["scan_mode"] == mode and values["scans"] == str(len(scans))
    # every revolution the device completed after the first logged one is in the log
    assert found[-1].index - found[0].index + 1 == len(found)
    assert isinstance(scans[0], m.LaserScan) and scans[0].time_increment < 0


@pytest.mark.parametrize("model", ["s2", "c1", "a3"])
def test_record_rplidar_counts_every_fault_kind(tmp_path, model):
    """Checksum errors, lost bytes, garbage and stalls in the typical mode: every logged scan is
    a revolution sent intact, and every faulted revolution the driver saw is counted. (This seed
    never damages more than two revolutions in a row: the driver reconnects after four.)"""
    scans, values, device = record_rplidar(tmp_path, model, "", "checksum=0.1,truncate=0.1,garbage=0.1,"
                                           "stall=0.08,stall_s=0.1,seed=6", seconds=3.0)
    found = logged_revolutions(scans, device)
    assert found and all(kind in device.injected for kind in ("checksum", "truncate", "garbage"))
    seen = [r for r in device.sent if found[0].index < r.index < found[-1].index]
    damaged = sum(bool(set(r.faults) - {"stall"}) for r in seen)
    dropped = int(values["corrupt_revolutions"]) + int(values["incomplete_revolutions"])
    assert damaged <= dropped <= damaged + 4  # the ones before the first and after the last logged scan
    assert len(found) == len(seen) - damaged + 2
    assert int(values["bad_capsules" if device.format else "bad_nodes"]) >= device.injected["checksum"] - 2
    assert values["reconnects"] == "0"


def test_trundle_emulate_and_record_s2(tmp_path):
    """Black box: ``trundle emulate lrf --protocol rplidar --model s2`` in its own process, then
    ``trundle record``: DenseBoost revolutions of a noise-free room, every range the room's
    distance to the millimetre."""
    scene = tmp_path / "room.toml"
    scene.write_text(DEFAULT_SCENE.read_text().replace("noise_m = 0.005", "noise_m = 0.0"))
    link = tmp_path / "s2"
    emulator = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", "lrf", "--protocol", "rplidar",
                                 "--model", "s2", "--link", str(link), "--scene", str(scene), "--duration", "30"],
                                stderr=subprocess.PIPE, text=True)
    try:
        wait_until(link.exists, "the emulator's link")
        out = tmp_path / "s2.mcap"
        assert main(["record", "--lrf", f"rplidar://{link}?model=s2", "-o", str(out), "--duration", "1.5"]) == 0
    finally:
        emulator.terminate()
        _, err = emulator.communicate(timeout=20)
    assert "emulating rplidar s2" in err
    with LogReader(out) as reader:
        scans = [x.msg for x in reader.messages(["/scan"])]
    model = RPLIDAR_MODELS["s2"]
    dense = model.mode("DenseBoost")
    grid = model.angles[::model.grid // dense.samples][::-1]  # beam i holds device sample N - 1 - i
    room = load_scene(scene).ranges(grid)
    want = np.where((room >= model.range_min) & (room <= dense.mode.max_distance), np.round(room * 1000) / 1000, np.inf)
    assert len(scans) >= 5
    for scan in scans:
        assert scan.ranges.size == dense.samples and scan.range_max == pytest.approx(30.0)
        np.testing.assert_array_equal(scan.ranges, want.astype(np.float32))


def test_emulate_lrf_command(tmp_path, capsys):
    assert main(["emulate", "lrf", "--link", str(tmp_path / "lrf"), "--faults", "bogus=1"]) == 2
    assert "unknown fault 'bogus'" in capsys.readouterr().err
    assert main(["emulate", "lrf", "--link", str(tmp_path / "none" / "lrf")]) == 2
    assert main(["emulate", "lrf", "--protocol", "rplidar", "--model", "urg-04lx", "--tcp", "0"]) == 2
    assert main(["emulate", "lrf", "--scene", str(tmp_path / "missing.toml"), "--tcp", "0"]) == 2
    assert "no such scene file" in capsys.readouterr().err
    for model in ("a2", "s2", "c1", "a3"):
        code = main(["emulate", "lrf", "--protocol", "rplidar", "--model", model, "--link", str(tmp_path / "lrf"),
                     "--faults", "checksum=0.1,seed=2", "--duration", "0.3"])
        assert code == 0 and f"emulating rplidar {model}" in capsys.readouterr().err
