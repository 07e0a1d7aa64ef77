"""Point landmarks from a 2-D laser scan without ids: the corners where two extracted walls meet.

Lines come from the split-and-merge extractor (``trundle.perception.scan_lines``). Two segments
consecutive in beam order form a corner when their facing ends lie within ``max_gap`` of each other
and of the lines' intersection, and the lines meet at an angle between ``min_angle_rad`` and
``pi - min_angle_rad`` (a flat join is no feature). The corner is the intersection; its covariance
comes from the two line fits: with perpendicular noise ``sigma`` (the segment's RMS residual, at
least ``sigma_m``), a line of ``n`` points has an offset variance ``sigma^2 / n`` at its centroid and
an angle variance ``sigma^2 / sum s_i^2`` (``s_i`` the points' positions along it), and the
intersection moves by ``A^-1 (d_offset - (n'_k . (p - c_k)) d_angle_k)`` (rows ``A_k`` the normals).
Observations are returned in the robot frame, for a laser mounted at ``mount`` (x, y, yaw).
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np

from trundle.logs.messages import LandmarkObservation, LaserScan
from trundle.perception.ransac import line_residuals
from trundle.perception.scan_lines import LineSegment, scan_points, split_and_merge


def _line_statistics(segment: LineSegment, points: np.ndarray, sigma_floor: float) -> tuple[np.ndarray, float, float]:
    """Centroid, offset variance and angle variance of a segment's line."""
    centroid = points.mean(axis=0)
    direction = np.array([-math.sin(segment.alpha), math.cos(segment.alpha)])
    along = (points - centroid) @ direction
    sigma = max(sigma_floor, float(np.sqrt(np.mean(line_residuals((segment.r, segment.alpha), points) ** 2))))
    return centroid, sigma ** 2 / len(points), sigma ** 2 / max(float(along @ along), 1e-12)


def corners(scan: LaserScan, segments: list[LineSegment] | None = None, max_gap: float = 0.3,
            min_angle_rad: float = math.radians(45.0), sigma_m: float = 0.01) -> list[tuple[np.ndarray, np.ndarray]]:
    """Corners (position (2,) m and 2x2 covariance, laser frame) where consecutive segments meet."""
    segments = split_and_merge(scan) if segments is None else segments
    points, beams = scan_points(scan)
    index = {int(b): k for k, b in enumerate(beams)}
    found = []
    for a, b in pairwise(segments):
        angle = abs(math.remainder(a.alpha - b.alpha, math.pi))
        if not min_angle_rad <= angle <= math.pi - min_angle_rad:
            continue
        normals = np.array([[math.cos(a.alpha), math.sin(a.alpha)], [math.cos(b.alpha), math.sin(b.alpha)]])
        corner = np.linalg.solve(normals, [a.r, b.r])
        ends = np.array(a.end), np.array(b.start)
        if (np.hypot(*(ends[0] - ends[1])) > max_gap or np.hypot(*(corner - ends[0])) > max_gap
                or np.hypot(*(corner - ends[1])) > max_gap):
            continue
        inverse = np.linalg.inv(normals)
        variances = []
        for segment, normal in ((a, normals[0]), (b, normals[1])):
            pts = points[[index[int(k)] for k in segment.beams]]
            centroid, offset_var, angle_var = _line_statistics(segment, pts, sigma_m)
            lever = np.array([-normal[1], normal[0]]) @ (corner - centroid)
            variances.append(offset_var + lever ** 2 * angle_var)
        found.append((corner, inverse @ np.diag(variances) @ inverse.T))
    return found


def corner_observations(scan: LaserScan, mount=(0.0, 0.0, 0.0), **options) -> list[LandmarkObservation]:
    """The scan's corners as anonymous landmark observations in the robot frame (laser at ``mount``)."""
    x, y, yaw = (float(v) for v in mount)
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s], [s, c]])
    return [LandmarkObservation.from_position("", rotation @ p + (x, y), rotation @ cov @ rotation.T)
            for p, cov in corners(scan, **options)]
