"""`trundle characterize LOG --topic T`: a sensor's characteristics from a log, as a report.

The topic's type says what the sensor is (LaserScan: laser; JointState: wheel encoders;
CompressedImage/Image: camera). Writes report.md, report.json and PNG plots into -o DIR;
``--json`` prints the figures as one JSON object (SI units).
"""

from __future__ import annotations

import argparse
import csv
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from trundle.fusion import sensor_characteristics as sc
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.reader import LogReader

STILL_SPEED = 1e-3  # m/s or rad/s below which the robot counts as standing still


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("log")
    p.add_argument("--topic", required=True, help="sensor topic, e.g. /scan, /wheels, /camera/image/compressed")
    p.add_argument("--reference", type=Path, help="CSV of true values over time: columns t_ns (or t_s) and value")
    p.add_argument("--beam", default="all", help="laser beam index compared with --reference, or 'all' (default)")
    p.add_argument("--stated-min", type=float, help="device's stated lower limit (default: from the messages)")
    p.add_argument("--stated-max", type=float, help="device's stated upper limit (default: from the messages)")
    p.add_argument("--bits", type=int, help="A/D bits, for the range / 2^bits resolution")
    p.add_argument("--min-still", type=float, default=1.0, help="shortest standing-still stretch used, s")
    p.add_argument("-o", "--output", type=Path, help="report folder (report.md, report.json, plots)")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    p.set_defaults(func=run)


def read_reference(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns, value) from a CSV with a header naming t_ns or t_s, and value."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as error:
        raise UserError(f"cannot read reference {path}: {error.strerror}") from None
    if not rows or "value" not in rows[0] or not ({"t_ns", "t_s"} & set(rows[0])):
        raise UserError(f"reference {path} needs a header with t_ns (or t_s) and value columns")
    try:
        t = np.array([int(r["t_ns"]) if "t_ns" in r else round(float(r["t_s"]) * 1e9) for r in rows], np.int64)
        v = np.array([float(r["value"]) for r in rows])
    except ValueError as error:
        raise UserError(f"reference {path}: {error}") from None
    order = np.argsort(t)
    return t[order], v[order]


def motion_speeds(reader: LogReader) -> tuple[np.ndarray, np.ndarray] | None:
    """(stamps, speeds) from /odom twist, else from wheel speeds in any JointState topic."""
    odom = [(x.msg.stamp_ns, abs(x.msg.vx), abs(x.msg.wz)) for x in reader.messages(["/odom"])]
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


def characterize_laser(scans: list[m.LaserScan], args: argparse.Namespace, reader: LogReader,
                       reference: tuple[np.ndarray, np.ndarray] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    stamps = np.array([s.stamp_ns for s in scans], np.int64)
    ranges = np.array([s.ranges for s in scans], np.float64)
    valid = np.isfinite(ranges)
    figures: dict[str, Any] = {"sensor": "laser", "class": sc.SENSOR_CLASSES["laser"].as_dict(),
                               "scans": len(scans), "beams": int(ranges.shape[1])}
    figures["range"] = sc.measurement_range(ranges[valid], args.stated_min if args.stated_min is not None else scans[0].range_min,
                                            args.stated_max if args.stated_max is not None else scans[0].range_max, args.bits)
    figures["bandwidth"] = sc.timing(stamps)
    figures["no_return_fraction"] = float(np.isposinf(ranges).mean())
    figures["error_reading_fraction"] = float((np.isnan(ranges) | np.isneginf(ranges)).mean())
    plots: dict[str, Any] = {}
    motion = motion_speeds(reader)
    if motion is not None:
        intervals = sc.static_intervals(*motion, threshold=STILL_SPEED, min_duration_s=args.min_still)
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
        if args.beam == "all":
            beams = ranges.shape[1]
            measured, true = ranges.reshape(-1), np.repeat(truth, beams)
            times, holds = np.repeat(seconds, beams), np.repeat(hold, beams)
        else:
            beam = int(args.beam)
            if not 0 <= beam < ranges.shape[1]:
                raise UserError(f"--beam {beam} is outside 0..{ranges.shape[1] - 1}")
            measured, true, times, holds = ranges[:, beam], truth, seconds, hold
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


def characterize_encoders(states: list[m.JointState], reader: LogReader) -> tuple[dict[str, Any], dict[str, Any]]:
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
    timing = sc.timing(stamps)
    return {"sensor": "camera", "class": sc.SENSOR_CLASSES["camera"].as_dict(), "frames": int(stamps.size),
            "bandwidth": timing, "dropped_frames": timing["dropped"]}, {}


def write_plots(folder: Path, plots: dict[str, Any]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    if "beam_noise" in plots:
        angles, std = plots["beam_noise"]
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.semilogy(np.degrees(angles), std * 1000, lw=0.8)
        ax.axhline(np.nanmedian(std) * 1000, color="k", ls="--", lw=0.8, label=f"median {np.nanmedian(std) * 1000:.1f} mm")
        ax.set(xlabel="beam angle (deg)", ylabel="noise std (mm, log)", title="Per-beam noise while standing still")
        ax.legend(loc="upper right")
        fig.tight_layout()
        fig.savefig(folder / "beam_noise.png", dpi=110)
        plt.close(fig)
        names.append("beam_noise.png")
    if "sensitivity" in plots:
        true, measured = plots["sensitivity"]
        keep = np.isfinite(true) & np.isfinite(measured)
        step = max(1, keep.sum() // 20000)
        fig, ax = plt.subplots(figsize=(5, 5))
        ax.plot(true[keep][::step], measured[keep][::step], ",", alpha=0.4)
        lim = [np.nanmin(true[keep]), np.nanmax(true[keep])]
        ax.plot(lim, lim, "k--", lw=0.8)
        ax.set(xlabel="true value (m)", ylabel="measured (m)", title="Sensitivity")
        fig.tight_layout()
        fig.savefig(folder / "sensitivity.png", dpi=110)
        plt.close(fig)
        names.append("sensitivity.png")
    return names


def markdown(figures: dict[str, Any], topic: str, plots: list[str]) -> str:
    lines = [f"# Sensor characteristics: `{topic}`", ""]
    cls = figures["class"]
    lines += [f"Class: **{cls['sense']}**, **{cls['energy']}**; application: {cls['application']}.", ""]

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        elif prefix != "class" and not prefix.startswith("class."):
            lines.append(f"| {prefix} | {value:.6g} |" if isinstance(value, float) else f"| {prefix} | {value} |")

    lines += ["| quantity | value (SI) |", "|---|---|"]
    walk("", {k: v for k, v in figures.items() if k != "class"})
    lines += [""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    return value


def run(args: argparse.Namespace) -> int:
    reader = LogReader(args.log)
    info = reader.info()
    if args.topic not in info.topics:
        raise UserError(f"topic {args.topic} is not in {args.log} (topics: {', '.join(sorted(info.topics))})")
    msgs = [x.msg for x in reader.messages([args.topic])]
    if len(msgs) < 3:
        raise UserError(f"topic {args.topic} has {len(msgs)} decodable messages; at least 3 are needed")
    reference = read_reference(args.reference) if args.reference else None
    first = msgs[0]
    if isinstance(first, m.LaserScan):
        figures, plots = characterize_laser(msgs, args, reader, reference)  # type: ignore[arg-type]
    elif isinstance(first, m.JointState):
        figures, plots = characterize_encoders(msgs, reader)  # type: ignore[arg-type]
    elif isinstance(first, (m.CompressedImage, m.Image)):
        figures, plots = characterize_camera(np.array([x.stamp_ns for x in msgs], np.int64))
    else:
        raise UserError(f"{args.topic} carries {info.topics[args.topic].ros_type}: not a laser, encoder or camera topic")
    figures = _jsonable(figures)
    if args.output:
        args.output.mkdir(parents=True, exist_ok=True)
        names = write_plots(args.output, plots)
        (args.output / "report.json").write_text(json.dumps(figures, indent=2))
        (args.output / "report.md").write_text(markdown(figures, args.topic, names))
    if args.json:
        print(json.dumps(figures))
    elif args.output:
        print(f"wrote {args.output / 'report.md'}, {args.output / 'report.json'}")
    else:
        print(markdown(figures, args.topic, []))
    return 0
