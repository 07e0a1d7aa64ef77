"""Descriptor matching: nearest neighbours under L2, L1 or Hamming distance, then filters.

Filters, applied in this order to each descriptor of the first set and its nearest neighbour in
the second: maximum distance; Lowe's ratio test (best / second best <= max_ratio); the
chapter's difference test (second best - best >= min_difference: the best must be clearly
better); two-way search (cross-check: each is the other's nearest neighbour). Brute force
(OpenCV's `batchDistance`, exact and deterministic) by default; FLANN (kd-trees for float
descriptors, LSH for binary ones; approximate and randomised) on request. The interface
follows scikit-image's `match_descriptors`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

NORMS = {"l2": cv2.NORM_L2, "l1": cv2.NORM_L1, "hamming": cv2.NORM_HAMMING}
ALIASES = {"euclidean": "l2", "cityblock": "l1", "manhattan": "l1"}


@dataclass(frozen=True)
class MatchResult:
    """pairs (Q, 2) int indices (into set 1, into set 2), their distances (Q,), and how many
    matches were left after each stage, in order ("nearest" first)."""

    pairs: np.ndarray
    distances: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)


def resolve_metric(descriptors: np.ndarray, metric: str | None) -> str:
    """The metric name: given (aliases allowed) or Hamming for uint8/bool descriptors, else L2."""
    if metric is None:
        return "hamming" if np.asarray(descriptors).dtype in (np.uint8, np.bool_) else "l2"
    metric = ALIASES.get(metric, metric)
    if metric not in NORMS:
        raise ValueError(f"unknown metric {metric!r} (l2, l1, hamming)")
    return metric


def _prepared(d: np.ndarray, metric: str) -> np.ndarray:
    d = np.asarray(d)
    if metric == "hamming":
        if d.dtype == np.bool_:
            d = np.packbits(d, axis=1)
        return np.ascontiguousarray(d, dtype=np.uint8)
    return np.ascontiguousarray(d, dtype=np.float32)


def nearest_neighbours(d1: np.ndarray, d2: np.ndarray, metric: str, k: int = 2,
                       flann: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(index, distance), each (N1, k): the k nearest rows of d2 for each row of d1, closest
    first; index -1 and distance inf where d2 has fewer than k rows."""
    n1 = len(d1)
    index = np.full((n1, k), -1, dtype=np.int64)
    distance = np.full((n1, k), np.inf)
    kk = min(k, len(d2))
    if n1 == 0 or kk == 0:
        return index, distance
    if not flann:
        dtype = cv2.CV_32S if metric == "hamming" else cv2.CV_32F
        dist, idx = cv2.batchDistance(d1, d2, dtype, normType=NORMS[metric], K=kk)
        index[:, :kk], distance[:, :kk] = idx, dist
        return index, distance
    params: dict[str, bool | int | float | str]
    if metric == "hamming":
        params = dict(algorithm=6, table_number=6, key_size=12, multi_probe_level=1)  # FLANN_INDEX_LSH
    elif metric == "l2":
        params = dict(algorithm=1, trees=5)                                           # FLANN_INDEX_KDTREE
    else:
        raise ValueError("FLANN supports the l2 and hamming metrics")
    matcher = cv2.FlannBasedMatcher(params, dict(checks=50))
    for row, found in enumerate(matcher.knnMatch(d1, d2, k=kk)):
        for j, m in enumerate(found):
            index[row, j], distance[row, j] = m.trainIdx, m.distance
    return index, distance


def match(d1: np.ndarray, d2: np.ndarray, metric: str | None = None, cross_check: bool = True,
          max_distance: float = math.inf, max_ratio: float = 1.0, min_difference: float = 0.0,
          flann: bool = False) -> MatchResult:
    """Match descriptor sets (rows) and report the matches left after each filter.

    `metric`: "l2", "l1" or "hamming" (None: Hamming for uint8/bool, L2 otherwise);
    `max_distance`: reject matches farther than this; `max_ratio`: reject when best / second
    best > max_ratio (Lowe uses 0.8; 1.0 keeps all); `min_difference`: reject when second
    best - best < min_difference (the chapter's threshold; 0 keeps all); `cross_check`: keep
    only mutual nearest neighbours; `flann`: approximate search instead of brute force.
    """
    metric = resolve_metric(d1, metric)
    a, b = _prepared(d1, metric), _prepared(d2, metric)
    index, distance = nearest_neighbours(a, b, metric, 2, flann)
    best, second = distance[:, 0], distance[:, 1]
    keep = index[:, 0] >= 0
    counts = {"nearest": int(keep.sum())}
    keep &= best <= max_distance
    counts["max_distance"] = int(keep.sum())
    with np.errstate(divide="ignore", invalid="ignore"):
        keep &= ~(best > max_ratio * second)
        counts["ratio"] = int(keep.sum())
        keep &= ~(second - best < min_difference)
    counts["difference"] = int(keep.sum())
    if cross_check and keep.any():
        back, _ = nearest_neighbours(b, a, metric, 1, flann)
        partner = index[:, 0]
        keep &= back[np.where(partner >= 0, partner, 0), 0] == np.arange(len(a))
    if cross_check:
        counts["cross_check"] = int(keep.sum())
    rows = np.flatnonzero(keep)
    return MatchResult(np.column_stack([rows, index[rows, 0]]), best[rows], counts)


def match_descriptors(d1: np.ndarray, d2: np.ndarray, metric: str | None = None, cross_check: bool = True,
                      max_distance: float = math.inf, max_ratio: float = 1.0, min_difference: float = 0.0,
                      flann: bool = False) -> np.ndarray:
    """Indices (Q, 2) of matched rows (set 1, set 2), as scikit-image's function; see `match`."""
    return match(d1, d2, metric, cross_check, max_distance, max_ratio, min_difference, flann).pairs
