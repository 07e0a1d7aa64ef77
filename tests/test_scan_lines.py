"""Line extraction on synthetic scans of rooms with known walls, by every method."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs.messages import LaserScan
from trundle.perception.scan_lines import EXTRACTORS, scan_points

METHODS = sorted(EXTRACTORS)


def _cast(walls: np.ndarray, pose: tuple[float, float, float], angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range to the nearest wall along each beam (inf: none) and which wall it hits (-1: none).

    walls: (W, 2, 2) segment end points in the world; pose: scanner (x, y, heading).
    Ray o + t d meets segment p + s e where t = (p - o) x e / (d x e), s = (p - o) x d / (d x e).
    """
    x, y, heading = pose
    d = np.stack([np.cos(angles + heading), np.sin(angles + heading)], axis=1)[:, None, :]   # (B, 1, 2)
    p = walls[None, :, 0, :] - np.array([x, y])                                               # (1, W, 2)
    e = walls[None, :, 1, :] - walls[None, :, 0, :]

    def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    with np.errstate(divide="ignore", invalid="ignore"):
        denominator = cross(d, e)
        t = cross(p, e) / denominator
        s = cross(p, d) / denominator
    t = np.where((t > 0) & (s >= 0) & (s <= 1) & np.isfinite(t), t, np.inf)
    hit = np.argmin(t, axis=1)
    ranges = t[np.arange(len(angles)), hit]
    return ranges, np.where(np.isfinite(ranges), hit, -1)


def _scan(ranges: np.ndarray, angle_min: float, increment: float) -> LaserScan:
    return LaserScan(0, "laser", angle_min, angle_min + increment * (len(ranges) - 1), increment, 0.0, 0.1,
                     0.02, 30.0, ranges)


def _wall_line(wall: np.ndarray, pose: tuple[float, float, float]) -> tuple[float, float]:
    """(r, alpha) of a wall in the scanner frame, from its end points."""
    x, y, heading = pose
    c, s = math.cos(heading), math.sin(heading)
    local = (wall - [x, y]) @ np.array([[c, -s], [s, c]])
    direction = local[1] - local[0]
    normal = np.array([direction[1], -direction[0]]) / np.hypot(*direction)
    r = float(normal @ local[0])
    if r < 0:
        normal, r = -normal, -r
    return r, math.atan2(normal[1], normal[0])


def _angle_error(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def _check(method: str, walls: np.ndarray, pose: tuple[float, float, float], noise: float, seed: int,
           fov_deg: float = 240.0, beams: int = 682, outliers: float = 0.0, one_per_wall: bool = True,
           **params: float) -> None:
    """Every wall seen by 30+ beams over 0.5+ m, with beams at most 10 cm apart, is found (r within
    2 cm, alpha within 1 deg) and its segment spans the seen part; the ends of every segment of
    10+ points lie within 3 cm of the wall most of its beams hit. (Fragments of a few points at
    corners and grazing walls are the false positives every method has; they are not checked.)"""
    rng = np.random.default_rng(seed)
    increment = math.radians(fov_deg) / (beams - 1 if fov_deg < 360 else beams)
    angle_min = -math.radians(fov_deg) / 2
    angles = angle_min + increment * np.arange(beams)
    truth, hit = _cast(walls, pose, angles)
    ranges = truth + rng.normal(0, noise, beams)
    if outliers:
        wrong = rng.random(beams) < outliers
        ranges[wrong] = rng.uniform(0.1, 1.0, wrong.sum()) * truth[wrong]
    ranges[rng.random(beams) < 0.02] = np.nan                        # REP 117 errors
    segments = EXTRACTORS[method](_scan(ranges, angle_min, increment), **params)
    lines = [_wall_line(w, pose) for w in walls]
    owner = []
    for segment in segments:           # the wall most of its beams hit: its ends must lie on it
        w = int(np.bincount(hit[segment.beams] + 1, minlength=len(walls) + 1).argmax()) - 1
        owner.append(w)
        if len(segment.beams) < 10:
            continue                   # a few points at a corner or grazing wall can fit a line anywhere
        r, alpha = lines[w] if w >= 0 else (np.nan, np.nan)
        normal = np.array([math.cos(alpha), math.sin(alpha)])
        off = [abs(float(normal @ end) - r) for end in (segment.start, segment.end)]
        assert max(off) < 0.03, f"segment {segment.start} - {segment.end} is not on wall {w}"
    exact = np.column_stack([truth * np.cos(angles), truth * np.sin(angles)])
    # What the scanner saw of each wall: runs of consecutive beams hitting it (a wall behind the
    # scanner shows at both ends of the field of view).
    edges = np.flatnonzero(np.diff(hit)) + 1
    for first, stop in zip(np.r_[0, edges], np.r_[edges, beams], strict=True):
        w, seen = hit[first], np.arange(first, stop)
        if w < 0 or len(seen) < 30 or math.dist(exact[seen[0]], exact[seen[-1]]) < 0.5:
            continue
        if np.hypot(*np.diff(exact[seen], axis=0).T).max() > 0.1:
            continue                   # seen so obliquely that a lost beam or two opens a gap over max_gap
        matching = [s for s, o in zip(segments, owner, strict=True) if o == w and np.isin(s.beams, seen).mean() > 0.5]
        assert matching, f"wall {w} {walls[w].tolist()} (beams {first}-{stop - 1}) not found by {method}"
        longest = max(matching, key=lambda s: s.length)
        assert abs(longest.r - lines[w][0]) < 0.02 and _angle_error(longest.alpha, lines[w][1]) < math.radians(1)
        if one_per_wall:
            assert len(matching) == 1, f"wall {w} split into {len(matching)} segments"
            # An end may reach a beam further (up to the unseen corner) or stop a beam short (the
            # corner point went to the other wall, or the beam was lost): allow two beam spacings.
            ends = sorted([longest.start, longest.end], key=lambda p: math.dist(p, exact[seen[0]]))
            assert math.dist(ends[0], exact[seen[0]]) < 0.15 + 2 * math.dist(exact[seen[0]], exact[seen[1]])
            assert math.dist(ends[1], exact[seen[-1]]) < 0.15 + 2 * math.dist(exact[seen[-1]], exact[seen[-2]])
        else:
            covered = sum(s.length for s in matching)
            assert covered > 0.8 * math.dist(exact[seen[0]], exact[seen[-1]])


def _room(width: float, depth: float) -> np.ndarray:
    corners = np.array([[0, 0], [width, 0], [width, depth], [0, depth]], dtype=float)
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


@pytest.mark.parametrize("method", METHODS)
def test_rectangular_room(method: str) -> None:
    _check(method, _room(6.0, 4.0), (2.0, 1.5, 0.3), noise=0.005, seed=1)


@pytest.mark.parametrize("method", METHODS)
def test_room_with_a_box_and_a_doorway(method: str) -> None:
    walls = np.concatenate([
        _room(7.0, 5.0)[[0, 1, 3]],
        np.array([[[7.0, 5.0], [3.5, 5.0]], [[2.5, 5.0], [0.0, 5.0]]]),          # north wall, 1 m doorway
        np.array([[[4.5, 1.0], [5.5, 1.0]], [[5.5, 1.0], [5.5, 2.0]],            # a 1 m box
                  [[5.5, 2.0], [4.5, 2.0]], [[4.5, 2.0], [4.5, 1.0]]]),
    ])
    _check(method, walls, (2.0, 2.0, 0.0), noise=0.005, seed=2, fov_deg=360, beams=1024)


@pytest.mark.parametrize("method", METHODS)
def test_outliers_do_not_make_segments(method: str) -> None:
    """An outlier next to a few wall points can tilt a 5-point fragment off the wall, so ask for 10."""
    _check(method, _room(6.0, 4.0), (3.0, 2.0, -1.0), noise=0.005, seed=3, outliers=0.03, one_per_wall=False,
           min_points=10)


@given(st.floats(2.0, 8.0), st.floats(2.0, 8.0), st.floats(0.15, 0.85), st.floats(0.15, 0.85),
       st.floats(-math.pi, math.pi), st.integers(0, 2**32 - 1), st.sampled_from(METHODS))
@settings(max_examples=80, deadline=None)
def test_random_rooms(width: float, depth: float, fx: float, fy: float, heading: float, seed: int,
                      method: str) -> None:
    pose = (0.5 + fx * (width - 1.0), 0.5 + fy * (depth - 1.0), heading)
    _check(method, _room(width, depth), pose, noise=0.005, seed=seed)


def test_scan_points_skip_invalid_readings() -> None:
    ranges = np.array([1.0, np.inf, -np.inf, np.nan, 0.01, 2.0, 40.0])
    points, beams = scan_points(_scan(ranges, 0.0, math.pi / 2))
    assert beams.tolist() == [0, 5]
    assert np.allclose(points, [[1.0, 0.0], [2 * math.cos(5 * math.pi / 2), 2 * math.sin(5 * math.pi / 2)]],
                       atol=1e-6)


@pytest.mark.parametrize("method", METHODS)
def test_empty_and_tiny_scans(method: str) -> None:
    assert EXTRACTORS[method](_scan(np.full(50, np.inf), -1.0, 0.04)) == []
    assert EXTRACTORS[method](_scan(np.array([1.0, 1.0, 1.0]), -0.1, 0.1)) == []
