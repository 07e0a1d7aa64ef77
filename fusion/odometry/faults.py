"""Realistic wheel-odometry faults, injected into recorded odometry so every fault can be tested on real scans.

Four kinds, each over a time window (seconds after the first odometry reading):

- ``heading_glitch``: the odometry heading turns by ``value`` radians within the window while the
  robot does not (a gyro or encoder glitch; the MIT CSAIL log has 17-24 degrees in about 0.6 s);
  everything after it is rotated with it, as integrated odometry would be.
- ``slip``: the wheels report ``1 + value`` times the distance the robot covered in the window
  (spinning on a smooth floor; a negative value: dragged wheels).
- ``scale``: the same over the window, as a wrong wheel radius gives (the window is usually the
  whole log).
- ``dropout``: no odometry at all in the window.

Faults act on increments: each odometry increment (robot frame) is changed by the share of the
window it overlaps, and the increments are chained again from the first pose, so a fault leaves
the odometry continuous and wrong from then on, as real faults do. The same faults apply to
odometry poses (``nav_msgs/Odometry``) and to wheel angles (``JointState``, through the
differential-drive model).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from trundle.fusion.geometry import compose, relative

KINDS = ("heading_glitch", "slip", "scale", "dropout")


@dataclass(frozen=True)
class OdometryFault:
    """One fault: ``kind``, window ``start_s`` .. ``start_s + duration_s`` (s after the first odometry
    reading) and ``value`` (heading_glitch: radians; slip and scale: fractional error; dropout: unused)."""

    kind: str
    start_s: float
    duration_s: float
    value: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown odometry fault {self.kind!r} (choose {', '.join(KINDS)})")
        if not (math.isfinite(self.start_s) and math.isfinite(self.duration_s) and math.isfinite(self.value)):
            raise ValueError("fault times and value must be finite")
        if self.duration_s < 0:
            raise ValueError(f"fault duration must not be negative, got {self.duration_s}")
        if self.kind in ("slip", "scale") and self.value <= -1.0:
            raise ValueError(f"a {self.kind} of {self.value} would reverse the wheels (must be > -1)")

    def as_dict(self) -> dict[str, float | str]:
        return asdict(self)


def overlap(t0_s: np.ndarray, t1_s: np.ndarray, fault: OdometryFault) -> np.ndarray:
    """Share (0..1) of each fault window that the intervals ``[t0, t1]`` cover (a zero-length window:
    1 for the interval holding its instant)."""
    start, end = fault.start_s, fault.start_s + fault.duration_s
    if fault.duration_s == 0:
        return ((t0_s < start) & (start <= t1_s)).astype(np.float64)
    return np.clip(np.minimum(t1_s, end) - np.maximum(t0_s, start), 0.0, None) / fault.duration_s


def interval_share(t0_s: np.ndarray, t1_s: np.ndarray, fault: OdometryFault) -> np.ndarray:
    """Share (0..1) of each interval ``[t0, t1]`` that lies inside the fault window."""
    start, end = fault.start_s, fault.start_s + fault.duration_s
    length = np.maximum(t1_s - t0_s, 1e-12)
    return np.clip(np.minimum(t1_s, end) - np.maximum(t0_s, start), 0.0, None) / length


def dropped(times_s: np.ndarray, faults: list[OdometryFault]) -> np.ndarray:
    """Mask of the readings at ``times_s`` that a dropout removes."""
    mask = np.zeros(len(times_s), bool)
    for fault in faults:
        if fault.kind == "dropout":
            mask |= (times_s >= fault.start_s) & (times_s <= fault.start_s + fault.duration_s)
    return mask


def _translation_factor(t0: np.ndarray, t1: np.ndarray, faults: list[OdometryFault]) -> np.ndarray:
    factor = np.ones(len(t0))
    for fault in faults:
        if fault.kind in ("slip", "scale"):
            factor *= 1.0 + fault.value * interval_share(t0, t1, fault)
    return factor


def _extra_turn(t0: np.ndarray, t1: np.ndarray, faults: list[OdometryFault]) -> np.ndarray:
    turn = np.zeros(len(t0))
    for fault in faults:
        if fault.kind == "heading_glitch":
            turn += fault.value * overlap(t0, t1, fault)
    return turn


def faulty_poses(times_s: np.ndarray, poses: np.ndarray, faults: list[OdometryFault]) -> np.ndarray:
    """Odometry poses (N, 3) with ``faults`` applied to their increments (dropouts are left to the caller,
    see :func:`dropped`); the first pose is kept."""
    times_s = np.asarray(times_s, np.float64)
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    if len(poses) < 2:
        return poses.copy()
    steps = relative(poses[:-1], poses[1:])
    t0, t1 = times_s[:-1], times_s[1:]
    steps[:, :2] *= _translation_factor(t0, t1, faults)[:, None]
    steps[:, 2] += _extra_turn(t0, t1, faults)
    out = np.empty_like(poses)
    out[0] = poses[0]
    for k, step in enumerate(steps):
        out[k + 1] = compose(out[k], step)
    return out


def faulty_wheels(times_s: np.ndarray, left_rad: np.ndarray, right_rad: np.ndarray, faults: list[OdometryFault],
                  wheel_radius_m: float, track_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative wheel angles (rad) with ``faults`` applied to their increments.

    Slip and scale multiply both wheels' increments; a heading glitch of ``dtheta`` turns the
    wheels in opposite directions by ``dtheta * track / (2 * radius)`` each (no distance, only turn).
    """
    times_s = np.asarray(times_s, np.float64)
    left = np.asarray(left_rad, np.float64)
    right = np.asarray(right_rad, np.float64)
    if len(left) < 2:
        return left.copy(), right.copy()
    t0, t1 = times_s[:-1], times_s[1:]
    factor = _translation_factor(t0, t1, faults)
    turn = _extra_turn(t0, t1, faults) * track_m / (2.0 * wheel_radius_m)
    d_left = np.diff(left) * factor - turn
    d_right = np.diff(right) * factor + turn
    return (np.concatenate([[left[0]], left[0] + np.cumsum(d_left)]),
            np.concatenate([[right[0]], right[0] + np.cumsum(d_right)]))


def random_glitches(count: int, span_s: float, magnitude_rad: float, duration_s: float,
                    seed: int) -> list[OdometryFault]:
    """``count`` heading glitches of ``+-magnitude_rad`` (random sign) over ``duration_s`` each, at random
    times in the middle 80 % of ``span_s`` seconds, at least ``span_s / (2 count)`` apart and never
    overlapping."""
    if count <= 0:
        return []
    rng = np.random.default_rng(seed)
    gap = max(span_s / (2.0 * count), duration_s)
    low, high = 0.1 * span_s, 0.9 * span_s - duration_s
    if high - low < (count - 1) * gap:
        raise ValueError(f"{count} glitches of {duration_s} s do not fit {span_s:.1f} s of odometry")
    # sorted uniform draws in a span shortened by the gaps, then spread out again: gaps guaranteed
    starts = np.sort(rng.uniform(low, high - (count - 1) * gap, count)) + gap * np.arange(count)
    signs = rng.choice([-1.0, 1.0], count)
    return [
        OdometryFault("heading_glitch", float(t), duration_s, float(s * magnitude_rad))
        for t, s in zip(starts, signs, strict=True)
    ]
