"""`trundle record --lrf` and `trundle emulate lrf` end to end: emulator -> driver -> MCAP -> reader."""

from __future__ import annotations

import time

import numpy as np

from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.rplidar_emulator import MODELS as RPLIDAR_MODELS, RplidarDevice
from trundle.tools.emulators.scene import load_scene
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
    for scan, info in zip(scans, timing):
        raw = int(dict(info.status[0].values)["raw_ms"])
        want = sent[raw].distances / 1000.0
        want = np.where(sent[raw].distances == 0, np.inf, np.where(sent[raw].distances < 20, np.nan, want))
        np.testing.assert_array_equal(scan.ranges, want.astype(np.float32))
    (tf,) = [x.msg for x in messages if x.topic == "/tf_static"][0].transforms
    assert (tf.frame_id, tf.child_frame_id, tf.translation[0]) == ("base_link", "front_laser", 0.2)
    diagnostics = [x.msg for x in messages if x.topic == "/diagnostics"][-1]
    values = dict(diagnostics.status[0].values)
    assert values["scans"] == str(len(scans)) and values["serial"] == "H0614967"


def test_record_rplidar_to_mcap(tmp_path):
    model = RPLIDAR_MODELS["a2"]
    device = RplidarDevice(model, load_scene().range_source(model.angles), now_ns=time.time_ns())
    out = tmp_path / "run.mcap"
    with DeviceServer(device, link_path=tmp_path / "ttyUSB0"):
        code = main(["record", "--lrf", f"rplidar://{tmp_path / 'ttyUSB0'}?model=a2&beams=180",
                         "-o", str(out), "--duration", "1.5"])
    assert code == 0
    with LogReader(out) as reader:
        scans = [x.msg for x in reader.messages(["/scan"])]
    assert len(scans) >= 5
    starts = {r.start_ns: r for r in device.sent}
    for scan in scans:
        first = scan.stamp_ns - int(scan.scan_time * 1e9 * 179 / 180)
        rev = starts[min(starts, key=lambda s: abs(s - first))]
        want = np.where(rev.distance_q2 == 0, np.inf, rev.distance_q2 / 4000.0).astype(np.float32)[::-1]
        np.testing.assert_array_equal(scan.ranges, want)
    assert isinstance(scans[0], m.LaserScan) and scans[0].time_increment < 0


def test_emulate_lrf_command(tmp_path, capsys):
    assert main(["emulate", "lrf", "--link", str(tmp_path / "lrf"), "--faults", "bogus=1"]) == 2
    assert "unknown fault 'bogus'" in capsys.readouterr().err
    assert main(["emulate", "lrf", "--link", str(tmp_path / "none" / "lrf")]) == 2
    assert main(["emulate", "lrf", "--protocol", "rplidar", "--model", "urg-04lx", "--tcp", "0"]) == 2
    assert main(["emulate", "lrf", "--scene", str(tmp_path / "missing.toml"), "--tcp", "0"]) == 2
    assert "no such scene file" in capsys.readouterr().err
    code = main(["emulate", "lrf", "--protocol", "rplidar", "--model", "a2", "--link", str(tmp_path / "lrf"),
                     "--faults", "checksum=0.1,seed=2", "--duration", "0.3"])
    assert code == 0 and "emulating rplidar a2" in capsys.readouterr().err
