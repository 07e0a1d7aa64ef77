"""BreezySLAM / CoreSLAM ``.dat`` logs (Paris Mines rover) -> JointState + LaserScan messages.

One scan per line: token 0 time (microseconds, device clock), tokens 2 and 3 the left and right
cumulative wheel-encoder ticks, tokens 24.. ranges in mm of a Hokuyo URG-04LX (682 beams used,
the last token dropped, as BreezySLAM's loader does). Models (``../shared/data/README.md``):

- wheels: 2000 ticks per revolution, radius 77 mm, track 330 mm; ticks become wheel angles
  (``JointState`` positions ``left``/``right`` in rad) so our differential-drive odometry makes
  the poses, exactly as it does for our own encoders;
- laser: the physical URG-04LX geometry, beam i at ``(i - 340) * 360/1024`` deg (steps 44..725);
  0 = no return (+inf), 1..19 = URG-04LX error codes (NaN), 20..5600 mm valid; mounted 145 mm
  ahead of the wheel axle (``/tf_static`` base_link -> laser).

Stamps stay in the device clock (ns); the log holds no wall-clock time to mix it with. A line's
time is taken as the end of the sweep (the last beam, when the scan was read out), so each
LaserScan is stamped 681 steps of 97.66 us (100 ms / 1024) earlier, at its first beam as ROS
stamps scans; wheel readings keep the line's time. (Measured: de-skewing exp2's scans with this
timing gives lower scan-to-map residuals than taking the line's time as the first or middle beam.)
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import DataError
from trundle.logs.importers import Item, open_text, write_log
from trundle.logs.topics import JOINT_STATES_TOPIC, SCAN_TOPIC, TF_STATIC_TOPIC

TICKS_PER_REV = 2000
WHEEL_RADIUS_M = 0.077
TRACK_M = 0.330
LASER_OFFSET_M = 0.145
BEAMS = 682
FIRST_RANGE_TOKEN = 24
ANGLE_STEP = 2.0 * math.pi / 1024.0
ANGLE_MIN = -340 * ANGLE_STEP
RANGE_MIN_M, RANGE_MAX_M = 0.020, 5.6
SCAN_TIME_S = 0.1
STEP_S = SCAN_TIME_S / 1024.0
SWEEP_NS = round((BEAMS - 1) * STEP_S * 1e9)
ROBOT = {"wheel_radius_m": WHEEL_RADIUS_M, "track_m": TRACK_M, "wheels": ["left", "right"], "laser_x_m": LASER_OFFSET_M}


@dataclass(frozen=True)
class DatLine:
    """One parsed line: device time (us), cumulative ticks, ranges (mm, 682 values)."""

    time_us: int
    left_ticks: int
    right_ticks: int
    ranges_mm: np.ndarray


def parse_line(line: str) -> DatLine | None:
    """One ``.dat`` line; None for a blank line; ValueError when fields are missing or not integers."""
    tokens = line.split()
    if not tokens:
        return None
    if len(tokens) < FIRST_RANGE_TOKEN + BEAMS:
        raise ValueError(f"needs at least {FIRST_RANGE_TOKEN + BEAMS} tokens, got {len(tokens)}")
    ranges = np.array([int(t) for t in tokens[FIRST_RANGE_TOKEN:FIRST_RANGE_TOKEN + BEAMS]], np.int64)
    if ranges.min() < 0:
        raise ValueError("negative range")
    return DatLine(int(tokens[0]), int(tokens[2]), int(tokens[3]), ranges)


def read_dat(path: str | os.PathLike[str]) -> tuple[list[DatLine], int]:
    """Parsed lines in file order and the number of malformed lines dropped."""
    lines: list[DatLine] = []
    malformed = 0
    for text in open_text(path):
        try:
            parsed = parse_line(text)
        except ValueError:
            malformed += 1
            continue
        if parsed is not None:
            lines.append(parsed)
    if not lines:
        raise DataError(f"{path}: no scan line (is it a BreezySLAM .dat log?)")
    return lines, malformed


def ranges_to_metres(ranges_mm: np.ndarray) -> np.ndarray:
    """URG-04LX readings (mm) as REP 117 ranges (m): 0 -> +inf, 1..19 (error codes) -> NaN."""
    ranges = np.asarray(ranges_mm, dtype=np.float64) / 1000.0
    ranges[ranges_mm == 0] = np.inf
    ranges[(ranges_mm > 0) & (ranges_mm < 20)] = np.nan
    return ranges


def messages(lines: list[DatLine]) -> Iterator[Item]:
    """The log as ``(topic, message, log_time_ns)``: /tf_static, then /joint_states and /scan per line.

    Device times that step back are kept as stamps; log times are made non-decreasing.
    """
    last = -(1 << 62)
    for k, line in enumerate(lines):
        stamp = line.time_us * 1000
        last = max(last, stamp)
        if k == 0:
            yield TF_STATIC_TOPIC, m.TFMessage((m.TransformStamped.planar(stamp, "base_link", "laser", LASER_OFFSET_M,
                                                                       0.0, 0.0),)), last
        angles = np.array([line.left_ticks, line.right_ticks], np.float64) * (2.0 * math.pi / TICKS_PER_REV)
        yield JOINT_STATES_TOPIC, m.JointState(stamp, "base_link", ("left", "right"), angles), last
        scan = m.LaserScan(stamp - SWEEP_NS, "laser", ANGLE_MIN, ANGLE_MIN + ANGLE_STEP * (BEAMS - 1), ANGLE_STEP,
                           STEP_S, SCAN_TIME_S, RANGE_MIN_M, RANGE_MAX_M, ranges_to_metres(line.ranges_mm))
        yield SCAN_TOPIC, scan, last


def import_breezyslam(path: str | os.PathLike[str], out: str | os.PathLike[str]) -> dict[str, int]:
    """Convert a BreezySLAM ``.dat`` log to MCAP; returns messages written per topic.

    The robot model travels with the log as metadata ``robot`` (JSON), so ``trundle slam`` can
    make odometry from the wheel angles without a config file.
    """
    lines, malformed = read_dat(path)
    metadata: dict[str, object] = {
        "command": "import breezyslam",
        "source": os.fspath(path),
        "malformed_lines": str(malformed),
        "robot": ROBOT,
    }
    return write_log(messages(lines), out, metadata=metadata)
