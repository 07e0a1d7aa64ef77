"""UTIAS MRCLAM (Leung et al., IJRR 2011) robot logs -> Odometry + LandmarkList messages.

The dataset as published, one folder per run: ``RobotN_Odometry.dat`` (``time v w``: forward
speed m/s and turn rate rad/s, each holding until the next line), ``RobotN_Measurement.dat``
(``time barcode range bearing``: a barcode read by the robot's camera; the file's header says
"Subject #" but the numbers are barcodes), ``Barcodes.dat`` (``subject barcode``: subjects 1-5
are the five robots, 6-20 the landmarks), ``Landmark_Groundtruth.dat`` (``subject x y sx sy``,
surveyed) and, optionally, ``RobotN_Groundtruth.dat`` (Vicon ``time x y theta``). Times are
Unix seconds; ``#`` lines are comments.

- ``/odom`` (nav_msgs/Odometry, odom -> base_link): the speeds integrated exactly along arcs,
  one message per odometry line with the pose at its time and its speeds as the twist.
- ``/landmarks`` (trundle_msgs/LandmarkList, base_link): the sightings of one instant; a
  landmark's id is its subject number (``"6"`` .. ``"20"``). Sightings of the other robots
  (subjects 1-5) are not landmarks, and barcodes the table does not list are not known: both are
  counted and dropped.
- Sensor model of the sightings (the dataset publishes none): ``sigma_range = 0.02 m + 3 % of the
  range``, ``sigma_bearing = 2 deg``. Measured on robot 1 of Dataset 2 against the survey and the
  Vicon poses, the robust standard deviations are 0.046, 0.083, 0.089, 0.125 m at 1-2, 2-3, 3-4,
  4-6 m and 1.1-1.6 deg; the model rounds them up so an estimator using it stays consistent. About
  1.4 % of sightings are outliers (beyond 0.5 m), which estimators must reject themselves.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import DataError, UsageError, UserError
from trundle.logs.importers import Item, open_text, write_log
from trundle.logs.stamps import seconds_ns
from trundle.logs.topics import LANDMARK_TOPIC, ODOM_TOPIC

RANGE_SIGMA_M = 0.02
RANGE_SIGMA_FRACTION = 0.03
BEARING_SIGMA_RAD = math.radians(2.0)
ROBOT_SUBJECTS = range(1, 6)  # every other subject is a landmark (6-20 in the published datasets)


@dataclass
class MrclamRun:
    """One robot's files, parsed: stamps in ns, odometry ``(v, w)``, sightings ``(barcode, range, bearing)``, the
    barcode table, the surveyed landmarks ``subject -> (x, y, sx, sy)``, the ground truth if present and
    the malformed rows dropped per file."""

    odometry_ns: np.ndarray
    odometry: np.ndarray
    sightings_ns: np.ndarray
    sightings: list[tuple[int, float, float]]
    subject_of_barcode: dict[int, int]
    landmarks: dict[int, tuple[float, float, float, float]]
    groundtruth_ns: np.ndarray | None = None
    groundtruth: np.ndarray | None = None
    malformed: dict[str, int] = field(default_factory=dict)


def _rows(path: Path, columns: int, what: str, malformed: dict[str, int], integer: tuple[int, ...] = ()
          ) -> tuple[np.ndarray, np.ndarray]:
    """The data rows of a dataset file (``#`` comments skipped): column 0 as times (ns; as an integer
    when 0 is in ``integer``) and the other columns as floats. A row with the wrong number of
    columns, a non-number, a non-integer in an ``integer`` column or a non-finite value is counted
    in ``malformed[file name]`` and dropped; a missing file is a UserError, one without a valid row a DataError."""
    if not path.is_file():
        raise UserError(f"no such file {path} ({what})")
    stamps, values = [], []
    bad = 0
    for line in open_text(path):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        try:
            if len(tokens) != columns or any(not tokens[k].lstrip("+-").isdigit() for k in integer):
                raise ValueError
            row = [float(t) for t in tokens[1:]]
            if not all(math.isfinite(v) for v in row):
                raise ValueError
            stamps.append(int(tokens[0]) if 0 in integer else seconds_ns(tokens[0]))
        except ValueError:
            bad += 1
            continue
        values.append(row)
    if bad:
        malformed[path.name] = malformed.get(path.name, 0) + bad
    if not values:
        raise DataError(f"{path}: no valid rows ({what})")
    return np.array(stamps, np.int64), np.array(values, np.float64).reshape(len(values), columns - 1)


def read_mrclam(folder: str | os.PathLike[str], robot: int) -> MrclamRun:
    """Read robot ``robot``'s files from a MRCLAM dataset folder; a missing file is a UserError,
    malformed rows are dropped and counted (``MrclamRun.malformed``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder} is not a folder (expected a MRCLAM dataset folder)")
    if not 1 <= robot <= 5:
        raise UsageError(f"MRCLAM has robots 1 to 5, not {robot}")
    malformed: dict[str, int] = {}
    odometry_ns, odometry = _rows(folder / f"Robot{robot}_Odometry.dat", 3, "odometry: time v w", malformed)
    measurement_file = f"Robot{robot}_Measurement.dat"
    sightings_ns, sightings = _rows(folder / measurement_file, 4, "measurements: time barcode range bearing",
                                    malformed, integer=(1,))
    subjects, barcodes = _rows(folder / "Barcodes.dat", 2, "barcodes: subject barcode", malformed, integer=(0, 1))
    landmark_ids, landmarks = _rows(folder / "Landmark_Groundtruth.dat", 5, "landmarks: subject x y sx sy",
                                    malformed, integer=(0,))
    order = np.argsort(odometry_ns, kind="stable")  # rows out of time order are put in order
    valid = sightings[:, 1] >= 0
    if not valid.all():
        malformed[measurement_file] = malformed.get(measurement_file, 0) + int((~valid).sum())
    run = MrclamRun(odometry_ns[order], odometry[order], sightings_ns[valid],
                    [(int(b), float(r), float(a)) for b, r, a in sightings[valid]],
                    {int(b): int(s) for s, b in zip(subjects, barcodes[:, 0], strict=True)},
                    {int(s): (float(x), float(y), float(sx), float(sy))
                     for s, (x, y, sx, sy) in zip(landmark_ids, landmarks, strict=True)},
                    malformed=malformed)
    truth_path = folder / f"Robot{robot}_Groundtruth.dat"
    if truth_path.is_file():
        run.groundtruth_ns, run.groundtruth = _rows(truth_path, 4, "ground truth: time x y theta", malformed)
    return run


def integrate(stamps_ns: np.ndarray, speeds: np.ndarray) -> np.ndarray:
    """Poses (N, 3) at ``stamps_ns`` from ``(v, w)`` rows each holding until the next stamp, exactly
    along arcs, starting at the origin."""
    poses = np.zeros((len(stamps_ns), 3))
    dt = np.diff(stamps_ns) * 1e-9
    x = y = theta = 0.0
    for k in range(len(dt)):
        v, w = speeds[k]
        d, turn = v * dt[k], w * dt[k]
        if abs(turn) > 1e-12:
            radius = d / turn
            x += radius * (math.sin(theta + turn) - math.sin(theta))
            y -= radius * (math.cos(theta + turn) - math.cos(theta))
        else:
            x += d * math.cos(theta)
            y += d * math.sin(theta)
        theta = math.remainder(theta + turn, 2.0 * math.pi)
        poses[k + 1] = (x, y, theta)
    return poses


def sighting_covariance(range_m: float) -> np.ndarray:
    """The sensor model's 2x2 covariance of (range, bearing) for a sighting at ``range_m``."""
    return np.diag([(RANGE_SIGMA_M + RANGE_SIGMA_FRACTION * range_m) ** 2, BEARING_SIGMA_RAD ** 2])


def landmark_lists(run: MrclamRun) -> tuple[list[m.LandmarkList], dict[str, int]]:
    """The sightings grouped by instant as LandmarkLists, and the counts of those dropped (sightings
    of robots, unknown barcodes)."""
    groups: dict[int, list[m.LandmarkObservation]] = {}
    dropped = {"robot_sightings": 0, "unknown_barcodes": 0}
    for stamp, (barcode, range_m, bearing) in zip(run.sightings_ns, run.sightings, strict=True):
        subject = run.subject_of_barcode.get(barcode)
        if subject is None:
            dropped["unknown_barcodes"] += 1
        elif subject in ROBOT_SUBJECTS:
            dropped["robot_sightings"] += 1
        else:
            groups.setdefault(int(stamp), []).append(
                m.LandmarkObservation(str(subject), range_m, bearing, sighting_covariance(range_m)))
    return [m.LandmarkList(t, "base_link", tuple(obs)) for t, obs in sorted(groups.items())], dropped


def messages(run: MrclamRun, sightings: list[m.LandmarkList]) -> Iterator[Item]:
    """``/odom`` and ``/landmarks`` in time order (log time = stamp; odometry first at equal times)."""
    poses = integrate(run.odometry_ns, run.odometry)
    odometry = [
        (int(t), 0, m.Odometry(int(t), "odom", "base_link", pose[0], pose[1], pose[2], vx=float(v), wz=float(w)))
        for t, pose, (v, w) in zip(run.odometry_ns, poses, run.odometry, strict=True)
    ]
    for t, kind, msg in sorted(odometry + [(s.stamp_ns, 1, s) for s in sightings], key=lambda item: item[:2]):
        yield (ODOM_TOPIC if kind == 0 else LANDMARK_TOPIC), msg, t


def import_mrclam(folder: str | os.PathLike[str], robot: int, out: str | os.PathLike[str]
                  ) -> tuple[dict[str, int], MrclamRun, dict[str, int]]:
    """Convert one robot's run to MCAP; returns messages written per topic, the parsed run (for
    ``--reference``: its ground truth and the survey) and the sightings dropped, by reason."""
    run = read_mrclam(folder, robot)
    sightings, dropped = landmark_lists(run)
    metadata: dict[str, object] = {
        "command": "import mrclam",
        "source": os.fspath(folder),
        "robot_number": str(robot),
        "dropped_sightings": dropped,
        "malformed_rows": run.malformed,
        "landmark_sensor": {
            "range_sigma_m": RANGE_SIGMA_M,
            "range_sigma_fraction": RANGE_SIGMA_FRACTION,
            "bearing_sigma_rad": BEARING_SIGMA_RAD,
        },
    }
    counts = write_log(messages(run, sightings), out, metadata=metadata)
    return counts, run, dropped
