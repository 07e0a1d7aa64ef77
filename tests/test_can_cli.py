"""`trundle emulate can` in its own process and `trundle record --can ... --encoders ...` into an
MCAP log; the raw frames in the log decode again to the logged wheel angles."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from trundle.drivers import odrive
from trundle.drivers.wheels import MAX_CARRY_S
from trundle.fusion.odometry.diff_drive import odometry_from_config
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


def start_emulator(link: Path, *options: str) -> subprocess.Popen:
    """`trundle emulate can --protocol odrive` (30 s) at ``link`` with ``options``, once its link exists."""
    emulator = subprocess.Popen([sys.executable, "-m", "trundle.tools.cli", "emulate", "can", "--protocol", "odrive",
                                 "--link", str(link), "--duration", "30", *options],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 90
    while not link.exists() and time.monotonic() < deadline and emulator.poll() is None:
        time.sleep(0.05)
    assert link.exists(), emulator.stderr.read() if emulator.poll() is not None else "no link"
    return emulator


def test_the_emulator_stands_still_by_default_as_the_laser_scene_does(tmp_path, capsys):
    """A first recording of `emulate can` and `emulate lrf` (a still scene) agrees: no --script, no motion."""
    link = tmp_path / "ttyCAN0"
    emulator = start_emulator(link)
    try:
        out = tmp_path / "still.mcap"
        assert main(["record", "--can", f"slcan://{link}", "--encoders", "odrive:0,1", "--duration", "2",
                     "-o", str(out)]) == 0
    finally:
        emulator.terminate()
        stdout, _ = emulator.communicate(timeout=10)
    assert stdout.startswith(f"SLCAN adapter on {link} (odrive nodes [0, 1]); the wheels stand still "
                             "(give --script to drive them); record with:")
    with LogReader(out) as log:
        wheels = [w.msg for w in log.messages(["/wheels"]) if np.isfinite(w.msg.position).all()]
    assert len(wheels) > 20
    assert all(np.array_equal(w.position, wheels[0].position) and not w.velocity.any() for w in wheels)


def test_record_from_the_emulator_process(tmp_path, capsys):
    link = tmp_path / "ttyCAN0"
    emulator = start_emulator(link, "--script", "0:0.5,0.5", "--fault", "1.0:heartbeat-stop:1",
                              "--fault", "1.8:heartbeat-resume:1")
    try:
        config = tmp_path / "robot.toml"
        config.write_text("[can]\nwheel_radius_m = 0.1\ntrack_m = 0.5\n")
        out = tmp_path / "run.mcap"
        assert main(["record", "--can", f"slcan://{link}", "--encoders", "odrive:0,1", "--config", str(config),
                     "--duration", "3", "-o", str(out)]) == 0
    finally:
        emulator.terminate()
        stdout, _ = emulator.communicate(timeout=10)
    assert "fault: heartbeat-stop (wheel 1)" in stdout and emulator.returncode == 0
    with LogReader(out) as log:
        info = log.info()
        assert {"/can/rx", "/wheels", "/diagnostics", "/odom", "/tf"} <= set(info.topics)
        frames = [m.msg for m in log.messages(["/can/rx"])]
        wheels = [m.msg for m in log.messages(["/wheels"])]
        live = [m.msg for m in log.messages(["/odom"])]
    odometry = odometry_from_config({"wheel_radius_m": 0.1, "track_m": 0.5})  # on the log, as on the robot
    odoms = [o for o in map(odometry.update, wheels) if o is not None]
    # re-decode the logged raw frames: each right-wheel angle is the last right estimate logged
    # before it, carried forward by its velocity to the wheel state's stamp (if at most 50 ms old)
    right = [(f.stamp_ns, *odrive.decode_encoder_estimates(f.data)) for f in frames
             if f.id == odrive.arbitration_id(1, odrive.GET_ENCODER_ESTIMATES)]
    stamps = np.array([r[0] for r in right])
    good = [w for w in wheels if np.isfinite(w.position).all()]
    for state in good[-50:]:
        stamp, pos, vel = right[int(np.searchsorted(stamps, state.stamp_ns, side="right")) - 1]
        lag_s = (state.stamp_ns - stamp) * 1e-9
        carried = pos + vel * lag_s if lag_s <= MAX_CARRY_S else pos
        assert state.position[1] == pytest.approx(2 * math.pi * carried, abs=1e-9)
    assert any(math.isnan(w.position[1]) for w in wheels)  # the heartbeat loss is in the log
    xs = np.array([o.x for o in odoms])
    # Driving straight at 0.5 turn/s on 0.1 m wheels. ODrive positions are cumulative, so the motion
    # during the heartbeat gap is kept: the step over the gap is the distance driven in it, and the
    # whole distance is the speed times the time.
    speed, t = 2 * math.pi * 0.1 * 0.5, np.array([o.stamp_ns for o in odoms]) * 1e-9
    assert xs[-1] - xs[0] == pytest.approx(speed * (t[-1] - t[0]), rel=0.05)
    gap = int(np.argmax(np.diff(t)))
    assert np.diff(t)[gap] > 0.3 and xs[gap + 1] - xs[gap] == pytest.approx(speed * np.diff(t)[gap], rel=0.1)
    assert odometry.gaps >= 1
    # the odometry recorded live is the odometry the same code computes again from the log
    assert len(live) == len(odoms)  # (yaw travels as a quaternion: equal to rounding)
    np.testing.assert_allclose([(o.x, o.y, o.theta) for o in live], [(o.x, o.y, o.theta) for o in odoms], atol=1e-12)


@pytest.mark.parametrize("argv", [
    ["--protocol", "odrive", "--link", "{tmp}/l", "--fault", "soon:bus-off"],
    ["--protocol", "odrive", "--link", "{tmp}/l", "--fault", "1:explode"],
    ["--protocol", "odrive", "--link", "{tmp}/l", "--script", "0:1"],
    ["--protocol", "odrive", "--link", "{tmp}/l", "--nodes", "0,x"],
    ["--protocol", "odrive", "--link", "/nonexistent/dir/l"],
])
def test_emulator_user_errors(tmp_path, capsys, argv):
    assert main(["emulate", "can", *[a.format(tmp=tmp_path) for a in argv]]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trundle emulate: ") and err.count("\n") == 1
