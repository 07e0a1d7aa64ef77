"""A sensor's characteristics from its messages: the figures (SI units) and the data of their plots.

Laser, wheel encoders and camera each have one function returning ``(figures, plots)``; the
figures come from :mod:`trundle.fusion.evaluation.sensor_characteristics`.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from trundle.fusion.evaluation import sensor_characteristics as sc
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.reader import LogReader
from trundle.logs.topics import ODOM_TOPIC

STILL_SPEED = 1e-3  # m/s or rad/s below which the robot counts as standing still


def motion_speeds(reader: LogReader) -> tuple[np.ndarray, np.ndarray] | None:
    """(stamps ns, speeds m/s and rad/s) from /odom twist, else wheel speeds (rad/s) from any JointState topic;
    None without either."""
    odom = [(o.stamp_ns, abs(o.vx), abs(o.wz)) for o in (x.msg for x in reader.messages([ODOM_TOPIC]))
            if isinstance(o, m.Odometry)]
    if odom:
        a = np.array(odom, np.float64)
        return a[:, 0].astype(np.int64), a[:, 1:]
    wheels = [x.msg for x in reader.messages() if isinstance(x.msg, m.JointState)]
    if len(wheels) < 2:
        return None
    t = np.array([w.stamp_ns for w in wheels], np.int64)
    if all(w.velocity.size for w in wheels):
        return t, np.array([w.velocity for w in wheels])
    pos = np.array([w.position for w in wheels])
    dt = np.maximum(np.diff(t) * 1e-9, 1e-9)[:, None]
    return t[1:], np.abs(np.diff(pos, axis=0)) / dt


def characterize_laser(scans: list[m.LaserScan], reader: LogReader, reference: tuple[np.ndarray, np.ndarray] | None,
                       stated_min: float | None = None, stated_max: float | None = None, bits: int | None = None,
                       min_still_s: float = 1.0, beam: int | str = "all") -> tuple[dict[str, Any], dict[str, Any]]:
    """A laser's figures and plot data from its ``scans``.

    Range against the stated limits (m; default: the scans' own), timing, no-return and error
    fractions; per-beam noise over the stretches of at least ``min_still_s`` (s) the robot stood
    still (from the log's odometry, read through ``reader``; without odometry the whole log, or
    none when there is a ``reference``); with a ``reference`` (t_ns, true range m), ``beam`` (an index or ``"all"``)
    against it: sensitivity, linearity, hysteresis, accuracy. ``bits``: A/D bits for the
    range / 2^bits resolution.
    """
    stamps = np.array([s.stamp_ns for s in scans], np.int64)
    ranges = np.array([s.ranges for s in scans], np.float64)
    valid = np.isfinite(ranges)
    figures: dict[str, Any] = {"sensor": "laser", "class": sc.SENSOR_CLASSES["laser"].as_dict(),
                               "scans": len(scans), "beams": int(ranges.shape[1])}
    figures["range"] = sc.measurement_range(ranges[valid], stated_min if stated_min is not None else scans[0].range_min,
                                            stated_max if stated_max is not None else scans[0].range_max, bits)
    figures["bandwidth"] = sc.timing(stamps)
    figures["no_return_fraction"] = float(np.isposinf(ranges).mean())
    figures["error_reading_fraction"] = float((np.isnan(ranges) | np.isneginf(ranges)).mean())
    plots: dict[str, Any] = {}
    motion = motion_speeds(reader)
    if motion is not None:
        intervals = sc.static_intervals(*motion, threshold=STILL_SPEED, min_duration_s=min_still_s)
        figures["still_from"] = "odometry"
    else:
        intervals = [(int(stamps[0]), int(stamps[-1]))] if reference is None else []
        figures["still_from"] = "whole log (no odometry in the log)"
    blocks = [ranges[(stamps >= a) & (stamps <= b)] for a, b in intervals]
    blocks = [blk for blk in blocks if blk.shape[0] >= 2]
    if blocks:
        per_beam = [sc.beam_statistics(blk) for blk in blocks]
        with warnings.catch_warnings():  # beams that never returned have no spread: NaN, said so
            warnings.simplefilter("ignore", RuntimeWarning)
            std = np.nanmean(np.array([p["std"] for p in per_beam]), axis=0)
        figures["static"] = {
            "intervals_s": [((a - stamps[0]) * 1e-9, (b - stamps[0]) * 1e-9) for a, b in intervals],
            "scans": int(sum(blk.shape[0] for blk in blocks)),
            "beams_with_noise": int(np.isfinite(std).sum()),
            "beam_noise_std_median": float(np.nanmedian(std)),
            "beam_noise_std_p95": float(np.nanpercentile(std, 95)),
            "precision": sc.precision([blk[:, j] for blk in blocks for j in range(blk.shape[1])]),
        }
        plots["beam_noise"] = (scans[0].angles(), std)
    if reference is not None:
        truth, hold = reference_at(stamps, *reference)
        seconds = (stamps - stamps[0]) * 1e-9
        if beam == "all":
            beams = ranges.shape[1]
            measured, true = ranges.reshape(-1), np.repeat(truth, beams)
            times, holds = np.repeat(seconds, beams), np.repeat(hold, beams)
        else:
            index = int(beam)
            if not 0 <= index < ranges.shape[1]:
                raise UserError(f"--beam {index} is outside 0..{ranges.shape[1] - 1}")
            measured, true, times, holds = ranges[:, index], truth, seconds, hold
        figures.update(reference_figures(measured, true, times, holds))
        plots["sensitivity"] = (true, measured)
    return figures, plots


def reference_at(stamps: np.ndarray, ref_t: np.ndarray, ref_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True value for each stamp: the nearest reference row within half the reference's median
    spacing (NaN further away), and the number of the hold (run of equal values) it belongs to.

    Reference rows are the true values at the sensor's measurement times (e.g. one per scan
    from the simulator or an emulator), so matching is by nearest time, not interpolation.
    """
    spacing = np.median(np.diff(ref_t)) if ref_t.size > 1 else 0
    right = np.clip(np.searchsorted(ref_t, stamps), 1, max(ref_t.size - 1, 1))
    left = right - 1
    nearest = np.where(np.abs(stamps - ref_t[left]) <= np.abs(ref_t[right] - stamps), left, right)
    close = np.abs(ref_t[nearest] - stamps) <= spacing / 2
    run = np.concatenate([[0], np.cumsum(np.diff(ref_v) != 0)])
    return np.where(close, ref_v[nearest], np.nan), np.where(close, run[nearest], -1)


def reference_figures(measured: np.ndarray, true: np.ndarray, times: np.ndarray, holds: np.ndarray) -> dict[str, Any]:
    """Sensitivity/linearity, hysteresis, accuracy and errors against a reference.

    A stepped reference (values held over several samples) is analysed by holds, which
    separates noise from non-linearity and hysteresis; a continuous sweep sample by sample.
    """
    valid = holds >= 0
    if valid.any() and np.unique(holds[valid]).size * 2 <= valid.sum():
        return sc.sweep_figures(measured, true, holds, times)
    out: dict[str, Any] = {"sensitivity": sc.linearity(measured, true), "errors": sc.errors(measured, true, times)}
    try:
        out["hysteresis"] = sc.hysteresis(measured, true)
    except ValueError as error:
        out["hysteresis"] = {"note": str(error)}
    keep = np.isfinite(measured) & np.isfinite(true)
    levels = np.unique(true[keep])
    if levels.size < keep.sum():
        out["precision"] = sc.precision([measured[keep][true[keep] == lv] for lv in levels])
    return out


def characterize_encoders(states: list[m.JointState]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Wheel encoders' figures from their joint ``states``: timing, and per joint the quantisation
    (rad), counts per revolution and range (rad); no plots."""
    stamps = np.array([s.stamp_ns for s in states], np.int64)
    pos = np.array([s.position for s in states])
    figures: dict[str, Any] = {"sensor": "wheel_encoder", "class": sc.SENSOR_CLASSES["wheel_encoder"].as_dict(),
                               "messages": len(states), "bandwidth": sc.timing(stamps), "joints": {}}
    for j, name in enumerate(states[0].name):
        step = sc.resolution(pos[:, j])
        figures["joints"][name] = {
            "quantisation_rad": step,
            "counts_per_revolution": None if not step else float(2 * np.pi / step),
            "range": sc.measurement_range(pos[:, j]),
        }
    return figures, {}


def characterize_camera(stamps: np.ndarray) -> tuple[dict[str, Any], dict[str, Any]]:
    """A camera's figures from its frames' ``stamps`` (ns): timing and dropped frames; no plots."""
    timing = sc.timing(stamps)
    return {"sensor": "camera", "class": sc.SENSOR_CLASSES["camera"].as_dict(), "frames": int(stamps.size),
            "bandwidth": timing, "dropped_frames": timing["dropped"]}, {}
