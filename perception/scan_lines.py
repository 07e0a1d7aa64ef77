"""Line extraction from a 2-D laser scan: split-and-merge, incremental, RANSAC and Hough.

Each extractor takes a ``LaserScan`` and returns ``LineSegment``s in the scan's frame (metres,
REP 103): the fitted line in normal form x cos(alpha) + y sin(alpha) = r (r >= 0, alpha in
(-pi, pi]), its end points (the first and last supporting points projected onto the line) and
the beam indices that support it. Invalid readings (REP 117: inf, NaN, outside
[range_min, range_max]) are skipped. Common parameters, all in metres:

- ``threshold``: largest distance of a supporting point from its line;
- ``max_gap``: largest distance between consecutive points of one segment (a larger gap is a
  break between objects, e.g. a doorway);
- ``min_points`` and ``min_length``: smallest segment kept.

Lines are fitted by total least squares (``trundle.perception.ransac.fit_line``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from trundle.logs.messages import LaserScan
from trundle.perception.ransac import fit_line, line_residuals, ransac


@dataclass(frozen=True, eq=False)
class LineSegment:
    """A wall piece: line (r m, alpha rad), end points (x, y) m and supporting beam indices."""

    r: float
    alpha: float
    start: tuple[float, float]
    end: tuple[float, float]
    beams: np.ndarray

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)


def scan_points(scan: LaserScan) -> tuple[np.ndarray, np.ndarray]:
    """Valid returns of a scan as (N, 2) points (x, y) in metres and their beam indices, in beam order."""
    ranges = scan.ranges.astype(np.float64)
    valid = np.isfinite(ranges) & (ranges >= scan.range_min) & (ranges <= scan.range_max)
    beams = np.flatnonzero(valid)
    angles = scan.angles()[beams]
    rho = ranges[beams]
    return np.column_stack([rho * np.cos(angles), rho * np.sin(angles)]), beams


def _breaks(points: np.ndarray, max_gap: float) -> list[tuple[int, int]]:
    """Half-open index ranges [i, j) of runs whose consecutive points are at most ``max_gap`` apart."""
    if len(points) == 0:
        return []
    gaps = np.flatnonzero(np.hypot(*np.diff(points, axis=0).T) > max_gap) + 1
    edges = np.concatenate([[0], gaps, [len(points)]])
    return [(int(a), int(b)) for a, b in pairwise(edges)]


def _fits(points: np.ndarray, threshold: float) -> tuple[float, float] | None:
    """The TLS line of ``points`` if every point lies within ``threshold`` of it, else None."""
    line = fit_line(points)
    if line is None or line_residuals(line, points).max() > threshold:
        return None
    return line


def _settle(points: np.ndarray, pieces: list[tuple[int, int]], rounds: int = 3) -> list[tuple[int, int]]:
    """Move the boundary between adjacent pieces [i, k) [k, j) to where the two fitted lines
    explain the points best (least squared distance), then refit; a few rounds.

    Growing and splitting decide a corner point by where a line broke, not by which line it is
    closer to; this hands such points to the right neighbour.
    """
    pieces = list(pieces)
    for _ in range(rounds):
        moved = False
        for n in range(len(pieces) - 1):
            (i, k), (k2, j) = pieces[n], pieces[n + 1]
            if k != k2 or k - i < 2 or j - k < 2:
                continue
            left, right = fit_line(points[i:k]), fit_line(points[k:j])
            if left is None or right is None:
                continue
            span = points[i:j]
            cost_left = np.concatenate([[0.0], np.cumsum(line_residuals(left, span) ** 2)])
            cost_right = np.concatenate([np.cumsum(line_residuals(right, span)[::-1] ** 2)[::-1], [0.0]])
            best = i + 2 + int(np.argmin((cost_left + cost_right)[2:j - i - 1]))   # both keep 2+ points
            if best != k:
                pieces[n], pieces[n + 1] = (i, best), (best, j)
                moved = True
        if not moved:
            break
    return pieces


def _merge(points: np.ndarray, pieces: list[tuple[int, int]], threshold: float) -> list[tuple[int, int]]:
    """Join adjacent pieces (in order) while their union still fits one line within ``threshold``."""
    merged: list[tuple[int, int]] = []
    for i, j in pieces:
        if merged and merged[-1][1] == i and _fits(points[merged[-1][0]:j], threshold) is not None:
            merged[-1] = (merged[-1][0], j)
        else:
            merged.append((i, j))
    return merged


def _segment(points: np.ndarray, beams: np.ndarray, min_points: int, min_length: float) -> LineSegment | None:
    """A segment fitted to ``points`` (in scan order), or None when it is too small."""
    if len(points) < max(min_points, 2):
        return None
    line = fit_line(points)
    if line is None:
        return None
    r, alpha = line
    normal = np.array([math.cos(alpha), math.sin(alpha)])
    ends = points[[0, -1]] - np.outer(points[[0, -1]] @ normal - r, normal)
    segment = LineSegment(r, alpha, (float(ends[0, 0]), float(ends[0, 1])), (float(ends[1, 0]), float(ends[1, 1])),
                          np.asarray(beams))
    return segment if segment.length >= min_length else None


def _collect(pieces: list[tuple[np.ndarray, np.ndarray]], min_points: int, min_length: float) -> list[LineSegment]:
    segments = [_segment(p, b, min_points, min_length) for p, b in pieces]
    return sorted((s for s in segments if s is not None), key=lambda s: int(s.beams[0]))


def split_and_merge(scan: LaserScan, threshold: float = 0.03, max_gap: float = 0.3, min_points: int = 5,
                    min_length: float = 0.1) -> list[LineSegment]:
    """Split-and-merge: split a run at the point farthest from the chord between its ends until
    every piece fits its line within ``threshold``; then merge neighbours whose union still fits,
    hand corner points to the line they fit better and merge again."""
    points, beams = scan_points(scan)
    merged: list[tuple[int, int]] = []
    for first, stop in _breaks(points, max_gap):
        pieces, stack = [], [(first, stop)]
        while stack:
            i, j = stack.pop()
            if j - i < 3 or _fits(points[i:j], threshold) is not None:
                pieces.append((i, j))
                continue
            chord = points[j - 1] - points[i]
            offset = points[i + 1:j - 1] - points[i]
            k = i + 1 + int(np.argmax(np.abs(chord[0] * offset[:, 1] - chord[1] * offset[:, 0])))
            stack += [(k, j), (i, k)]                    # k is never an end: both halves non-empty
        merged += _merge(points, _settle(points, _merge(points, sorted(pieces), threshold)), threshold)
    return _collect([(points[i:j], beams[i:j]) for i, j in merged], min_points, min_length)


def incremental(scan: LaserScan, threshold: float = 0.03, max_gap: float = 0.3, min_points: int = 5,
                min_length: float = 0.1) -> list[LineSegment]:
    """Incremental (line tracking): grow a line point by point while every point stays within
    ``threshold`` of the refitted line; start a new line at the first point that breaks it.

    The stopping point is found by exponential then binary search over the segment length (the
    condition only gets harder as points are added), so a segment costs O(log N) fits. Corner
    points are then handed to the neighbouring line they fit better.
    """
    points, beams = scan_points(scan)
    pieces: list[tuple[int, int]] = []
    for first, stop in _breaks(points, max_gap):
        run: list[tuple[int, int]] = []
        i = first
        while stop - i >= max(min_points, 2):
            seed = i + max(min_points, 2)
            if _fits(points[i:seed], threshold) is None:
                i += 1                                   # no line starts here: drop the point
                continue
            good, step = seed, 1
            while good + step <= stop and _fits(points[i:good + step], threshold) is not None:
                good, step = good + step, step * 2
            bad = min(good + step, stop + 1)             # first length known (or assumed) to fail
            while bad - good > 1:
                middle = (good + bad) // 2
                if _fits(points[i:middle], threshold) is not None:
                    good = middle
                else:
                    bad = middle
            run.append((i, good))
            i = good
        pieces += _settle(points, run)
    return _collect([(points[i:j], beams[i:j]) for i, j in pieces], min_points, min_length)


def _pieces_of(selected: np.ndarray, points: np.ndarray, max_gap: float) -> list[np.ndarray]:
    """Split the (scan-ordered) indices ``selected`` into runs without gaps over ``max_gap``."""
    return [selected[a:b] for a, b in _breaks(points[selected], max_gap)]


def _take_line(line: tuple[float, float], points: np.ndarray, left: np.ndarray, threshold: float,
               max_gap: float, min_points: int, min_length: float) -> list[np.ndarray]:
    """Runs of the remaining points ``left`` that support ``line`` (refitted twice) and are big enough."""
    for _ in range(2):
        near = left[line_residuals(line, points[left]) < threshold]
        refit = fit_line(points[near]) if len(near) >= 2 else None
        if refit is None:
            return []
        line = refit
    near = left[line_residuals(line, points[left]) < threshold]
    return [run for run in _pieces_of(near, points, max_gap)
            if _segment(points[run], run, min_points, min_length) is not None]


def ransac_lines(scan: LaserScan, threshold: float = 0.03, max_gap: float = 0.3, min_points: int = 5,
                 min_length: float = 0.1, max_lines: int = 50, max_trials: int = 500,
                 rng: np.random.Generator | int | None = None) -> list[LineSegment]:
    """RANSAC: repeatedly find the line with most inliers among the remaining points, keep its
    gap-free runs of inliers as segments and remove them. ``rng``: seed or Generator (default 0)."""
    points, beams = scan_points(scan)
    rng = np.random.default_rng(0 if rng is None else rng)
    left = np.arange(len(points))
    runs: list[np.ndarray] = []
    while len(runs) < max_lines and len(left) >= max(min_points, 2):
        found = ransac(points[left], fit_line, line_residuals, 2, threshold, max_trials, rng=rng)
        if found.model is None:
            break
        taken = _take_line(found.model, points, left, threshold, max_gap, min_points, min_length)
        if not taken:
            break
        runs += taken
        left = np.setdiff1d(left, np.concatenate(taken))
    return _collect([(points[run], beams[run]) for run in runs], min_points, min_length)


def hough_lines(scan: LaserScan, threshold: float = 0.03, max_gap: float = 0.3, min_points: int = 5,
                min_length: float = 0.1, max_lines: int = 50, angle_step: float = math.radians(1.0),
                distance_step: float | None = None) -> list[LineSegment]:
    """Hough transform: every point votes for the lines (alpha, r) through it; the strongest
    cell gives a line whose gap-free runs of nearby points become segments; their votes are
    withdrawn and the next peak taken. ``distance_step`` defaults to ``threshold``.
    A peak that yields no segment is suppressed with its neighbouring cells; the search ends
    after ``max_lines`` segments, when no cell has ``min_points`` votes, or after ``max_lines``
    fruitless peaks."""
    points, beams = scan_points(scan)
    step = distance_step or threshold
    angles = np.arange(0.0, math.pi, angle_step)
    trig = np.stack([np.cos(angles), np.sin(angles)])               # (2, A)
    reach = float(np.hypot(*points.T).max()) if len(points) else 0.0
    cells_r = int(math.ceil(2 * reach / step)) + 2
    suppressed = np.zeros((angles.size, cells_r), dtype=bool)
    left = np.arange(len(points))
    runs: list[np.ndarray] = []
    fruitless = 0
    while len(runs) < max_lines and fruitless < max_lines and len(left) >= max(min_points, 2):
        cell_r = np.floor((points[left] @ trig + reach) / step).astype(np.int64)   # (N, A), signed r
        flat = (np.arange(angles.size) * cells_r + cell_r).ravel()
        votes = np.bincount(flat, minlength=angles.size * cells_r).reshape(angles.size, cells_r)
        votes[suppressed] = 0
        a, c = np.unravel_index(int(np.argmax(votes)), votes.shape)
        if votes[a, c] < min_points:
            break
        r = (c + 0.5) * step - reach
        line = (r, angles[a]) if r >= 0 else (-r, angles[a] - math.pi)
        taken = _take_line(line, points, left, threshold, max_gap, min_points, min_length)
        if not taken:
            suppressed[max(a - 1, 0):a + 2, max(c - 1, 0):c + 2] = True
            fruitless += 1
            continue
        runs += taken
        left = np.setdiff1d(left, np.concatenate(taken))
    return _collect([(points[run], beams[run]) for run in runs], min_points, min_length)


EXTRACTORS = {"split_and_merge": split_and_merge, "incremental": incremental, "ransac": ransac_lines,
              "hough": hough_lines}
