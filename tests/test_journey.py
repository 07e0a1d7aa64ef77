"""The user's journey: a log made by the recorder (from the emulators) and one made by the daemon
(the demo's short log) go through every command that reads a log: info, slam, localize on slam's
map, perceive with each pipeline, characterize, export, replay, recover on a cut copy and slam on
the recovered file. Each ends with exit code 0, no traceback and output that makes sense."""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tests.cli_run import succeeds
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.emulators.camera_emulator import CameraEmulator
from trundle.tools.emulators.can_nodes import CanNodeRunner, VelocityScript, WheelMotion, odrive_nodes
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.scene import load_scene
from trundle.tools.emulators.scip2_emulator import MODELS, ScipDevice
from trundle.tools.emulators.slcan_emulator import SlcanEmulator

DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo_short" / "demo.mcap"


@pytest.fixture(scope="module")
def recorder_log(tmp_path_factory) -> Path:
    """`trundle record` of an emulated laser, two ODrive axes (firmware 0.6: the default `auto`
    must read them) behind an SLCAN adapter and an MJPEG camera, with the wheel model in --config."""
    folder = tmp_path_factory.mktemp("recorder")
    model = MODELS["utm-30lx"]
    laser = ScipDevice(model, load_scene().range_source(model.angles, seed=3), now_ns=time.time_ns())
    adapter = SlcanEmulator(str(folder / "ttyCAN0")).start()
    runner = CanNodeRunner(adapter.bus, odrive_nodes([0, 1], firmware="0.6"),
                           WheelMotion(VelocityScript.parse("0:0.5,0.5;2:0.5,-0.5;3:0.5,0.5")), adapter=adapter)
    config = folder / "robot.toml"
    config.write_text('[lrf]\nx = 0.2\n\n[can]\nwheel_radius_m = 0.1\ntrack_m = 0.5\ndirection = [1, -1]\n')
    out = folder / "run.mcap"
    runner.start()
    try:
        with DeviceServer(laser, link_path=folder / "lrf"), CameraEmulator(fps=10, width=320, height=240) as camera:
            code = main(["record", "--lrf", f"scip2://{folder / 'lrf'}", "--can", f"slcan://{folder / 'ttyCAN0'}",
                         "--encoders", "odrive:0,1", "--camera", camera.url, "--config", str(config),
                         "--duration", "6", "-o", str(out)])
    finally:
        runner.stop()
        adapter.close()
    assert code == 0
    return out


@pytest.fixture(params=["recorder", "daemon"])
def log(request, recorder_log) -> Path:
    return recorder_log if request.param == "recorder" else DEMO_LOG


def trundle(capsys, *argv: object) -> str:
    """Run a command: it must end with exit code 0 and no traceback; returns its stdout."""
    return succeeds(capsys, *argv)[0]


def test_every_log_reading_command_works_on_the_recorder_and_daemon_logs(log, tmp_path, capsys):
    info = json.loads(trundle(capsys, "info", log, "--json"))
    topics = info["topics"]
    assert info["complete"] and {"/scan", "/wheels", "/odom", "/camera/image_raw/compressed"} <= set(topics)
    assert "Topic: /scan" in trundle(capsys, "info", log)

    slam = tmp_path / "slam"
    printed = trundle(capsys, "slam", log, "-o", slam)
    report = json.loads((slam / "report.json").read_text())
    assert report["scans"] == topics["/scan"]["count"] and report["keyframes"] > 0
    assert report["odometry_source"].startswith("wheel encoders (/wheels; wheel model from the log's metadata)")
    assert f"odometry: {report['odometry_source']}" in printed
    assert all((slam / name).is_file() for name in ("map.pgm", "map.yaml", "map.png", "trajectory.csv", "slam.mcap"))

    located = json.loads(trundle(capsys, "localize", log, "--map", slam, "--json"))
    assert located["scans"] == report["scans"] and located["odometry"]  # its own map: it converges
    assert located["converged_at_scans"] and located["tracked_scans"] > located["scans"] // 2

    for pipeline, options in (("color", ["--lower", "0,0.5,0.3", "--upper", "360,1,1"]),
                              ("markers", []), ("features", ["--method", "orb"])):
        out = tmp_path / f"{pipeline}.mcap"
        summary = json.loads(trundle(capsys, "perceive", log, "--pipeline", pipeline, "-o", out, "--json", *options))
        assert summary["frames"] == topics["/camera/image_raw/compressed"]["count"] and summary["corrupt_messages"] == 0
        assert LogReader(out).info().complete

    figures = json.loads(trundle(capsys, "characterize", log, "--topic", "/scan", "--json"))
    assert figures["sensor"] == "laser" and figures["scans"] == topics["/scan"]["count"]
    wheels = json.loads(trundle(capsys, "characterize", log, "--topic", "/wheels", "--json"))
    assert wheels["sensor"] == "wheel_encoder" and set(wheels["joints"]) == {"left", "right"}

    rows = trundle(capsys, "export", log, "--topic", "/odom").splitlines()
    assert rows[0].startswith("log_time_ns,") and len(rows) == topics["/odom"]["count"] + 1
    ndjson = tmp_path / "wheels.ndjson"
    trundle(capsys, "export", log, "--topic", "/wheels", "--format", "ndjson", "-o", ndjson)
    assert len(ndjson.read_text().splitlines()) == topics["/wheels"]["count"]

    replayed = trundle(capsys, "replay", log, "--rate", "0")
    assert f"replayed {info['messages']} messages" in replayed

    cut = tmp_path / "cut.mcap.active"  # as a killed recorder leaves it: the first 70 % of the file
    data = log.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    assert "INCOMPLETE" in trundle(capsys, "info", cut)
    recovered = tmp_path / "recovered"
    recovered.mkdir()
    said = trundle(capsys, "recover", cut, recovered)
    fixed = recovered / "cut.mcap"
    assert f"into {fixed}" in said and not list(tmp_path.glob("**/*.tmp"))
    salvage = LogReader(fixed).info()
    assert salvage.complete and 0.4 * info["messages"] < salvage.message_count < info["messages"]
    trundle(capsys, "slam", fixed, "-o", tmp_path / "slam-recovered")
    again = json.loads((tmp_path / "slam-recovered" / "report.json").read_text())
    assert 0 < again["scans"] < report["scans"] and again["odometry_source"] == report["odometry_source"]


def test_the_recorder_log_holds_what_the_devices_sent(recorder_log):
    """Sensible content: the laser's rate, both wheels turning as scripted, the camera's size."""
    reader = LogReader(recorder_log)
    info = reader.info()
    assert info.topics["/scan"].rate_hz == pytest.approx(40.0, rel=0.25)
    wheels = [x.msg for x in reader.messages(["/wheels"]) if np.isfinite(x.msg.position).all()]
    turned = wheels[-1].position - wheels[0].position
    assert turned[0] > 2 * math.pi * 0.5 * 3 and abs(turned[0]) > abs(turned[1])  # right runs backwards 1 s
    (camera_info,) = [x.msg for x in reader.messages(["/camera/camera_info"])]
    assert (camera_info.width, camera_info.height) == (320, 240)
    metadata = info.metadata["trundle"]
    assert metadata["command"] == "record" and json.loads(metadata["devices"])["can"]["wheel_radius_m"] == 0.1


def test_a_carmen_log_without_odom_lines_goes_through_the_journey(tmp_path, capsys):
    """An imported log: odometry from the laser lines (said), then slam says what it ran on."""
    carmen = tmp_path / "run.clf"
    lines = []
    for k in range(40):  # a robot driving 4 m straight down a corridor 2 m wide (walls at y = +-1)
        x = 0.1 * k
        ranges = [min(1.0 / max(abs(math.sin(math.radians(a - 90))), 1e-3), 20.0) for a in range(180)]
        lines.append(
            f"FLASER 180 {' '.join(f'{r:.3f}' for r in ranges)} {x} 0 0 {x} 0 0 {k * 0.2:.1f} host {k * 0.2:.1f}"
        )
    carmen.write_text("\n".join(lines) + "\n")
    imported = tmp_path / "run.mcap"
    said = trundle(capsys, "import", "carmen", carmen, "-o", imported)
    assert "odometry: no ODOM lines: the FLASER lines' odometry fields (40 poses)" in said
    assert LogReader(imported).info().topics["/odom"].count == 40
    trundle(capsys, "slam", imported, "-o", tmp_path / "slam")
    report = json.loads((tmp_path / "slam" / "report.json").read_text())
    assert (
        report["odometry_source"]
        == "odometry messages (/odom): no ODOM lines: the FLASER lines' odometry fields (40 poses)"
    )
    shutil.rmtree(tmp_path / "slam")
    bare = tmp_path / "bare.mcap"
    trundle(capsys, "import", "carmen", carmen, "-o", bare, "--odometry", "none")
    code = main(["slam", str(bare), "-o", str(tmp_path / "slam")])
    out, err = capsys.readouterr()
    assert code == 0 and "odometry: none" in out and "has no odometry" in err and err.count("\n") == 2
    assert "the map's self-check was not made" in err  # 4 m of corridor: no keyframe outside its own submaps
