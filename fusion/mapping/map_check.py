"""Map self-check: does each keyframe's scan agree with the map the rest of the run built?

A broken map can look clean: free-space clearing erases the doubled walls of a room mapped twice
at different headings, and only the scans drawn at their estimated poses show it. So after the
final optimisation every keyframe's scan endpoints are compared, at its optimised pose, with
every submap that it played no part in (submaps hold the keyframes of a stretch of the run and
move rigidly with the pose graph; those it was matched against or inserted into are left out,
since they agree with it by construction). Per submap, an endpoint *agrees* when an occupied
cell lies within ``tolerance_cells`` of it (plus the width of one beam at its range: the
laser's own angular resolution, so a long-range sensor is not judged on what it cannot resolve),
and *conflicts* when it lies where that submap saw free space and nothing occupied is near;
elsewhere the submap knows nothing. A keyframe whose
endpoints conflict more often than they agree is inconsistent: more of its scan contradicts the
rest of the map than supports it. The map fails when a stretch of ``min_stretch`` consecutive
compared keyframes (5: a metre of travel at the keyframe spacing) is inconsistent; shorter runs are
left to people and doors that moved. A run with nothing to compare (a short or stationary log: every
keyframe lies in the submaps it was part of) is *not checked*, neither passed nor failed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from trundle.fusion.compiled import kernel
from trundle.fusion.geometry import inverse, transform_points
from trundle.fusion.mapping.submaps import Submap

HALF_DIAGONAL = 0.5 ** 0.5  # cells from a cell's centre to its corner
NOT_CHECKED = "not checked"  # MapCheck.status with no keyframe compared


@dataclass(frozen=True)
class MapCheck:
    """Outcome of :func:`check_map`.

    ``consistency`` is the share of agreeing among all agreeing and conflicting endpoint
    comparisons (None when nothing could be compared); ``keyframe_consistency`` the same per
    keyframe (NaN: not compared); ``stretches`` the inconsistent runs ``(first, last)`` of keyframe
    indices, inclusive; ``passed`` is False when any run is ``min_stretch`` compared keyframes long,
    None when no keyframe could be compared (not checked).
    """

    consistency: float | None
    keyframe_consistency: np.ndarray
    comparisons: np.ndarray
    stretches: list[tuple[int, int]] = field(default_factory=list)
    passed: bool | None = True
    min_stretch: int = 5

    @property
    def status(self) -> str:
        """``passed``, ``failed`` or ``not checked`` (nothing to compare)."""
        return NOT_CHECKED if self.passed is None else ("passed" if self.passed else "failed")

    @property
    def compared_keyframes(self) -> int:
        return int(np.isfinite(self.keyframe_consistency).sum())

    @property
    def inconsistent_keyframes(self) -> int:
        return int((self.keyframe_consistency < 0.5).sum())


@kernel
def submap_votes(points: np.ndarray, cos: float, sin: float, x: float, y: float, origin_x: float, origin_y: float,
                 resolution: float, distance: np.ndarray, observed: np.ndarray, log_odds: np.ndarray,
                 tolerance_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Agree / conflict mask of map-frame ``points`` (N, 2) against a submap grid: each point moved into the
    grid's frame by the pose ``(x, y)`` with heading cosine and sine ``cos``, ``sin`` (``transform_points``'
    arithmetic), its cell found (``world_to_cell``'s), and there the ``distance`` field (m) within its
    ``tolerance_m`` (agree), or else a cell ``observed`` with negative ``log_odds`` (conflict). One pass
    where numpy made a dozen temporaries of half a million points a submap."""
    count = points.shape[0]
    height, width = distance.shape
    agree = np.zeros(count, np.bool_)
    conflict = np.zeros(count, np.bool_)
    for i in range(count):
        px, py = points[i, 0], points[i, 1]
        u = (cos * px - sin * py + x - origin_x) / resolution
        v = (sin * px + cos * py + y - origin_y) / resolution
        if u >= 0.0 and v >= 0.0 and u < width and v < height:   # floor(u), floor(v) on the grid (NaN: not)
            col, row = int(math.floor(u)), int(math.floor(v))
            near = distance[row, col] <= tolerance_m[i] * (1.0 + 1e-6)
            agree[i] = near
            conflict[i] = observed[row, col] and log_odds[row, col] < 0.0 and not near
    return agree, conflict


def _submap_votes(submap: Submap, frame: np.ndarray, points_map: np.ndarray, tolerance_m: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Agree / conflict mask of map-frame points against one submap placed at ``frame``; ``tolerance_m``
    per point (compiled: :func:`submap_votes`)."""
    grid = submap.grid
    if grid.shape[0] == 0:
        return np.zeros(len(points_map), bool), np.zeros(len(points_map), bool)
    to_local = inverse(frame)
    distance = grid.distance_field(0.5)  # tolerances beyond half a metre are cut
    return submap_votes(np.ascontiguousarray(points_map, np.float64).reshape(-1, 2), float(np.cos(to_local[2])),
                        float(np.sin(to_local[2])), float(to_local[0]), float(to_local[1]), float(grid.origin[0]),
                        float(grid.origin[1]), grid.resolution, distance, grid.observed, grid.log_odds,
                        np.ascontiguousarray(tolerance_m, np.float64))


def check_map(submaps: list[Submap], submap_frames: np.ndarray, keyframe_poses: np.ndarray,
              keyframe_points: list[np.ndarray], keyframe_ranges: list[np.ndarray], beam_spacing_rad: np.ndarray,
              exclude_keyframes: int, tolerance_cells: float = 2.0, min_stretch: int = 5) -> MapCheck:
    """Check every keyframe against the submaps it was not part of (see the module doc).

    ``submap_frames`` (S, 3) are the map poses of the submaps' local frames; ``keyframe_points``
    the keyframes' scan points in the robot frame, ``keyframe_ranges`` their ranges (m) and
    ``beam_spacing_rad`` each keyframe's angle between beams; a submap is left out for keyframe
    ``k`` when it holds a keyframe within ``exclude_keyframes`` of ``k`` (those it was tracked
    against and inserted into).
    """
    count = len(keyframe_poses)
    agree = np.zeros(count)
    conflict = np.zeros(count)
    world = [transform_points(pose, points) for pose, points in zip(keyframe_poses, keyframe_points, strict=True)]
    lows = np.array([w.min(axis=0) if len(w) else (np.inf, np.inf) for w in world]).reshape(-1, 2)
    highs = np.array([w.max(axis=0) if len(w) else (-np.inf, -np.inf) for w in world]).reshape(-1, 2)
    for submap, frame in zip(submaps, submap_frames, strict=True):
        if not submap.nodes or submap.grid.shape[0] == 0:
            continue
        first, last = min(submap.nodes), max(submap.nodes)
        corners = (
            np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * np.array(submap.grid.shape[::-1]) * submap.grid.resolution
        )
        box = transform_points(frame, corners + submap.grid.origin)
        lo, hi = box.min(axis=0), box.max(axis=0)
        ks = np.flatnonzero(np.all(highs >= lo, axis=1) & np.all(lows <= hi, axis=1))
        ks = ks[(ks < first - exclude_keyframes) | (ks > last + exclude_keyframes)]
        if not len(ks):
            continue
        sizes = [len(world[k]) for k in ks]
        # within tolerance_cells of the cell, not of its centre (the field measures to centres): + half a diagonal
        tolerance = np.concatenate([(tolerance_cells + HALF_DIAGONAL) * submap.grid.resolution
                                    + keyframe_ranges[k] * beam_spacing_rad[k] for k in ks])
        votes = _submap_votes(submap, frame, np.concatenate([world[k] for k in ks]), tolerance)
        submap.grid.release_cache()  # its whole-grid distance field: 150 MB over fr079's submaps if all were kept
        owner = np.repeat(ks, sizes)
        agree += np.bincount(owner, votes[0], minlength=count)
        conflict += np.bincount(owner, votes[1], minlength=count)
    total = agree + conflict
    per_keyframe = np.full(count, np.nan)
    per_keyframe[total > 0] = agree[total > 0] / total[total > 0]
    consistency = float(agree.sum() / total.sum()) if total.sum() > 0 else None
    stretches = _stretches(per_keyframe)
    passed = None if consistency is None else all(_compared(per_keyframe, a, b) < min_stretch for a, b in stretches)
    return MapCheck(consistency, per_keyframe, total, stretches, passed, min_stretch)


def _compared(per_keyframe: np.ndarray, first: int, last: int) -> int:
    return int(np.isfinite(per_keyframe[first:last + 1]).sum())


def _stretches(per_keyframe: np.ndarray, window: int = 5) -> list[tuple[int, int]]:
    """Runs of inconsistent keyframes: the median of ``window`` compared keyframes around each below 0.5
    (a broken stretch keeps a few keyframes that happen to agree; a lone bad one is not a stretch),
    bridging keyframes that could not be compared."""
    compared = np.flatnonzero(np.isfinite(per_keyframe))
    values = per_keyframe[compared]
    half = window // 2
    smooth = np.array([np.median(values[max(0, i - half):i + half + 1]) for i in range(len(values))])
    runs: list[tuple[int, int]] = []
    start = last = -1
    for k, value in zip(compared, smooth, strict=True):
        if value < 0.5 and per_keyframe[k] < 0.5:
            if start < 0:
                start = int(k)
            last = int(k)
        elif value >= 0.5 and start >= 0:
            runs.append((start, last))
            start = -1
    if start >= 0:
        runs.append((start, last))
    return runs
