"""Planar rigid-body (SE(2)) algebra over poses ``(x, y, theta)`` and scan-to-points conversion.

Poses are arrays whose last axis is ``(x, y, theta)`` in metres and radians (REP 103), so every
function works on one pose of shape (3,) or on a batch (..., 3) alike.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from trundle.logs.messages import LaserScan


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped into [-pi, pi)."""
    if isinstance(angle, (float, int)):  # fast path: per-scan bookkeeping calls this with scalars
        return (float(angle) + math.pi) % (2.0 * math.pi) - math.pi
    wrapped = np.remainder(np.asarray(angle, dtype=np.float64) + np.pi, 2.0 * np.pi) - np.pi
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def _one_pose(a: object) -> bool:
    """Is ``a`` a single finite pose, a float array of shape (3,)? The per-scan bookkeeping's poses are (an
    infinite heading takes numpy's path: ``math.cos`` raises where ``np.cos`` gives NaN)."""
    return isinstance(a, np.ndarray) and a.shape == (3,) and a.dtype == np.float64 and not math.isinf(a[2])


def _wrap(angle: float) -> float:
    """:func:`wrap_angle` of a float (its scalar path, which the numpy expressions below took for one pose)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# One pose at a time (the per-scan bookkeeping: a few dozen calls a scan) the algebra runs on floats with
# ``math``, where numpy's ops on 3-element arrays cost a microsecond or two each: the same operations in
# the same order on the same float64 values, so the same results (tested against the array expressions).
def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a (+) b``: pose ``b`` given in the frame of ``a``, expressed in ``a``'s parent frame."""
    if _one_pose(a) and _one_pose(b):
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        c, s = math.cos(at), math.sin(at)
        return np.array([ax + c * bx - s * by, ay + s * bx + c * by, _wrap(at + bt)])
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1],
                     a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """``a^-1``: the parent frame's pose seen from ``a``."""
    if _one_pose(a):
        ax, ay, at = a.tolist()
        c, s = math.cos(at), math.sin(at)
        return np.array([-c * ax - s * ay, s * ax - c * ay, _wrap(-at)])
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1],
                     s * a[..., 0] - c * a[..., 1],
                     wrap_angle(-a[..., 2])], axis=-1)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 (+) b``: pose ``b`` expressed in the frame of pose ``a`` (both in one parent frame)."""
    if _one_pose(a) and _one_pose(b):
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        c, s = math.cos(at), math.sin(at)
        dx, dy = bx - ax, by - ay
        return np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(bt - at)])
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def rotation(theta: float) -> np.ndarray:
    """The 2x2 rotation matrix of ``theta`` radians."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 2) given in the frame of ``pose`` expressed in the pose's parent frame.

    Written out per coordinate: numpy's matmul of an (N, 2) array by a 2 x 2 matrix took 60 ms for
    the half million points the map check places per submap, this takes 5."""
    pose = np.asarray(pose, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    out = np.empty(points.shape)
    out[..., 0] = c * points[..., 0] - s * points[..., 1] + pose[0]
    out[..., 1] = s * points[..., 0] + c * points[..., 1] + pose[1]
    return out


def rotate_covariance(covariance: np.ndarray, theta: float) -> np.ndarray:
    """A (x, y, theta) covariance expressed in a frame rotated by ``theta``."""
    r = np.eye(3)
    r[:2, :2] = rotation(theta)
    return r @ np.asarray(covariance, dtype=np.float64) @ r.T


@dataclass(frozen=True)
class ScanReturns:
    """A scan's valid returns as points (N, 2, metres) in the frame of the sensor pose they were placed with,
    and the time (s) after the scan's stamp at which each was measured (None: the scan gives no
    ``time_increment``, or the times were not asked for)."""

    points: np.ndarray
    times: np.ndarray | None


def scan_returns(scan: LaserScan, sensor_pose: np.ndarray | None = None, range_min: float | None = None,
                 range_max: float | None = None, times: bool = True) -> ScanReturns:
    """The valid returns of ``scan`` (see :func:`scan_to_points`) as points in the ``sensor_pose`` frame, before
    any de-skew: one conversion that :func:`deskewed` then moves by as many velocities as wanted.

    The beams are picked and placed by two compiled passes around numpy's cosine and sine of their angles
    (numpy's vector code, whose last bits the C library's do not always match): the same values as the
    two dozen numpy expressions they replace, for a tenth of the calls."""
    low = scan.range_min if range_min is None else range_min
    high = scan.range_max if range_max is None else range_max
    index, r, angles = _compiled(_kept_beams)(scan.ranges, float(low), float(high), scan.angle_min,
                                              scan.angle_increment)
    if sensor_pose is None:
        c, s, x, y = 1.0, 0.0, 0.0, 0.0
        placed = False
    else:
        pose = np.asarray(sensor_pose, dtype=np.float64)
        c, s, x, y = float(np.cos(pose[2])), float(np.sin(pose[2])), float(pose[0]), float(pose[1])
        placed = True
    points = _compiled(_placed_beams)(r, np.cos(angles), np.sin(angles), placed, c, s, x, y)
    dt = index * float(scan.time_increment) if times and scan.time_increment > 0 else None
    return ScanReturns(points, dt)


def _kept_beams(ranges: np.ndarray, low: float, high: float, angle_min: float, increment: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The beams of ``ranges`` (float32) whose range is finite and in [``low``, ``high``]: their indices,
    ranges (float64) and angles (``angle_min + increment * index``, as :meth:`LaserScan.angles`)."""
    n = ranges.shape[0]
    index = np.empty(n, np.int64)
    kept = np.empty(n)
    angles = np.empty(n)
    count = 0
    for i in range(n):
        value = np.float64(ranges[i])
        if math.isfinite(value) and value >= low and value <= high:
            index[count] = i
            kept[count] = value
            angles[count] = angle_min + increment * np.float64(i)
            count += 1
    return index[:count].copy(), kept[:count].copy(), angles[:count].copy()


def _placed_beams(r: np.ndarray, cos: np.ndarray, sin: np.ndarray, placed: bool, c: float, s: float, x: float,
                  y: float) -> np.ndarray:
    """Points (N, 2) at ranges ``r`` along directions (``cos``, ``sin``), then (``placed``) rotated by the angle
    of cosine ``c`` and sine ``s`` and moved by (``x``, ``y``): :func:`transform_points`' arithmetic."""
    out = np.empty((r.shape[0], 2))
    for i in range(r.shape[0]):
        px, py = r[i] * cos[i], r[i] * sin[i]
        if placed:
            out[i, 0] = c * px - s * py + x
            out[i, 1] = s * px + c * py + y
        else:
            out[i, 0], out[i, 1] = px, py
    return out


def deskewed(returns: ScanReturns, velocity: np.ndarray | None) -> np.ndarray:
    """``returns``' points with the motion during the sweep undone (see :func:`scan_to_points`); as they are
    without a ``velocity`` or without beam times."""
    points = returns.points
    if velocity is not None and returns.times is not None:
        dt = returns.times
        vx, vy, wz = (float(v) for v in velocity)
        turn = wz * dt
        points = _compiled(_moved_beams)(points, np.cos(turn), np.sin(turn), dt, vx, vy)
    return points


def _moved_beams(points: np.ndarray, cos: np.ndarray, sin: np.ndarray, dt: np.ndarray, vx: float, vy: float
                 ) -> np.ndarray:
    """Each point (N, 2) turned by its angle of cosine ``cos`` and sine ``sin`` and moved by ``(vx, vy) dt``."""
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        out[i, 0] = cos[i] * points[i, 0] - sin[i] * points[i, 1] + vx * dt[i]
        out[i, 1] = sin[i] * points[i, 0] + cos[i] * points[i, 1] + vy * dt[i]
    return out


def scan_to_points(scan: LaserScan, sensor_pose: np.ndarray | None = None, range_min: float | None = None,
                   range_max: float | None = None, velocity: np.ndarray | None = None) -> np.ndarray:
    """Valid returns of ``scan`` as points (N, 2) in metres, in the frame of ``sensor_pose``.

    A beam is kept when its range is finite and inside ``[range_min, range_max]`` (defaults: the
    scan's own limits), so REP 117's +inf / -inf / NaN readings drop out. ``sensor_pose`` is the
    laser's pose in the robot frame (default: identity, points stay in the laser frame).
    ``velocity`` (vx m/s, vy m/s, wz rad/s, robot frame) undoes the motion during the sweep: beam
    i, measured ``i * time_increment`` after the stamp, is moved into the robot frame at the stamp
    (constant velocity over the sweep).
    """
    return deskewed(scan_returns(scan, sensor_pose, range_min, range_max, times=velocity is not None), velocity)


def no_return_directions(scan: LaserScan, sensor_pose: np.ndarray | None = None) -> np.ndarray:
    """Unit vectors (M, 2) of the beams that saw nothing (+inf, REP 117), in the ``sensor_pose`` frame.

    Free space along them can be cleared up to a chosen distance when building a map.
    """
    angles = scan.angles()[np.isposinf(scan.ranges)]
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    if sensor_pose is None:
        return directions
    return directions @ rotation(float(np.asarray(sensor_pose)[2])).T


def _voxel_means(points: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """The mean of ``points`` (N, 2) per distinct key (N,), in order of each key's first point: the sums
    in point order (as ``np.add.at``), divided by the counts. The keys are found in an open-addressing
    table of twice their number (numba's typed dict took four times as long)."""
    n = len(keys)
    size = 2
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)   # per bucket, the slot of the key there (-1: empty)
    slot_keys = np.empty(n, np.int64)
    sums = np.zeros((n, 2))
    counts = np.zeros(n, np.int64)
    used = 0
    for i in range(n):
        key = keys[i]
        h = key ^ (key >> 33)   # a 64-bit mix (wrapping), so cells along a row or a column spread
        h *= -49064778989728563
        h ^= h >> 33
        bucket = h & mask
        while table[bucket] >= 0 and slot_keys[table[bucket]] != key:
            bucket = (bucket + 1) & mask
        slot = table[bucket]
        if slot < 0:
            slot = used
            table[bucket] = slot
            slot_keys[slot] = key
            used += 1
        sums[slot, 0] += points[i, 0]
        sums[slot, 1] += points[i, 1]
        counts[slot] += 1
    means = np.empty((used, 2))
    for slot in range(used):
        means[slot, 0] = sums[slot, 0] / counts[slot]
        means[slot, 1] = sums[slot, 1] / counts[slot]
    return means


@functools.cache
def _compiled(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function`` compiled (numba, cached on disk) on first use: the shared ground imports numba only when
    something filters or converts points (the simulator and the emulators import this module too)."""
    from trundle.fusion.compiled import kernel

    return kernel(function)


def voxel_means(points: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """:func:`_voxel_means` compiled."""
    return _compiled(_voxel_means)(points, keys)


def voxel_filter(points: np.ndarray, cell_m: float) -> np.ndarray:
    """One point per ``cell_m`` square cell (the mean of the points in it), order of first appearance.

    Thins dense near-range returns so every part of a scan weighs alike in matching. The cells are grouped
    in one compiled pass (:func:`voxel_means`) where ``np.unique``, ``np.add.at`` and an argsort took
    50 us a scan; the same sums in the same order, so the same means.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0 or cell_m <= 0:
        return points
    cells = np.floor(points / cell_m).astype(np.int64)
    keys = (cells[:, 0] << 32) + cells[:, 1]  # one integer per cell
    return voxel_means(np.ascontiguousarray(points.reshape(-1, 2)), keys)
