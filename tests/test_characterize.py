"""`trundle characterize` recovers characteristics injected into an emulated laser.

The SCIP 2.0 emulator serves a stepped distance sweep (every beam sees the same true
distance, rising then falling) through an impairment of known gain, bias, non-linearity,
hysteresis and noise, at an injected scan rate; our driver records it over a pty. The
expected figures are derived from the impairment's formula by hand, not by our code.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import threading
from pathlib import Path

import numpy as np
import pytest
from lrf_harness import Recorder, running, wait_until

from trundle.drivers.lrf import driver_from_url
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main
from trundle.tools.emulators.device_server import DeviceServer
from trundle.tools.emulators.scip2_emulator import MODELS, ScipDevice
from trundle.tools.sim.sensor_model import RangeImpairment

GAIN, BIAS, QUAD, CENTRE, HYST, NOISE = 1.02, 0.05, 0.02, 2.5, 0.03, 0.01
LEVELS = np.round(np.arange(1.0, 4.0001, 0.25), 2)  # 13 levels, symmetric about CENTRE
# Up to a turning point past the top, down to one below the bottom: every level in LEVELS is
# met rising and falling (27 holds); the turning points 4.25 and 0.75 are met from one side.
SWEEP = np.concatenate([LEVELS, [4.25], LEVELS[::-1], [0.75]])
SCANS_PER_HOLD = 5
RPM = 1200  # 20 Hz injected instead of the UTM-30LX's 40 Hz


class Sweep:
    """Range source: hold each level for SCANS_PER_HOLD scans; remember (time, true value)."""

    def __init__(self, beams: int) -> None:
        self.beams = beams
        self.impair = RangeImpairment(GAIN, BIAS, QUAD, CENTRE, HYST, NOISE, quantum=0.0, seed=7)
        self.rows: list[tuple[int, float]] = []
        self.lock = threading.Lock()

    def __call__(self, t_s: float) -> np.ndarray:
        with self.lock:
            k = len(self.rows)
            v = float(SWEEP[min(k // SCANS_PER_HOLD, SWEEP.size - 1)])
            if k < SWEEP.size * SCANS_PER_HOLD:
                self.rows.append((round(t_s * 1e9), v))
        return self.impair(np.full(self.beams, v))

    @property
    def done(self) -> bool:
        with self.lock:
            return len(self.rows) >= SWEEP.size * SCANS_PER_HOLD


def test_injected_characteristics_are_recovered_within_5_percent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = MODELS["utm-30lx"]
    model = dataclasses.replace(base, params=dataclasses.replace(base.params, rpm=RPM))
    sweep = Sweep(model.steps.size)
    link = tmp_path / "ttyLRF"
    server = DeviceServer(ScipDevice(model, sweep), link_path=link)
    sink = Recorder()
    with running(server, driver_from_url(f"scip2://{link}", sink, {})):
        wait_until(lambda: sweep.done, "the sweep to finish")
        wait_until(lambda: sink.scans() and sink.scans()[-1].stamp_ns > sweep.rows[-1][0] + 100_000_000,
                   "the last sweep scan to be logged")
    log = tmp_path / "sweep.mcap"
    with Logger(log) as logger:
        for scan in sink.scans():
            logger.write("/scan", scan, scan.stamp_ns)
    reference = tmp_path / "truth.csv"
    with open(reference, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t_ns", "value"])
        writer.writerows(sweep.rows)

    assert main(["characterize", str(log), "--topic", "/scan", "--reference", str(reference), "--json",
                 "-o", str(tmp_path / "report")]) == 0
    fig = json.loads(capsys.readouterr().out)

    # By hand: the static curve is GAIN*v + BIAS + QUAD*(v-CENTRE)^2 over 13 levels with
    # (v-CENTRE) = 0.25*k, k=-6..6, so mean((v-CENTRE)^2) = 0.0625*182/13 = 0.875; the line
    # through it has slope GAIN and intercept BIAS + 0.875*QUAD, and its worst deviation is
    # QUAD*(1.5^2 - 0.875) at the ends, over a full scale of GAIN*3 m.
    sens = fig["sensitivity"]
    assert sens["gain"] == pytest.approx(GAIN, rel=0.05)
    assert sens["offset"] == pytest.approx(BIAS + 0.875 * QUAD, rel=0.05)
    assert sens["nonlinearity"] == pytest.approx(QUAD * (2.25 - 0.875), rel=0.05)
    assert sens["nonlinearity_percent_fs"] == pytest.approx(100 * QUAD * 1.375 / (GAIN * 3), rel=0.05)
    assert fig["hysteresis"]["hysteresis"] == pytest.approx(HYST, rel=0.05)
    assert fig["errors"]["noise_std"] == pytest.approx(NOISE, rel=0.05)
    # Systematic error: the mean of GAIN*v + BIAS + QUAD*(v-c)^2 +- HYST/2 - v over the sweep.
    v = np.array([row[1] for row in sweep.rows])
    direction = np.repeat(np.concatenate([[1.0], np.sign(np.diff(SWEEP))]), SCANS_PER_HOLD)[: v.size]
    expected_bias = np.mean((GAIN - 1) * v + BIAS + QUAD * (v - CENTRE) ** 2 + HYST / 2 * direction)
    assert fig["errors"]["bias"] == pytest.approx(expected_bias, rel=0.05)
    assert fig["bandwidth"]["rate_hz"] == pytest.approx(RPM / 60, rel=0.05)
    assert fig["class"] == {"sense": "exteroceptive", "energy": "active",
                            "application": fig["class"]["application"]}
    assert (tmp_path / "report" / "report.md").exists() and (tmp_path / "report" / "sensitivity.png").exists()


def test_bad_topic_and_reference_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "empty.mcap"
    with Logger(log):
        pass
    assert main(["characterize", str(log), "--topic", "/scan"]) == 2
    assert "not in" in capsys.readouterr().err


def test_real_hokuyo_log_gives_per_beam_noise_where_the_robot_stands_still(tmp_path: Path) -> None:
    """exp2.dat (a real URG-04LX with wheel encoders): standing-still stretches are found from
    the wheel angles; every beam that returned gets a noise figure, plotted."""
    from conftest import shared_file

    from trundle.logs.importers.breezyslam import import_breezyslam

    log = tmp_path / "exp2.mcap"
    import_breezyslam(shared_file("breezyslam/exp2.dat"), log)
    out = tmp_path / "report"
    assert main(["characterize", str(log), "--topic", "/scan", "-o", str(out)]) == 0
    fig = json.loads((out / "report.json").read_text())
    assert fig["still_from"] == "odometry"
    static = fig["static"]
    assert len(static["intervals_s"]) >= 1 and static["scans"] >= 20
    assert static["beams_with_noise"] > 200
    # URG-04LX datasheet accuracy: +-10 mm (60 mm - 1 m), 1 % of distance beyond
    assert 0.001 < static["beam_noise_std_median"] < 0.02
    assert fig["range"]["resolution"] == pytest.approx(0.001, rel=0.01)  # millimetre output
    assert fig["range"]["upper"] <= fig["range"]["stated_upper"]
    assert fig["bandwidth"]["rate_hz"] == pytest.approx(10.0, rel=0.05)
    assert (out / "beam_noise.png").stat().st_size > 5000


def test_encoder_counts_per_revolution_from_real_ticks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """exp2's wheel encoders give 2000 ticks per revolution (BreezySLAM's robot model)."""
    from conftest import shared_file

    from trundle.logs.importers.breezyslam import import_breezyslam

    log = tmp_path / "exp2.mcap"
    import_breezyslam(shared_file("breezyslam/exp2.dat"), log)
    assert main(["characterize", str(log), "--topic", "/joint_states", "--json"]) == 0
    fig = json.loads(capsys.readouterr().out)
    assert fig["class"]["sense"] == "proprioceptive"
    for joint in ("left", "right"):
        assert fig["joints"][joint]["counts_per_revolution"] == pytest.approx(2000, rel=1e-4)
    assert fig["bandwidth"]["rate_hz"] == pytest.approx(10.0, rel=0.05)


def test_camera_rate_jitter_and_dropped_frames(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from trundle.logs import messages as m

    period = 1_000_000_000 // 30
    frames = [k for k in range(90) if k not in (10, 40, 41)]
    log = tmp_path / "cam.mcap"
    with Logger(log) as logger:
        for k in frames:
            logger.write(
                "/camera/image_raw/compressed",
                m.CompressedImage(k * period, "camera", "jpeg", b"\xff\xd8\xff\xd9"),
                k * period,
            )
    assert main(["characterize", str(log), "--topic", "/camera/image_raw/compressed", "--json"]) == 0
    fig = json.loads(capsys.readouterr().out)
    assert fig["class"]["energy"] == "passive"
    assert fig["dropped_frames"] == 3
    assert fig["bandwidth"]["rate_hz"] == pytest.approx(30.0, rel=1e-6)
    assert fig["bandwidth"]["jitter_s"] < 1e-8
