"""Scan-to-map matching: multi-resolution correlative search, then Levenberg-Marquardt refinement.

The search (Olson 2009; branch and bound over max-pooled grids as in Cartographer, Hess et al.
2016) scores every pose in a window by the mean likelihood-field value under the scan's points
and finds the best exactly, robust to poor initial guesses. The refinement then minimises the
robust (Huber) sum of squared distances from the points to the nearest occupied cells, read
from a bilinearly interpolated distance field, with the one Levenberg-Marquardt core
(:func:`solve_pose`), which gives sub-cell precision and, from the Gauss-Newton Hessian, a
covariance for the match. Both are compiled, each a call or a few per match: the pyramid by OpenCV's
element-wise maxima, the branch and bound in :mod:`~trundle.fusion.matching.block_scores` (numba), the
refinement's whole solve in
:mod:`~trundle.fusion.matching.pose_solver` over the residuals of :mod:`~trundle.fusion.matching.field_residuals`.
"""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from trundle.fusion.compiled import kernel
from trundle.fusion.geometry import wrap_angle
from trundle.fusion.mapping.occupancy_grid import FieldWindow, LogOddsGrid, MatchFields
from trundle.fusion.matching.block_scores import branch_and_bound, flat_cells, lattice_cells
from trundle.fusion.matching.field_residuals import NO_WALLS, match_statistics, pairwise_sum
from trundle.fusion.matching.pose_solver import DONE, solve_pose_in_window
from trundle.fusion.optimization.levenberg_marquardt import Settings, levenberg_marquardt


@dataclass(frozen=True)
class MatchResult:
    """A scan match: robot ``pose`` (x, y, theta) in the grid frame with its 3x3 ``covariance``.

    ``score`` is the mean likelihood-field value under the points at ``pose`` (0..1, 1 = every
    point on an occupied cell); ``residual_m`` the mean distance of the inlier points to the
    nearest occupied cell; ``inlier_fraction`` the share of points within ``inlier_m`` of one;
    ``search_score`` the best correlative score (NaN when no search ran); ``overlap`` the share
    of points on cells the grid has observed and ``overlap_score`` the mean likelihood over those
    alone: a scan that sees new space scores low overall but not there, a scan put in the wrong
    place lands on known free space and scores low there too.
    """

    pose: np.ndarray
    covariance: np.ndarray
    score: float
    residual_m: float
    inlier_fraction: float
    search_score: float
    iterations: int
    overlap: float = 1.0
    overlap_score: float = 0.0


def angular_step(resolution: float, max_range_m: float) -> float:
    """The rotation that moves a point at ``max_range_m`` by one cell: ``acos(1 - r^2 / (2 d^2))``."""
    d = max(max_range_m, resolution)
    return math.acos(max(-1.0, 1.0 - resolution ** 2 / (2.0 * d * d)))


class _PyramidMemory:
    """The memory of the last pyramid made, handed to the next one once no array uses it any more.

    A pyramid is megabytes (its levels over a window that holds a whole scan), made again for every new
    reference a scan is matched against: a submap that took a keyframe, a fresh grid. Memory the allocator
    has just returned to the system comes back as pages that fault on first touch, 2.6 us each on this VM:
    60-70 faults, a sixth of an Intel comparison match. Whether an array still uses the memory is its
    reference count: every view of it (a cached pyramid, a level kept past its pyramid) holds it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._kept: np.ndarray | None = None
        self._unused = np.empty(0, np.float32)   # held as the kept memory is when no array uses it

    def take(self, size: int) -> np.ndarray:
        """float32 memory of at least ``size`` elements that no array uses, its contents anything."""
        with self._lock:
            kept, unused = self._kept, self._unused
            # the same holders counted the same way (what an interpreter counts varies between versions),
            # so any more are arrays that use it
            if kept is not None and kept.size >= size and sys.getrefcount(kept) == sys.getrefcount(unused):
                return kept
        memory = np.empty(size, np.float32)
        with self._lock:
            self._kept = memory
        return memory


PYRAMID_MEMORY = _PyramidMemory()


def score_pyramid(field: np.ndarray, levels: int, pad: int | None = None) -> np.ndarray:
    """Max-pooled copies (levels, H, W) of ``field`` padded with ``pad`` (default ``2**(levels-1)``) zero cells
    on every side.

    Level ``h`` holds at ``[r, c]`` the maximum of the padded field over ``[r, r + 2^h) x [c, c + 2^h)``,
    an upper bound of the score of every translation in that block (branch and bound). Each level is two
    OpenCV element-wise maxima: of the level below and itself ``2^(h-1)`` rows down, then of that and itself
    as many columns on (a cell within the shift of the far edge keeps its own value). OpenCV's vector code
    is twice as fast as a compiled loop here, and a maximum is exact: the same values. No maximum reads the
    array it writes (whether OpenCV may overlap them is not documented). The levels and the scratch level
    are one block of :data:`PYRAMID_MEMORY`, every cell of it written.
    """
    pad = 1 << (levels - 1) if pad is None else pad
    field = np.asarray(field, np.float32)
    height, width = field.shape[0] + 2 * pad, field.shape[1] + 2 * pad
    size = (levels + 1) * height * width
    memory = PYRAMID_MEMORY.take(size)
    planes = memory[:size].reshape(levels + 1, height, width)
    pyramid, down = planes[:levels], planes[levels]   # down: a level's maximum down the columns
    cv2.copyMakeBorder(field, pad, pad, pad, pad, cv2.BORDER_CONSTANT, dst=pyramid[0], value=0.0)
    for h in range(1, levels):
        below, level, shift = pyramid[h - 1], pyramid[h], 1 << (h - 1)
        rows, cut = max(height - shift, 0), max(width - shift, 0)
        cv2.max(below[:rows], below[shift:], dst=down[:rows])
        down[rows:] = below[rows:]
        cv2.max(down[:, :cut], down[:, shift:], dst=level[:, :cut])
        level[:, cut:] = down[:, cut:]
    return pyramid


def correlative_search(grid: LogOddsGrid, points_xy: np.ndarray, initial_pose_xyt: np.ndarray, *,
                       window_xy_m: float = 0.3, window_theta_rad: float = math.radians(10.0),
                       angular_step_rad: float | None = None, sigma_m: float | None = None,
                       min_score: float = 0.0, prior_std_xy_m: float | None = None,
                       prior_std_theta_rad: float | None = None, max_distance_m: float = 0.5,
                       wall_lines: bool = True) -> tuple[np.ndarray, float] | None:
    """Best pose on the search lattice around ``initial_pose_xyt`` and its score, or None below ``min_score``.

    ``points_xy`` (N, 2) are the scan's points in the robot frame. The lattice spans
    ``+-window_xy_m`` in x and y in steps of one cell and ``+-window_theta_rad`` in steps of
    ``angular_step_rad`` (default: one cell at the farthest point). ``sigma_m`` is the
    likelihood-field width (default one cell). With ``prior_std_xy_m`` / ``prior_std_theta_rad``
    each score is weighted by a Gaussian prior around the initial pose (as in Olson's real-time
    correlative matcher), which keeps a corridor or a row of doors from pulling the match to a
    look-alike place far from the prediction; the score returned is then the weighted one, while
    ``min_score`` applies to the unweighted score of that pose (a good match far out in a wide
    prior is still a good match).
    Branch and bound over a max-pooled pyramid makes the result the exact lattice optimum at a
    fraction of the exhaustive cost. The pyramid covers the cells the lattice can reach, no more: it
    is built on the likelihood window of the match fields that :func:`refine_pose` reads with the
    same ``max_distance_m`` and ``wall_lines`` (:func:`match_fields`), so a match computes one window.
    """
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if any(prior is not None and not prior > 0.0 for prior in (prior_std_xy_m, prior_std_theta_rad)):
        raise ValueError("a prior's standard deviation must be positive")
    if len(points) == 0 or grid.shape[0] == 0:
        return None
    res = grid.resolution
    sigma = res if sigma_m is None else sigma_m
    x0, y0, t0 = (float(v) for v in initial_pose_xyt)
    if angular_step_rad is None:
        angular_step_rad = angular_step(res, float(np.max(np.hypot(points[:, 0], points[:, 1]))))
    n_theta = int(math.floor(window_theta_rad / angular_step_rad))
    limit = int(math.ceil(window_xy_m / res))
    # Blocks of 2^(levels - 1) cells, two per axis: a level above them would hold every offset in one
    # block per angle, and its blocks' children are these, in the order the search takes them (so of equal
    # scores the same pose wins). The zero border is as wide as that block, wider than any offset.
    span_levels = int(math.ceil(math.log2(2 * limit + 1)))
    levels, pad = max(1, min(8, span_levels)), 1 << min(span_levels, 7)

    # the angles, and each rotated point's cell for the lattice's centre offset (compiled: one pass, no (angles, N)
    # temporaries)
    origin = grid.origin
    thetas, cols, rows, c_lo, c_hi, r_lo, r_hi = lattice_cells(points, t0, float(angular_step_rad), n_theta, x0, y0,
                                                               float(origin[0]), float(origin[1]), res)
    # The likelihood over a window holding every cell a lattice pose puts a point on (the match
    # fields' window, which the refinement reads too), max-pooled once per window.
    window = match_fields(grid, max_distance_m, sigma, wall_lines).around_box(c_lo - limit, c_hi + limit,
                                                                              r_lo - limit, r_hi + limit)
    pyramids: dict[tuple[int, int], tuple[FieldWindow, np.ndarray]] = grid.cached(("pyramids", float(sigma)), dict)
    if (levels, pad) not in pyramids or pyramids[levels, pad][0] is not window:
        pyramids[levels, pad] = (window, score_pyramid(window.likelihood, levels, pad))
    pyramid = pyramids[levels, pad][1]
    # Cell of each rotated point for offset (0, 0), clipped once so that every offset in
    # [0, 2 limit] stays in the array: a point off the grid then lands in the zero border,
    # which keeps level 0 exact and coarser levels upper bounds.
    height, width = pyramid.shape[1:]
    base = flat_cells(cols, rows, pad - limit - window.col0, pad - limit - window.row0, width - 1 - 2 * limit,
                      height - 1 - 2 * limit, width)
    found, a_i, dx, dy, score = branch_and_bound(
        pyramid, base, thetas, t0, limit, res, -1.0 if prior_std_xy_m is None else prior_std_xy_m,
        -1.0 if prior_std_theta_rad is None else prior_std_theta_rad, min_score)
    if not found:
        return None
    return np.array([x0 + (dx - limit) * res, y0 + (dy - limit) * res, wrap_angle(thetas[a_i])]), float(score)


# The matchers' schedule: Marquardt's scale-invariant damping from lambda 1e-3, any decrease accepted;
# stop at steps below 1 mm and 0.5 mrad (a tenth of the least uncertainty a match claims, 1 cm and
# 0.25 deg), at a decrease below 0.1 %, or when lambda passes 1e6.
MATCH_SETTINGS = Settings(initial_lambda=1e-3, min_lambda=1e-9, max_lambda=1e6, min_model_fidelity=0.0,
                          diagonal_damping=True, min_diagonal=1e-9, relative_tolerance=1e-3, absolute_tolerance=0.0,
                          step_tolerance=(1e-3, 1e-3, 5e-4))
Evaluation = tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
# the same schedule as the compiled refinement's arguments (:func:`solve_pose_in_window`)
SCHEDULE = np.array([MATCH_SETTINGS.initial_lambda, MATCH_SETTINGS.lambda_factor, MATCH_SETTINGS.min_lambda,
                     MATCH_SETTINGS.max_lambda, MATCH_SETTINGS.min_model_fidelity, MATCH_SETTINGS.min_diagonal,
                     MATCH_SETTINGS.relative_tolerance, MATCH_SETTINGS.absolute_tolerance])
STEP_TOLERANCE = np.array(MATCH_SETTINGS.step_tolerance, np.float64)


def solve_pose(evaluate: Callable[[np.ndarray], Evaluation], initial_pose_xyt: np.ndarray,
               max_iterations: int) -> tuple[np.ndarray, int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Minimise a robust cost over one planar pose with the Levenberg-Marquardt core (shared by the matchers).

    ``evaluate(pose)`` returns ``(cost, residuals (N,), jacobian (N, 3), weights (N,), mask (N,))``
    with ``cost`` the sum of a robust kernel's loss of the squared residuals and ``weights`` its
    IRLS weights; the normal equations are ``J^T W J`` and ``J^T W r``. Schedule and stopping rules:
    :data:`MATCH_SETTINGS`. The pose is a Euclidean state to the core (``x + dx``, theta wrapped at
    the end), not an SE(2) block: the Jacobians are those of that world-frame parameterisation, the
    steps are millimetres, and the retraction (measured on the landmark-grid SLAM test, drift seeds
    1-4) moved the matches by less than a millimetre and the runs by as much as their spread over seeds.
    Returns the pose, the iterations run and the last ``(residuals, jacobian, weights, mask)`` at that pose.
    The scan-to-grid refinement runs this loop compiled (:func:`solve_pose_in_window`, the same schedule);
    point-to-line ICP runs it here.
    """
    seen: dict[bytes, Evaluation] = {}   # every pose evaluated, so a step's evaluation also linearises

    def evaluated(pose: np.ndarray) -> Evaluation:
        key = pose.tobytes()
        if key not in seen:
            seen[key] = evaluate(pose)
        return seen[key]

    def linearize(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        _, r, jac, weight, _ = evaluated(pose)
        jw = jac * weight[:, None]
        return jw.T @ jac, jw.T @ r

    start = np.asarray(initial_pose_xyt, dtype=np.float64)
    pose, result = levenberg_marquardt(lambda pose: evaluated(pose)[0], linearize, start, 0, max_iterations,
                                       MATCH_SETTINGS)
    _, residuals, jacobian, weights, mask = evaluated(pose)
    pose[2] = wrap_angle(pose[2])
    return pose, result.iterations, (residuals, jacobian, weights, mask)


@kernel
def match_covariance(jacobian: np.ndarray, residuals: np.ndarray, weights: np.ndarray, inliers: np.ndarray,
                     min_std_xy_m: float, min_std_theta_rad: float, max_variance: float = 100.0,
                     shaped: bool = False) -> np.ndarray:
    """Pose covariance of a converged match from ``s^2 (J^T W J)^-1`` over its ``inliers`` (a mask of the rows).

    ``s^2`` is the weighted residual variance. Directions the points do not constrain (a
    corridor's axis) get ``max_variance`` rather than infinity. By default a floor of
    ``min_std_xy_m`` / ``min_std_theta_rad`` standard deviation is added for the map's
    discretisation. Taken as it is though, ``s^2 (J^T W J)^-1`` claims millimetres from a thousand
    points on a few walls (their errors are not independent: a wall is one constraint, however
    many points lie on it), so the floor then dominates every direction alike. Its shape is right:
    a corridor's axis holds far less information than its width. ``shaped`` keeps that shape and
    scales it so that the best-constrained translation and the rotation are no more certain than
    the floor; every weaker direction then gets proportionally more variance, so a filter takes a
    direction the scan hardly constrains from its prediction (odometry, a motion model).
    Compiled, with numpy's steps: the products through BLAS, the eigenvectors through LAPACK's ``syevd``
    as numpy's, the variance's sum pairwise (:func:`pairwise_sum`), so the same values to the bit (rows
    finite; a dozen numpy calls took 50-140 us a match).
    """
    count = 0
    for i in range(inliers.shape[0]):
        count += 1 if inliers[i] else 0
    jac, jw, squares = np.empty((count, 3)), np.empty((count, 3)), np.empty(count)
    k = 0
    for i in range(inliers.shape[0]):
        if inliers[i]:
            for j in range(3):
                jac[k, j] = jacobian[i, j]
                jw[k, j] = jacobian[i, j] * weights[i]
            squares[k] = weights[i] * residuals[i] ** 2
            k += 1
    hessian = jw.T @ jac
    variance = max(pairwise_sum(squares, 0, count) / max(count - 3, 1), 1e-10)
    eigenvalues, vectors = np.linalg.eigh(hessian)
    information = np.maximum(eigenvalues, variance / max_variance) / variance
    raw = (vectors / information) @ vectors.T
    floor = np.zeros((3, 3))
    floor[0, 0], floor[1, 1], floor[2, 2] = min_std_xy_m ** 2, min_std_xy_m ** 2, min_std_theta_rad ** 2
    if not shaped:
        covariance = raw + floor
    else:
        best_xy = np.linalg.eigvalsh(np.ascontiguousarray(raw[:2, :2]))[0]
        scale = max(1.0, min_std_xy_m ** 2 / max(best_xy, 1e-300), min_std_theta_rad ** 2 / max(raw[2, 2], 1e-300))
        values, axes = np.linalg.eigh(scale * raw)
        covariance = (axes * np.minimum(values, max_variance)) @ axes.T + 1e-6 * floor
    return 0.5 * (covariance + covariance.T)


def match_fields(grid: LogOddsGrid, max_distance_m: float, sigma_m: float, wall_lines: bool) -> MatchFields:
    """The fields the search and the refinement read on ``grid`` (one cached instance per grid version):
    wall lines when the grid keeps its returns' moments and ``wall_lines`` asks for them."""
    return grid.match_fields(max_distance_m, sigma_m, lines=grid.moments is not None and wall_lines)


def refine_pose(grid: LogOddsGrid, points_xy: np.ndarray, initial_pose_xyt: np.ndarray, *,
                max_distance_m: float = 0.5, huber_m: float | None = None, inlier_m: float | None = None,
                max_iterations: int = 20, sigma_m: float | None = None, min_std_xy_m: float = 0.01,
                min_std_theta_rad: float = math.radians(0.25), search_score: float = float("nan"),
                shaped_covariance: bool = False, wall_lines: bool = True) -> MatchResult:
    """Levenberg-Marquardt refinement of ``initial_pose_xyt`` against ``grid``'s distance field.

    Minimises ``sum huber(d_i)`` with ``d_i`` the distance (m, capped at ``max_distance_m``) from
    point i to the nearest occupied cell; ``huber_m`` defaults to one cell, ``inlier_m`` to two.
    On a grid that keeps its returns' moments (``subcell``) and with ``wall_lines`` (a scan that
    samples walls densely enough, see :func:`samples_walls_densely`), a second refinement follows from
    there, with ``d_i`` the signed distance to the wall line of the nearest occupied cell where
    its returns lie on one (:meth:`LogOddsGrid.line_data`; the field elsewhere): the
    interpolated distance field has the wide basin, but it cannot put a wall's zero between two
    cell centres; a line can, so the match is not pulled onto the cell lattice.
    The covariance is ``s^2 (J^T W J)^-1`` with ``s^2`` the weighted residual variance, plus a floor
    of ``min_std_xy_m`` / ``min_std_theta_rad`` standard deviation for the grid's discretisation
    (``shaped_covariance``: its shape scaled to that floor instead, see :func:`match_covariance`).
    """
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    res = grid.resolution
    huber = res if huber_m is None else huber_m
    inlier = 2.0 * res if inlier_m is None else inlier_m
    sigma = res if sigma_m is None else sigma_m
    fields = match_fields(grid, max_distance_m, sigma, wall_lines)
    origin = grid.origin

    px, py = points[:, 0], points[:, 1]

    def solve(start: np.ndarray, walls: bool, window: FieldWindow
              ) -> tuple[np.ndarray, int, tuple[np.ndarray, ...], FieldWindow]:
        while True:   # the solve stops where a step leaves the window: grown, solved again
            height, width = window.squared.shape
            bounds = np.array([window.row0, window.row0 + height, window.col0, window.col0 + width], np.int64)
            lines = window.lines if walls else None
            nearest, mean, normal, is_line = NO_WALLS if lines is None else (lines.nearest, lines.mean, lines.normal,
                                                                             lines.is_line)
            status, box, pose, iterations, *state = solve_pose_in_window(
                window.squared, window.distances, window.occupied, window.occupied_starts, window.occupied_cols,
                window.occupied_row0, window.occupied_col0, window.radius, nearest, mean, normal, is_line, bounds,
                np.array(fields.extent, np.int64), px, py, np.asarray(start, np.float64), origin, res, max_distance_m,
                huber, max_iterations, SCHEDULE, STEP_TOLERANCE)
            if status == DONE:
                return pose, iterations, tuple(state), window
            grown = fields.around_box(*box.tolist())
            if grown is window:   # cannot happen for finite points (the kernel asks what around() gives)
                raise RuntimeError(f"the match field window does not grow to {box}")
            window = grown

    # the window the search left (the solve grows it where its points go), else one where they start
    window = fields.window
    if window is None:
        x, y, theta = (float(v) for v in initial_pose_xyt)
        c, s = math.cos(theta), math.sin(theta)
        window = fields.around((c * px - s * py + (x - origin[0])) / res, (s * px + c * py + (y - origin[1])) / res)
    pose, iterations, (d, jac, weight, active), window = solve(initial_pose_xyt, False, window)
    walls = window.lines if fields.lines and max_iterations > 0 else None
    if walls is not None and len(walls.mean):  # from the field's wide basin to the walls
        pose, more, (d, jac, weight, active), window = solve(pose, True, window)
        iterations += more
    # score, overlap, overlap score, inlier residual and inliers in one compiled pass (numpy's means, to the bit),
    # in the window the solve ended in: it holds the points at the pose and the cells next to them
    score, overlap, overlap_score, residual, inliers, n_in = match_statistics(
        window.likelihood, window.row0, window.col0, px, py, pose, origin, res, grid.observed, d, active, inlier)
    covariance = match_covariance(jac, d, weight, inliers, min_std_xy_m, min_std_theta_rad, shaped=shaped_covariance)
    return MatchResult(pose, covariance, score, residual, n_in / max(len(points), 1), search_score, iterations,
                       overlap, overlap_score)


@kernel
def median_step(points: np.ndarray) -> float:
    """The median distance between consecutive points (N >= 2, 2), NaN if any is NaN: the C library's hypot
    (which numpy's calls) and numpy's median, to the bit, in one pass where numpy made four arrays."""
    steps = np.empty(points.shape[0] - 1)
    for i in range(steps.shape[0]):
        steps[i] = math.hypot(points[i + 1, 0] - points[i, 0], points[i + 1, 1] - points[i, 1])
        if math.isnan(steps[i]):
            return math.nan
    return np.median(steps)


def samples_walls_densely(points_xy: np.ndarray, resolution: float) -> bool:
    """Do a scan's consecutive returns lie within a cell of each other (median)? Then each wall cell
    holds returns of most scans and the lines through them are well defined; a sparse scan (a 1-degree
    laser at several metres) leaves gaps between a wall's cells, across which a point's nearest
    cell may be another wall's."""
    points = np.asarray(points_xy, np.float64).reshape(-1, 2)
    if len(points) < 3:
        return False
    return bool(median_step(np.ascontiguousarray(points)) <= resolution)


def match_scan(grid: LogOddsGrid, points_xy: np.ndarray, initial_pose_xyt: np.ndarray, *,
               window_xy_m: float = 0.3, window_theta_rad: float = math.radians(10.0),
               angular_step_rad: float | None = None, sigma_m: float | None = None, min_score: float = 0.0,
               refine: bool = True, max_distance_m: float = 0.5, huber_m: float | None = None,
               min_std_xy_m: float = 0.01, min_std_theta_rad: float = math.radians(0.25),
               prior_std_xy_m: float | None = None, prior_std_theta_rad: float | None = None,
               shaped_covariance: bool = False, wall_lines: bool = True) -> MatchResult | None:
    """Match ``points_xy`` (robot frame) against ``grid`` near ``initial_pose_xyt``; None if nothing scores
    ``min_score``.

    A correlative search over ``+-window_xy_m`` / ``+-window_theta_rad`` (optionally weighted by a
    Gaussian prior, see :func:`correlative_search`) finds the best lattice pose, then (``refine``)
    Levenberg-Marquardt polishes it and estimates the covariance.
    """
    found = correlative_search(grid, points_xy, initial_pose_xyt, window_xy_m=window_xy_m,
                               window_theta_rad=window_theta_rad, angular_step_rad=angular_step_rad,
                               sigma_m=sigma_m, min_score=min_score, prior_std_xy_m=prior_std_xy_m,
                               prior_std_theta_rad=prior_std_theta_rad, max_distance_m=max_distance_m,
                               wall_lines=wall_lines)
    if found is None:
        return None
    pose, search_score = found
    return refine_pose(grid, points_xy, pose, max_distance_m=max_distance_m, huber_m=huber_m,
                       max_iterations=20 if refine else 0, sigma_m=sigma_m, min_std_xy_m=min_std_xy_m,
                       min_std_theta_rad=min_std_theta_rad, search_score=search_score,
                       shaped_covariance=shaped_covariance, wall_lines=wall_lines)
