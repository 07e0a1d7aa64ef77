"""Robust model fitting: RANSAC and the models the chapter fits with it.

`ransac` is model-agnostic (minimal sample, inlier band, best model, least-squares refit on the
inliers). The models are plain functions: a 2-D line in normal form, a homography (normalised
DLT), a fundamental matrix (normalised 8-point, Sampson residual) and an essential matrix
(OpenCV's 5-point solver as the minimal fit, cheirality check on the result). A motion prior
(camera motion predicted from wheel odometry) rejects matches that no physical motion near the
prediction can explain. Points are (N, 2) arrays of pixel (x, y) unless stated otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

Data = np.ndarray | tuple[np.ndarray, ...]
REFITS = 10


@dataclass(frozen=True)
class RansacResult:
    """Best model (None when no sample gave one), boolean inlier mask and trials run."""

    model: Any
    inliers: np.ndarray
    trials: int


def _subset(data: Data, index: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(d[index] for d in data) if isinstance(data, tuple) else (data[index],)


def _candidates(fitted: Any) -> list[Any]:
    if fitted is None:
        return []
    return list(fitted) if isinstance(fitted, list) else [fitted]


def required_trials(inlier_ratio: float, min_samples: int, confidence: float) -> float:
    """Trials needed to draw one all-inlier sample with probability `confidence`."""
    good = inlier_ratio ** min_samples
    if good >= 1.0:
        return 0.0
    miss = math.log1p(-good)
    return math.log(1.0 - confidence) / miss if miss < 0.0 else math.inf


def ransac(data: Data, fit: Callable[..., Any], residuals: Callable[..., np.ndarray], min_samples: int,
           threshold: float, max_trials: int = 1000, confidence: float = 0.99,
           rng: np.random.Generator | int | None = None) -> RansacResult:
    """Fit a model robustly to `data` (an array, or a tuple of arrays of equal length).

    Each trial draws `min_samples` distinct rows, calls `fit(*sample)` (a model, a list of
    candidate models, or None for a degenerate sample) and scores every candidate by the number
    of rows with `residuals(model, *data) < threshold`; ties go to the smaller sum of inlier
    residuals. Trials stop early once `confidence` of having drawn an all-inlier sample is
    reached. The best model is then refitted by `fit` on all its inliers and the inliers
    recomputed, repeatedly until they stop changing (at most REFITS times).
    `rng`: a Generator, a seed, or None for seed 0 (results are reproducible by default).
    """
    arrays = data if isinstance(data, tuple) else (data,)
    n = len(arrays[0])
    if any(len(a) != n for a in arrays):
        raise ValueError("all data arrays need the same length")
    if min_samples < 1:
        raise ValueError("min_samples must be at least 1")
    none = np.zeros(n, dtype=bool)
    if n < min_samples:
        return RansacResult(None, none, 0)
    rng = np.random.default_rng(0 if rng is None else rng)
    best_model, best_inliers, best_count, best_cost = None, none, -1, math.inf
    needed, trials = float(max_trials), 0
    while trials < min(max_trials, needed):
        trials += 1
        sample = _subset(data, rng.choice(n, min_samples, replace=False))
        for model in _candidates(fit(*sample)):
            r = residuals(model, *arrays)
            inliers = r < threshold
            count = int(inliers.sum())
            if count < best_count:
                continue
            cost = float(r[inliers].sum())
            if count > best_count or cost < best_cost:
                best_model, best_inliers, best_count, best_cost = model, inliers, count, cost
                needed = required_trials(count / n, min_samples, confidence)
    if best_model is None:
        return RansacResult(None, none, trials)
    for _ in range(REFITS):
        if best_inliers.sum() <= min_samples:
            break
        refit = _candidates(fit(*_subset(data, best_inliers)))
        if not refit:
            break
        inliers = residuals(refit[0], *arrays) < threshold
        if inliers.sum() < min_samples:
            break
        same = np.array_equal(inliers, best_inliers)
        best_model, best_inliers = refit[0], inliers
        if same:
            break
    return RansacResult(best_model, best_inliers, trials)


# --- 2-D line, normal form x cos(alpha) + y sin(alpha) = r --------------------------------------


def fit_line(points: np.ndarray) -> tuple[float, float] | None:
    """Total-least-squares line (r, alpha) through (N, 2) points; r >= 0, alpha in (-pi, pi].

    Minimises the sum of squared perpendicular distances. None when the points do not span a
    direction (fewer than two distinct points).
    """
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return None
    centre = p.mean(axis=0)
    d = p - centre
    sxx, syy, sxy = float(d[:, 0] @ d[:, 0]), float(d[:, 1] @ d[:, 1]), float(d[:, 0] @ d[:, 1])
    if (sxx + syy) / len(p) <= 1e-24 * max(1.0, float(centre @ centre)):
        return None
    alpha = 0.5 * math.atan2(-2.0 * sxy, syy - sxx)
    r = centre[0] * math.cos(alpha) + centre[1] * math.sin(alpha)
    if r < 0:
        r, alpha = -r, alpha + math.pi
    alpha = math.atan2(math.sin(alpha), math.cos(alpha))
    return float(r), float(alpha) + 0.0


def line_residuals(model: tuple[float, float], points: np.ndarray) -> np.ndarray:
    """Perpendicular distance of each point to the line (r, alpha)."""
    r, alpha = model
    p = np.asarray(points, dtype=float)
    return np.abs(p[:, 0] * math.cos(alpha) + p[:, 1] * math.sin(alpha) - r)


# --- Homography (normalised DLT) -----------------------------------------------------------------


def _hartley(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Similarity T moving the centroid to 0 and the mean distance to sqrt(2); returns (T, T p)."""
    p = np.asarray(points, dtype=float)
    centre = p.mean(axis=0)
    spread = np.sqrt(((p - centre) ** 2).sum(axis=1)).mean()
    s = math.sqrt(2.0) / spread if spread > 0 else 1.0
    t = np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])
    return t, (p - centre) * s


def _null_vector(a: np.ndarray, rank: int) -> np.ndarray | None:
    """Unit vector minimising |a v|; None when a has rank below `rank` (degenerate points)."""
    _, s, vt = np.linalg.svd(a)
    if len(s) < rank or s[rank - 1] <= 1e-9 * s[0]:
        return None
    return vt[-1]


def fit_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Homography H (3x3, H[2, 2] = 1 where possible) with dst ~ H src, by normalised DLT.

    Needs 4 or more point pairs; None for degenerate configurations (e.g. 3 collinear of 4).
    """
    if len(src) < 4:
        return None
    t1, a = _hartley(src)
    t2, b = _hartley(dst)
    n = len(a)
    x, y, u, v = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
    zero, one = np.zeros(n), np.ones(n)
    rows = np.empty((2 * n, 9))
    rows[0::2] = np.stack([-x, -y, -one, zero, zero, zero, u * x, u * y, u], axis=1)
    rows[1::2] = np.stack([zero, zero, zero, -x, -y, -one, v * x, v * y, v], axis=1)
    h = _null_vector(rows, 8)
    if h is None:
        return None
    m = np.linalg.solve(t2, h.reshape(3, 3) @ t1)
    scale = m[2, 2] if abs(m[2, 2]) > 1e-12 * np.abs(m).max() else np.linalg.norm(m)
    return m / scale


def project(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (N, 2) points (points mapped to infinity become inf)."""
    p = np.asarray(points, dtype=float)
    q = p @ h[:, :2].T + h[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = q[:, :2] / q[:, 2:3]
    return np.where(np.isfinite(out), out, np.inf)


def homography_residuals(h: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Transfer error |dst - H src| in image-2 pixels (as OpenCV's findHomography measures)."""
    return np.sqrt(((project(h, src) - dst) ** 2).sum(axis=1))


# --- Fundamental matrix (normalised 8-point, Sampson distance) -----------------------------------


def _eight_point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray | None:
    """Rank-2 F with x2^T F x1 = 0 by the normalised 8-point algorithm, unit Frobenius norm."""
    if len(x1) < 8:
        return None
    t1, a = _hartley(x1)
    t2, b = _hartley(x2)
    rows = np.column_stack([b[:, 0:1] * a, b[:, 0:1], b[:, 1:2] * a, b[:, 1:2], a, np.ones(len(a))])
    f = _null_vector(rows, 8)
    if f is None:
        return None
    u, s, vt = np.linalg.svd(f.reshape(3, 3))
    f = t2.T @ (u @ np.diag([s[0], s[1], 0.0]) @ vt) @ t1
    return f / np.linalg.norm(f)


def fit_fundamental(x1: np.ndarray, x2: np.ndarray) -> np.ndarray | None:
    """Fundamental matrix (3x3, rank 2, unit norm) with x2^T F x1 = 0 from 8 or more pairs."""
    return _eight_point(x1, x2)


def sampson_distance(f: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric distance of each pair to the epipolar constraint x2^T F x1 = 0.

    In the units of the points (pixels for F, normalised image units for E).
    """
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    fx1 = h1 @ f.T
    ftx2 = h2 @ f
    e = (h2 * fx1).sum(axis=1)
    denom = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.abs(e) / np.sqrt(denom)
    return np.where(np.isfinite(d), d, np.inf)


# --- Essential matrix (5-point minimal solver, cheirality) ----------------------------------------


@dataclass(frozen=True)
class RelativePose:
    """Essential matrix and the camera motion it encodes: x2 = R x1 + t (camera-1 -> camera-2
    coordinates), t of unit length (the scale is not observable)."""

    essential: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray


def fit_essential(x1: np.ndarray, x2: np.ndarray) -> list[np.ndarray] | np.ndarray | None:
    """Essential matrices from normalised image coordinates (K^-1 x).

    Exactly 5 pairs: the up-to-10 solutions of Nister's 5-point solver (OpenCV's). More pairs:
    the linear 8-point least-squares fit projected onto the essential manifold (singular values
    1, 1, 0).
    """
    if len(x1) < 5:
        return None
    if len(x1) == 5:
        e, _ = cv2.findEssentialMat(np.ascontiguousarray(x1, dtype=np.float64),
                                    np.ascontiguousarray(x2, dtype=np.float64), np.eye(3), method=cv2.LMEDS)
        if e is None:
            return None
        return [e[i:i + 3] for i in range(0, e.shape[0], 3)]
    f = _eight_point(x1, x2)
    if f is None:
        return None
    u, _, vt = np.linalg.svd(f)
    e = u @ np.diag([1.0, 1.0, 0.0]) @ vt
    return e / np.linalg.norm(e)


def triangulated_depths(rotation: np.ndarray, translation: np.ndarray, x1: np.ndarray,
                        x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths of each pair's triangulated point in camera 1 and camera 2 (normalised coords)."""
    p1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    p2 = np.hstack([rotation, np.reshape(translation, (3, 1))])
    xh = cv2.triangulatePoints(p1, p2, np.asarray(x1, dtype=np.float64).T, np.asarray(x2, dtype=np.float64).T)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = (xh[:3] / xh[3]).T
    return points[:, 2], points @ rotation[2] + float(np.ravel(translation)[2])


def in_front(rotation: np.ndarray, translation: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Cheirality: pairs that the motion (R, t) reconstructs in front of both cameras."""
    z1, z2 = triangulated_depths(rotation, translation, x1, x2)
    return np.isfinite(z1) & np.isfinite(z2) & (z1 > 0) & (z2 > 0)


def essential_pose(e: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): of the four motions E encodes, the one that puts most of the pairs (normalised
    coordinates) in front of both cameras."""
    r1, r2, t = cv2.decomposeEssentialMat(e)
    motions = [(r1, t.ravel()), (r1, -t.ravel()), (r2, t.ravel()), (r2, -t.ravel())]
    counts = [int(in_front(r, tt, x1, x2).sum()) for r, tt in motions]
    return motions[int(np.argmax(counts))]


def normalise_points(points: np.ndarray, camera_matrix: np.ndarray) -> np.ndarray:
    """Pixel (x, y) -> normalised image coordinates K^-1 (x, y, 1) (no lens distortion)."""
    p = np.column_stack([np.asarray(points, dtype=float), np.ones(len(points))])
    q = np.linalg.solve(np.asarray(camera_matrix, dtype=float), p.T).T
    return q[:, :2] / q[:, 2:3]


# --- Motion prior from odometry -------------------------------------------------------------------

# Optical frame (x right, y down, z forward) expressed in base_link (x forward, y left, z up).
OPTICAL_IN_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_motion_from_odometry(dx: float, dy: float, dtheta: float,
                                base_to_camera: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera motion (R, t), x2 = R x1 + t in camera coordinates, from a planar odometry step.

    (dx, dy, dtheta): pose of base_link at time 2 in base_link at time 1 (metres, radians, REP
    103). `base_to_camera`: 4x4 pose of the camera optical frame in base_link; default is a
    camera at the base origin looking forward.
    """
    mount = np.eye(4)
    mount[:3, :3] = OPTICAL_IN_BASE
    if base_to_camera is not None:
        mount = np.asarray(base_to_camera, dtype=float)
    c, s = math.cos(dtheta), math.sin(dtheta)
    step = np.array([[c, -s, 0.0, dx], [s, c, 0.0, dy], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    cam2_in_cam1 = np.linalg.inv(mount) @ step @ mount
    cam1_in_cam2 = np.linalg.inv(cam2_in_cam1)
    return cam1_in_cam2[:3, :3], cam1_in_cam2[:3, 3]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def motion_prior_mask(x1: np.ndarray, x2: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                      camera_matrix: np.ndarray, threshold: float = 20.0) -> np.ndarray:
    """Pairs of pixels (x1, x2) that the predicted camera motion (R, t) can explain.

    A scene point seen at x1 can only appear in image 2 on the ray that starts at x1' = K R K^-1
    x1 (infinite depth) and runs along its epipolar line in the direction of decreasing depth
    (away from the focus of expansion when driving forward). A pair is kept when x2 lies within
    `threshold` pixels of that ray: Sampson distance to the predicted epipolar geometry below the
    threshold and no more than the threshold behind x1'. Pure rotation (|t| ~ 0): x2 within the
    threshold of x1'. The threshold must cover the odometry's error (a heading error of 1 degree
    moves points by about f * 0.017 pixels).
    """
    k = np.asarray(camera_matrix, dtype=float)
    rotation = np.asarray(rotation, dtype=float)
    t = np.asarray(translation, dtype=float).ravel()
    infinite = k @ rotation @ np.linalg.inv(k)
    if np.linalg.norm(t) < 1e-9:
        return homography_residuals(infinite, x1, x2) < threshold
    t = t / np.linalg.norm(t)
    f = np.linalg.inv(k).T @ _skew(t) @ rotation @ np.linalg.inv(k)
    a = np.column_stack([x1, np.ones(len(x1))]) @ infinite.T
    b = k @ t
    # direction x2 moves in as the inverse depth grows from 0: d/ds of (a + s b)_xy / (a + s b)_z
    direction = b[:2] * a[:, 2:3] - a[:, :2] * b[2]
    length = np.sqrt((direction ** 2).sum(axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        start = a[:, :2] / a[:, 2:3]
        behind = -((x2 - start) * direction).sum(axis=1) / length
    behind = np.where(np.isfinite(behind), behind, 0.0)
    return (sampson_distance(f, x1, x2) < threshold) & (behind < threshold) & (a[:, 2] > 0)


# --- Convenience: the three image models with their RANSAC ---------------------------------------


def _pixels(points: Sequence | np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=float).reshape(-1, 2)


def find_homography(src: np.ndarray, dst: np.ndarray, threshold: float = 3.0, max_trials: int = 2000,
                    confidence: float = 0.995, rng: np.random.Generator | int | None = None) -> RansacResult:
    """RANSAC homography dst ~ H src from matched pixels (inlier band `threshold` px)."""
    return ransac((_pixels(src), _pixels(dst)), fit_homography, homography_residuals, 4, threshold,
                  max_trials, confidence, rng)


def find_fundamental(x1: np.ndarray, x2: np.ndarray, threshold: float = 1.0, max_trials: int = 2000,
                     confidence: float = 0.995, rng: np.random.Generator | int | None = None) -> RansacResult:
    """RANSAC fundamental matrix (x2^T F x1 = 0) from matched pixels (Sampson band in px)."""
    return ransac((_pixels(x1), _pixels(x2)), fit_fundamental, sampson_distance, 8, threshold,
                  max_trials, confidence, rng)


def find_essential(x1: np.ndarray, x2: np.ndarray, camera_matrix: np.ndarray, threshold: float = 1.0,
                   max_trials: int = 1000, confidence: float = 0.995, rng: np.random.Generator | int | None = None,
                   prior: tuple[np.ndarray, np.ndarray] | None = None, prior_threshold: float = 20.0) -> RansacResult:
    """RANSAC essential matrix and camera motion from matched pixels of a calibrated camera.

    `threshold`: Sampson band in pixels (converted with the mean focal length). Pairs the final
    motion reconstructs behind either camera are not inliers (cheirality). `prior`: predicted
    motion (R, t) (e.g. `camera_motion_from_odometry`); pairs it cannot explain within
    `prior_threshold` px are rejected before RANSAC. The model is a `RelativePose`.
    """
    p1, p2 = _pixels(x1), _pixels(x2)
    k = np.asarray(camera_matrix, dtype=float)
    allowed = np.ones(len(p1), dtype=bool)
    if prior is not None:
        allowed = motion_prior_mask(p1, p2, prior[0], prior[1], k, prior_threshold)
    n1, n2 = normalise_points(p1, k), normalise_points(p2, k)
    focal = 0.5 * (k[0, 0] + k[1, 1])
    found = ransac((n1[allowed], n2[allowed]), fit_essential, sampson_distance, 5, threshold / focal,
                   max_trials, confidence, rng)
    inliers = np.zeros(len(p1), dtype=bool)
    if found.model is None:
        return RansacResult(None, inliers, found.trials)
    a1, a2 = n1[allowed], n2[allowed]
    rotation, translation = essential_pose(found.model, a1[found.inliers], a2[found.inliers])
    inliers[np.flatnonzero(allowed)] = found.inliers & in_front(rotation, translation, a1, a2)
    return RansacResult(RelativePose(found.model, rotation, translation), inliers, found.trials)
