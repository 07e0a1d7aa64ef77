"""CARMEN logs (``.clf``, ``.log``, GMapping ``.gfs.log``) -> LaserScan / Odometry messages.

Reads ODOM, FLASER, RLASER and ROBOTLASER1 lines (format: CARMEN logger documentation, see
``../shared/notes/slam-eval.md``); other message types and ``#`` comments are skipped, malformed
lines counted and dropped. Conventions:

- Times: every line ends ``ipc_timestamp hostname logger_timestamp`` (s); the message stamp is
  the ipc time, the MCAP log time the logger time, made non-decreasing so scans keep their file
  order (CARMEN logs step back in time now and then).
- FLASER / RLASER carry no angles: 180 deg from -90 deg, with GMapping's step for its beam
  counts (180 or 181 beams -> 1 deg, 360 or 361 -> 0.5 deg, ...; otherwise 180/n deg).
- "No return" is written as the maximum range: readings at or above ``max_range_m`` become +inf
  (REP 117). For FLASER the value is inferred when not given: the largest reading in the file,
  if it occurs more than once.
- ROBOTLASER1 gives the laser's and the robot's pose: their difference is the laser mount,
  published once on ``/tf_static`` (base_link -> laser). Older ROBOTLASER1 lines without
  remissions and turn axis are recognised by their token count.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import DataError, UsageError
from trundle.logs.importers import Item, open_text, write_log
from trundle.logs.topics import ODOM_TOPIC, REAR_SCAN_TOPIC, SCAN_TOPIC, TF_STATIC_TOPIC

GMAPPING_STEPS = {180: 180, 181: 180, 360: 360, 361: 360, 540: 540, 541: 540, 720: 720, 721: 720}


@dataclass(frozen=True)
class CarmenOdom:
    """One ODOM line: pose (m, rad) and velocities tv (m/s), rv (rad/s)."""

    stamp_s: float
    logger_s: float
    x: float
    y: float
    theta: float
    tv: float
    rv: float


@dataclass(frozen=True)
class CarmenLaser:
    """One laser line: ranges (m) with their angles, the robot pose, odometry pose and laser mount."""

    kind: str
    stamp_s: float
    logger_s: float
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    max_range: float | None
    pose: tuple[float, float, float]
    odom_pose: tuple[float, float, float]
    laser_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class CarmenLog:
    """A parsed CARMEN log: ODOM and laser records in file order, and what was skipped."""

    odometry: list[CarmenOdom] = field(default_factory=list)
    lasers: list[CarmenLaser] = field(default_factory=list)
    order: list[tuple[str, int]] = field(default_factory=list)  # ("odom" | "laser", index) in file order
    skipped: dict[str, int] = field(default_factory=dict)
    malformed: int = 0


def flaser_step(beams: int) -> float:
    """Angular step (rad) of a FLASER/RLASER line with ``beams`` readings over 180 deg."""
    return math.pi / GMAPPING_STEPS.get(beams, beams)


def parse_line(line: str) -> CarmenOdom | CarmenLaser | None:
    """One CARMEN line as a record; None for comments and message types we do not read.

    Raises ValueError for a line of a type we read whose fields are missing or not numbers.
    """
    try:
        return _parse_tokens(line.split())
    except IndexError:
        raise ValueError("line ends early") from None


def _parse_tokens(tokens: list[str]) -> CarmenOdom | CarmenLaser | None:
    if not tokens or tokens[0].startswith("#"):
        return None
    kind = tokens[0]
    if kind == "ODOM":
        if len(tokens) != 10:
            raise ValueError(f"ODOM needs 10 tokens, got {len(tokens)}")
        x, y, theta, tv, rv = (float(t) for t in tokens[1:6])
        return CarmenOdom(_finite(tokens[7]), _finite(tokens[9]), x, y, theta, tv, rv)
    if kind in ("FLASER", "RLASER"):
        n = int(tokens[1])
        if n < 1 or len(tokens) != n + 11:
            raise ValueError(f"{kind} with {n} beams needs {n + 11} tokens, got {len(tokens)}")
        ranges = np.array(tokens[2:2 + n], dtype=np.float64)
        values = [float(t) for t in tokens[2 + n:8 + n]]
        return CarmenLaser(kind, _finite(tokens[8 + n]), _finite(tokens[10 + n]), ranges, -math.pi / 2,
                           flaser_step(n), None, tuple(values[:3]), tuple(values[3:6]))  # type: ignore[arg-type]
    if kind == "ROBOTLASER1":
        return _robotlaser(tokens)
    return None


def _finite(token: str) -> float:
    value = float(token)
    if not math.isfinite(value):
        raise ValueError(f"non-finite time {token}")
    return value


def _robotlaser(tokens: list[str]) -> CarmenLaser:
    start, fov, step, max_range = (float(t) for t in tokens[2:6])
    n = int(tokens[8])
    if n < 1 or len(tokens) < n + 21:
        raise ValueError(f"ROBOTLASER1 with {n} beams is too short ({len(tokens)} tokens)")
    ranges = np.array(tokens[9:9 + n], dtype=np.float64)
    rest = tokens[9 + n:]
    if len(rest) == 13:  # old variant: no remissions, no turn axis
        tail = rest
    else:
        m_count = int(rest[0])
        tail = rest[1 + m_count:]
        if m_count < 0 or len(tail) != 14:
            raise ValueError(f"ROBOTLASER1 with {n} beams and {m_count} remissions has {len(tokens)} tokens")
    lx, ly, lt, rx, ry, rt = (float(t) for t in tail[:6])
    c, s = math.cos(rt), math.sin(rt)
    offset = (c * (lx - rx) + s * (ly - ry), -s * (lx - rx) + c * (ly - ry),
              math.remainder(lt - rt, 2 * math.pi))
    if step <= 0 and fov > 0:
        step = fov / max(n - 1, 1)
    return CarmenLaser("ROBOTLASER1", _finite(tail[-3]), _finite(tail[-1]), ranges, start, step, max_range,
                       (rx, ry, rt), (rx, ry, rt), offset)


def read_carmen(path: str | os.PathLike[str]) -> CarmenLog:
    """Parse a CARMEN log file (``.gz`` too); raises DataError when it holds no laser or odometry line."""
    log = CarmenLog()
    for line in open_text(path):
        try:
            record = parse_line(line)
        except ValueError:
            log.malformed += 1
            continue
        if record is None:
            kind = line.split()[0] if line.split() else ""
            if kind and not kind.startswith("#"):
                log.skipped[kind] = log.skipped.get(kind, 0) + 1
        elif isinstance(record, CarmenOdom):
            log.order.append(("odom", len(log.odometry)))
            log.odometry.append(record)
        else:
            log.order.append(("laser", len(log.lasers)))
            log.lasers.append(record)
    if not log.order:
        raise DataError(f"{path}: no ODOM, FLASER, RLASER or ROBOTLASER1 line (is it a CARMEN log?)")
    return log


def infer_no_return(log: CarmenLog) -> float | None:
    """The FLASER/RLASER "no return" value: the largest reading, if it occurs more than once."""
    ranges = [laser.ranges for laser in log.lasers if laser.max_range is None]
    if not ranges:
        return None
    values = np.concatenate(ranges)
    top = float(values.max())
    return top if int(np.count_nonzero(values == top)) > 1 else None


def scan_poses(log: CarmenLog) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns) and robot poses (N, 3) of the front-laser lines (in GMapping output: corrected poses)."""
    lasers = [laser for laser in log.lasers if laser.kind != "RLASER"]
    return (np.array([_ns(laser.stamp_s) for laser in lasers], np.int64),
            np.array([laser.pose for laser in lasers], np.float64).reshape(-1, 3))


def _ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


ODOMETRY_SOURCES = ("auto", "odom", "laser", "none")


def choose_odometry(log: CarmenLog, requested: str = "auto") -> tuple[str, str]:
    """The odometry source to import (``odom``, ``laser`` or ``none``) and a sentence saying what it is.

    ``auto`` takes the ODOM lines when there are any, else the odometry fields of the laser lines
    (many benchmark logs carry odometry only there: FLASER ``odom_x odom_y odom_theta``,
    ROBOTLASER1's robot pose), else none; laser fields that never change count as none.
    """
    if requested not in ODOMETRY_SOURCES:
        raise UsageError(f"unknown odometry source {requested!r} (choose {', '.join(ODOMETRY_SOURCES)})")
    front = [laser for laser in log.lasers if laser.kind != "RLASER"]
    moving = len({laser.odom_pose for laser in front}) > 1
    kinds = "/".join(sorted({laser.kind for laser in front})) or "laser"
    if requested == "auto":
        requested = "odom" if log.odometry else "laser" if moving else "none"
    if requested == "odom":
        return "odom", f"{len(log.odometry)} ODOM lines"
    if requested == "laser":
        return "laser", (f"no ODOM lines: the {kinds} lines' odometry fields ({len(front)} poses)" if not log.odometry
                         else f"the {kinds} lines' odometry fields ({len(front)} poses)")
    return "none", ("no odometry: no ODOM lines and the laser lines' odometry fields never change" if not moving
                    else "no odometry (as asked)")


def messages(log: CarmenLog, *, odometry: str = "odom", laser_odometry: np.ndarray | None = None,
             max_range_m: float | None = None) -> Iterator[Item]:
    """The log as ``(topic, message, log_time_ns)``: /scan, /scan_rear, /odom, /tf_static.

    ``odometry``: ``"odom"`` publishes the ODOM lines; ``"laser"`` one odometry per front-laser
    line from its odometry fields, or from ``laser_odometry`` (N, 3) when given (e.g. a drifting
    odometry made from reference poses); ``"none"`` publishes no odometry.
    """
    if odometry not in ("odom", "laser", "none"):
        raise UsageError(f"unknown odometry source {odometry!r} (choose odom, laser or none)")
    no_return = max_range_m if max_range_m is not None else infer_no_return(log)
    front = [i for i, laser in enumerate(log.lasers) if laser.kind != "RLASER"]
    if laser_odometry is not None:
        laser_odometry = np.asarray(laser_odometry, dtype=np.float64).reshape(-1, 3)
        if len(laser_odometry) != len(front):
            raise DataError(f"{len(laser_odometry)} odometry poses for {len(front)} front-laser scans")
    front_index = {i: k for k, i in enumerate(front)}
    last_log_ns = -(1 << 62)
    mounted: set[str] = set()
    for what, index in log.order:
        if what == "odom":
            record = log.odometry[index]
            log_ns = last_log_ns = max(last_log_ns, _ns(record.logger_s))
            if odometry == "odom":
                yield ODOM_TOPIC, m.Odometry(_ns(record.stamp_s), "odom", "base_link", record.x, record.y, record.theta,
                                          vx=record.tv, wz=record.rv), log_ns
            continue
        laser = log.lasers[index]
        log_ns = last_log_ns = max(last_log_ns, _ns(laser.logger_s))
        rear = laser.kind == "RLASER"
        frame = "laser_rear" if rear else "laser"
        if frame not in mounted:
            mounted.add(frame)
            offset = (0.0, 0.0, math.pi) if rear and laser.laser_offset == (0.0, 0.0, 0.0) else laser.laser_offset
            yield TF_STATIC_TOPIC, m.TFMessage((m.TransformStamped.planar(_ns(laser.stamp_s), "base_link", frame,
                                                                       *offset),)), log_ns
        if odometry == "laser" and not rear:
            x, y, theta = laser.odom_pose if laser_odometry is None else laser_odometry[front_index[index]]
            odom = m.Odometry(_ns(laser.stamp_s), "odom", "base_link", float(x), float(y), float(theta))
            yield ODOM_TOPIC, odom, log_ns
        yield (REAR_SCAN_TOPIC if rear else SCAN_TOPIC), to_scan(laser, frame, no_return), log_ns


def to_scan(laser: CarmenLaser, frame_id: str, no_return_m: float | None) -> m.LaserScan:
    """A CARMEN laser record as a LaserScan; readings >= the no-return value become +inf."""
    limit = laser.max_range if laser.max_range is not None else no_return_m
    ranges = laser.ranges.copy()
    ranges[~np.isfinite(ranges) | (ranges < 0)] = np.nan
    if limit is not None:
        ranges[ranges >= limit] = np.inf
    finite = ranges[np.isfinite(ranges)]
    range_max = limit if limit is not None else (float(finite.max()) if finite.size else 0.0)
    n = ranges.size
    return m.LaserScan(_ns(laser.stamp_s), frame_id, laser.angle_min, laser.angle_min + laser.angle_increment * (n - 1),
                       laser.angle_increment, 0.0, 0.0, 0.0, range_max, ranges)


def import_carmen(path: str | os.PathLike[str], out: str | os.PathLike[str], *, odometry: str = "auto",
                  laser_odometry: np.ndarray | None = None, max_range_m: float | None = None,
                  log: CarmenLog | None = None, description: str = "") -> dict[str, int]:
    """Convert a CARMEN log to MCAP; returns messages written per topic.

    ``odometry`` is a source of :func:`choose_odometry` (default ``auto``); with ``laser_odometry``
    (poses per front-laser line) give ``odometry="laser"`` and the ``description`` of those poses.
    The source and its description are stored in the log's metadata (``odometry``,
    ``odometry_description``), so ``trundle slam`` can say what it ran on.
    """
    log = read_carmen(path) if log is None else log
    if laser_odometry is None or odometry != "laser":
        odometry, description = choose_odometry(log, odometry)
    metadata: dict[str, object] = {
        "command": "import carmen",
        "source": os.fspath(path),
        "odometry": odometry,
        "odometry_description": description,
        "malformed_lines": str(log.malformed),
        "skipped_lines": log.skipped,
    }
    return write_log(messages(log, odometry=odometry, laser_odometry=laser_odometry, max_range_m=max_range_m),
                     out, metadata=metadata)
