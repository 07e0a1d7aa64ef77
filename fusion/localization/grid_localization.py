"""Localisation on a fixed map: global localisation from an unknown start, tracking, kidnap recovery.

The map (a ``LogOddsGrid``) is only read, never updated. Three pieces:

- :func:`global_search`: an exhaustive correlative search over every free cell of a coarse copy
  of the map and every heading (Olson 2009's correlative matching; the per-heading correlation
  runs as one ``cv2.filter2D`` over the map), whose best distinct peaks are refined against the
  full-resolution map by ``trundle.fusion.matching.scan_matching.match_scan``.
- :class:`Localizer` keeps those candidates as weighted hypotheses, moves them with odometry,
  re-matches each scan locally and reweights them by match score (``log w += beta (score - 1)``),
  until one holds ``converged_probability`` of the weight and has been tracked ``min_scans``.
- Once converged, one pose is tracked with a ``PoseEKF`` (odometry predict, scan-match correct).
  A match the gate rejects is gated again against a prediction widened by a wheel slip
  (``slip_sigma_*``: differential-drive odometry fails mostly in heading). A kidnapping shows as
  ``lost_after`` consecutive scans whose local match scores below ``lost_score`` or disagrees
  with the odometry even so. The localizer then searches globally; if the best place found is
  where it was tracking, the odometry merely slipped (counted in ``stats.false_alarms``) and
  tracking resumes there, otherwise it reports the kidnapping and follows the new hypotheses.
- :meth:`Localizer.fix` takes an absolute pose fix (landmarks with known map positions,
  :mod:`trundle.fusion.localization.landmark_localization`): it localises globally at once, corrects the
  track, and fixes that keep disagreeing with it reveal a kidnapping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from trundle.fusion.geometry import compose, relative, voxel_filter, wrap_angle
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.matching.scan_matching import MatchResult, match_scan
from trundle.fusion.odometry.ekf import PoseEKF, odometry_noise
from trundle.logs.errors import UserError
from trundle.logs.messages import OccupancyGrid

SEARCHING, TRACKING = "searching", "tracking"


@dataclass(frozen=True)
class CoarseMap:
    """A coarse likelihood field for global search: ``field`` (rows, cols) in [0, 1], ``free`` mask.

    Cell ``[r, c]`` has its centre at ``origin + (c + 0.5, r + 0.5) * resolution``.
    """

    field: np.ndarray
    free: np.ndarray
    origin: np.ndarray
    resolution: float


def grid_from_map(occupancy: OccupancyGrid) -> LogOddsGrid:
    """A read-only ``LogOddsGrid`` from a saved map (e.g. ``trundle.fusion.mapping.map_io.load_map``).

    Cells of at least 50 % occupancy become occupied (``l_max``), known cells below free
    (``l_min``), -1 unknown (unobserved). The arrays are made read-only so nothing can update the
    map while localising. A rotated map origin is not supported.
    """
    if abs(occupancy.origin_theta) > 1e-9:
        raise UserError(f"maps with a rotated origin ({occupancy.origin_theta} rad) are not supported")
    grid = LogOddsGrid(float(occupancy.resolution), origin_xy=(occupancy.origin_x, occupancy.origin_y))
    data = occupancy.data
    log_odds = np.where(data >= 50, grid.l_max, np.where(data >= 0, grid.l_min, 0.0)).astype(np.float32)
    observed = data >= 0
    log_odds.flags.writeable = False
    observed.flags.writeable = False
    grid.log_odds, grid.observed = log_odds, observed
    return grid


def coarse_map(grid: LogOddsGrid, resolution_m: float = 0.2, sigma_m: float | None = None) -> CoarseMap:
    """Downsample ``grid`` for global search.

    A coarse cell's distance to the nearest obstacle is the smallest over its fine cells, so its
    likelihood ``exp(-d^2 / (2 sigma^2))`` (``sigma_m`` default: ``resolution_m``) bounds theirs; it
    is free when any of its fine cells was observed free (the robot can only stand in free space).
    """
    factor = max(1, int(round(resolution_m / grid.resolution)))
    sigma = factor * grid.resolution if sigma_m is None else sigma_m
    distance = grid.distance_field(4.0 * sigma)
    free = grid.observed & (grid.log_odds < 0)
    height, width = grid.shape
    rows, cols = -(-height // factor), -(-width // factor)
    pad = ((0, rows * factor - height), (0, cols * factor - width))
    distance = np.pad(distance, pad, constant_values=4.0 * sigma).reshape(rows, factor, cols, factor).min(axis=(1, 3))
    coarse_free = np.pad(free, pad).reshape(rows, factor, cols, factor).any(axis=(1, 3))
    likelihood = np.exp(-0.5 * (distance / sigma) ** 2).astype(np.float32)
    likelihood[distance >= 4.0 * sigma] = 0.0
    return CoarseMap(likelihood, np.asarray(coarse_free), grid.origin.copy(), factor * grid.resolution)


def correlate_headings(coarse: CoarseMap, points_xy: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """Scores (H, rows, cols): mean coarse likelihood under the points for every heading and cell.

    ``points_xy`` (N, 2) are in the robot frame; entry ``[h, r, c]`` scores the robot at the centre
    of cell ``(r, c)`` facing ``headings[h]``. Points are rounded to coarse cells.
    """
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    res = coarse.resolution
    out = np.zeros((len(headings), *coarse.field.shape), np.float32)
    if len(points) == 0:
        return out
    for h, theta in enumerate(headings):
        c, s = math.cos(theta), math.sin(theta)
        cells = np.rint(np.column_stack([c * points[:, 0] - s * points[:, 1],
                                         s * points[:, 0] + c * points[:, 1]]) / res).astype(np.int64)
        radius = int(np.abs(cells).max())
        kernel = np.zeros((2 * radius + 1, 2 * radius + 1), np.float32)
        np.add.at(kernel, (cells[:, 1] + radius, cells[:, 0] + radius), 1.0 / len(points))
        out[h] = cv2.filter2D(coarse.field, cv2.CV_32F, kernel, anchor=(radius, radius),
                              borderType=cv2.BORDER_CONSTANT)
    return out


def global_search(grid: LogOddsGrid, points_xy: np.ndarray, *, coarse: CoarseMap | None = None,
                  angular_step_rad: float = math.radians(2.0), max_candidates: int = 20,
                  separation_m: float = 1.0, separation_rad: float = math.radians(20.0),
                  refine_window_xy_m: float | None = None, refine_window_theta_rad: float | None = None,
                  max_range_m: float = 10.0, match_angular_step_rad: float = math.radians(0.5)) -> list[MatchResult]:
    """Poses of the robot anywhere on the map that explain ``points_xy``, best first.

    Parameters
    ----------
    grid : the map (read only).
    points_xy : (N, 2) scan points in the robot frame, metres.
    coarse : a precomputed :func:`coarse_map` (default: built from ``grid`` at 0.2 m).
    angular_step_rad : heading step of the exhaustive search.
    max_candidates : how many distinct peaks to refine and return.
    separation_m, separation_rad : two peaks closer than both are one candidate.
    refine_window_xy_m, refine_window_theta_rad : window of the full-resolution match around a
        peak (default: one coarse cell and one heading step).
    max_range_m : points farther than this are left out of the coarse search.
    match_angular_step_rad : heading step of the full-resolution correlative match.
    """
    coarse = coarse_map(grid) if coarse is None else coarse
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    near = points[np.hypot(points[:, 0], points[:, 1]) <= max_range_m]
    if len(near) < 3:
        return []
    headings = np.asarray(wrap_angle(np.arange(0.0, 2.0 * math.pi, angular_step_rad)))
    scores = correlate_headings(coarse, near, headings)
    scores[:, ~coarse.free] = 0.0
    # local maxima over (heading, row, col), heading axis circular
    spread = np.stack([cv2.dilate(layer, np.ones((3, 3), np.uint8)) for layer in scores])
    spread = np.maximum(spread, np.maximum(np.roll(spread, 1, axis=0), np.roll(spread, -1, axis=0)))
    peaks = (scores == spread) & (scores > 0)
    h, r, c = np.nonzero(peaks)
    order = np.argsort(scores[h, r, c])[::-1]
    poses = np.column_stack([coarse.origin[0] + (c + 0.5) * coarse.resolution,
                             coarse.origin[1] + (r + 0.5) * coarse.resolution, headings[h]])[order]
    chosen: list[np.ndarray] = []
    while len(poses) and len(chosen) < max_candidates:  # greedy non-maximum suppression, best first
        chosen.append(poses[0])
        apart = ((np.hypot(poses[:, 0] - poses[0, 0], poses[:, 1] - poses[0, 1]) > separation_m)
                 | (np.abs(wrap_angle(poses[:, 2] - poses[0, 2])) > separation_rad))
        poses = poses[apart]
    window_xy = coarse.resolution if refine_window_xy_m is None else refine_window_xy_m
    window_theta = angular_step_rad if refine_window_theta_rad is None else refine_window_theta_rad
    results = [match_scan(grid, points, pose, window_xy_m=window_xy, window_theta_rad=window_theta,
                          angular_step_rad=match_angular_step_rad) for pose in chosen]
    return sorted((r for r in results if r is not None), key=lambda r: -r.score)


@dataclass(frozen=True)
class LocalizationUpdate:
    """Result of one scan: the best pose (map frame) and its covariance, status and match quality.

    ``status`` is ``"searching"`` (several hypotheses, not yet sure) or ``"tracking"``;
    ``converged`` turns True on the scan where tracking starts; ``kidnapped`` on the scan where a
    kidnapping was detected (a new global search started); ``probability`` is the best
    hypothesis' share of the weight; ``score`` its match score (0..1, NaN if unmatched).
    """

    pose: np.ndarray
    covariance: np.ndarray
    status: str
    score: float
    probability: float
    hypotheses: int
    converged: bool = False
    kidnapped: bool = False


@dataclass
class _Hypothesis:
    pose: np.ndarray
    covariance: np.ndarray
    log_weight: float
    score: float
    scans: int = 1
    motion: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class LocalizerConfig:
    """Parameters of :class:`Localizer` (metres, radians)."""

    coarse_resolution_m: float = 0.2
    angular_step_rad: float = math.radians(2.0)
    max_candidates: int = 20
    max_range_m: float = 10.0
    beta: float = 20.0
    converged_probability: float = 0.95
    min_scans: int = 3
    good_score: float = 0.6
    prune_probability: float = 1e-4
    merge_m: float = 0.3
    merge_rad: float = math.radians(10.0)
    window_xy_m: float = 0.3
    window_theta_rad: float = math.radians(10.0)
    window_xy_per_m: float = 0.2
    window_theta_per_m: float = math.radians(5.0)
    no_odometry_window_xy_m: float = 1.0
    no_odometry_window_theta_rad: float = math.radians(30.0)
    match_angular_step_rad: float = math.radians(0.5)
    hypothesis_voxel_m: float = 0.1
    lost_score: float = 0.5
    lost_after: int = 2
    gate_chi2: float = 50.0
    slip_sigma_xy_m: float = 0.05
    slip_sigma_theta_rad: float = math.radians(10.0)
    odom_sigma_xy_m: float = 0.001
    odom_sigma_theta_rad: float = 0.001
    odom_sigma_xy_per_m: float = 0.1
    odom_sigma_theta_per_m: float = math.radians(5.0)
    odom_sigma_theta_per_rad: float = 0.1


@dataclass
class LocalizerStats:
    scans: int = 0
    global_searches: int = 0
    converged_at: list[int] = field(default_factory=list)
    kidnaps_at: list[int] = field(default_factory=list)
    false_alarms: int = 0
    fixes: int = 0
    fixes_rejected: int = 0


class Localizer:
    """Localise scans on a fixed map from an unknown start; detect and recover from kidnapping."""

    def __init__(self, grid: LogOddsGrid, config: LocalizerConfig | None = None) -> None:
        self.grid = grid
        self.config = config or LocalizerConfig()
        self.coarse = coarse_map(grid, self.config.coarse_resolution_m)
        self.status = SEARCHING
        self.stats = LocalizerStats()
        self._hypotheses: list[_Hypothesis] = []
        self._ekf: PoseEKF | None = None
        self._bad = 0
        self._fix_misses = 0

    @property
    def hypotheses(self) -> list[tuple[np.ndarray, float]]:
        """Current hypotheses as (pose, probability), best first."""
        probabilities = self._probabilities()
        return [(h.pose.copy(), float(p)) for h, p in zip(self._hypotheses, probabilities, strict=True)]

    def update(self, points_xy: np.ndarray, odometry_delta_xyt: np.ndarray | None = None) -> LocalizationUpdate:
        """Process one scan: ``points_xy`` (N, 2) in the robot frame, ``odometry_delta_xyt`` the motion
        since the previous scan in the previous robot frame (None when there is no odometry)."""
        index = self.stats.scans
        self.stats.scans += 1
        points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        if self.status == TRACKING:
            update = self._track(points, odometry_delta_xyt)
            if update is not None:
                return update
            tracked = self._hypotheses[0].pose
            self._start_search(points)
            best = self._hypotheses[0] if self._hypotheses else None
            if best is not None and best.score >= self.config.good_score and self._same_place(best.pose, tracked):
                self.stats.false_alarms += 1  # the map agrees with the track: the odometry slipped
                return self._resume(best)
            self.stats.kidnaps_at.append(index)
            return self._report(kidnapped=True)
        if not self._hypotheses:
            self._start_search(points)
        else:
            self._reweight(points, odometry_delta_xyt)
            if not self._hypotheses:
                self._start_search(points)
        best = self._hypotheses[0] if self._hypotheses else None
        if (best is not None and self._probabilities()[0] >= self.config.converged_probability
                and best.scans >= self.config.min_scans and best.score >= self.config.good_score):
            self.stats.converged_at.append(index)
            self._resume(best)
            return self._report(converged=True)
        return self._report()

    def fix(self, pose_xyt, covariance, gate_chi2: float = 16.27) -> LocalizationUpdate:
        """An absolute pose fix (map frame, 3x3 covariance), e.g. from landmarks with known map positions.

        While searching, the fix is the answer: tracking starts there. While tracking, a fix within
        ``gate_chi2`` (Mahalanobis, 3 dof; default 99.9 %) of the tracked pose corrects it; ``lost_after``
        fixes in a row outside it reveal a kidnapping, and tracking restarts at the fix. Counted in
        ``stats.fixes``, ``stats.fixes_rejected``, ``stats.converged_at`` and ``stats.kidnaps_at``
        (at the index of the next scan).
        """
        index = self.stats.scans
        pose = np.asarray(pose_xyt, np.float64).reshape(3)
        covariance = np.asarray(covariance, np.float64).reshape(3, 3)
        self.stats.fixes += 1
        hypothesis = _Hypothesis(pose.copy(), covariance.copy(), 0.0, self.config.good_score, self.config.min_scans)
        if self.status != TRACKING or self._ekf is None:
            self.stats.converged_at.append(index)
            self._resume(hypothesis)
            return self._report(converged=True)
        if self._ekf.correct(pose, covariance, gate_chi2):
            self._fix_misses = 0
            self._hypotheses[0].pose, self._hypotheses[0].covariance = (
                self._ekf.pose.copy(),
                self._ekf.covariance.copy(),
            )
            return self._report()
        self.stats.fixes_rejected += 1
        self._fix_misses += 1
        if self._fix_misses < self.config.lost_after:
            return self._report()
        self.stats.kidnaps_at.append(index)
        self.stats.converged_at.append(index)
        self._resume(hypothesis)
        return self._report(converged=True, kidnapped=True)

    def _resume(self, best: _Hypothesis) -> LocalizationUpdate:
        """Track ``best`` from here on."""
        self.status = TRACKING
        self._ekf = PoseEKF(best.pose, best.covariance)
        self._hypotheses = [best]
        self._bad = 0
        self._fix_misses = 0
        return self._report()

    def _same_place(self, a: np.ndarray, b: np.ndarray) -> bool:
        return bool(np.hypot(*(a[:2] - b[:2])) < self.config.merge_m
                    and abs(float(wrap_angle(a[2] - b[2]))) < self.config.merge_rad)

    # --- searching ---------------------------------------------------------------------------

    def _start_search(self, points: np.ndarray) -> None:
        cfg = self.config
        self.status = SEARCHING
        self._ekf = None
        self.stats.global_searches += 1
        found = global_search(self.grid, voxel_filter(points, cfg.hypothesis_voxel_m), coarse=self.coarse,
                              angular_step_rad=cfg.angular_step_rad, max_candidates=cfg.max_candidates,
                              max_range_m=cfg.max_range_m, match_angular_step_rad=cfg.match_angular_step_rad)
        self._hypotheses = [_Hypothesis(r.pose, r.covariance, cfg.beta * (r.score - 1.0), r.score) for r in found]
        self._normalise()

    def _windows(self, delta: np.ndarray | None) -> tuple[float, float]:
        cfg = self.config
        if delta is None:
            return cfg.no_odometry_window_xy_m, cfg.no_odometry_window_theta_rad
        distance = float(np.hypot(delta[0], delta[1]))
        return (cfg.window_xy_m + cfg.window_xy_per_m * distance,
                cfg.window_theta_rad + cfg.window_theta_per_m * distance)

    def _reweight(self, points: np.ndarray, delta: np.ndarray | None) -> None:
        cfg = self.config
        window_xy, window_theta = self._windows(delta)
        thinned = voxel_filter(points, cfg.hypothesis_voxel_m)
        for h in self._hypotheses:
            predicted = compose(h.pose, h.motion if delta is None else delta)
            result = match_scan(self.grid, thinned, predicted, window_xy_m=window_xy, window_theta_rad=window_theta,
                                angular_step_rad=cfg.match_angular_step_rad)
            h.score = 0.0 if result is None else result.score
            if result is not None:
                h.motion = relative(h.pose, result.pose)
                h.pose, h.covariance = result.pose, result.covariance
            h.log_weight += cfg.beta * (h.score - 1.0)
            h.scans += 1
        self._hypotheses = [h for h in self._hypotheses if h.score >= cfg.lost_score]
        self._normalise()

    def _normalise(self) -> None:
        """Sort by weight, merge hypotheses that met at one pose, drop negligible ones."""
        cfg = self.config
        self._hypotheses.sort(key=lambda h: -h.log_weight)
        kept: list[_Hypothesis] = []
        for h in self._hypotheses:
            twin = next((k for k in kept if self._same_place(h.pose, k.pose)), None)
            if twin is None:
                kept.append(h)
            else:
                twin.log_weight = float(np.logaddexp(twin.log_weight, h.log_weight))
                twin.scans = max(twin.scans, h.scans)
        self._hypotheses = kept
        if kept:
            probabilities = self._probabilities()
            self._hypotheses = [h for h, p in zip(kept, probabilities, strict=True) if p >= cfg.prune_probability]

    def _probabilities(self) -> np.ndarray:
        if not self._hypotheses:
            return np.zeros(0)
        w = np.array([h.log_weight for h in self._hypotheses])
        p = np.exp(w - w.max())
        return p / p.sum()

    # --- tracking ----------------------------------------------------------------------------

    def _track(self, points: np.ndarray, delta: np.ndarray | None) -> LocalizationUpdate | None:
        """Follow the converged pose; None once ``lost_after`` scans in a row matched badly."""
        cfg = self.config
        assert self._ekf is not None
        hypothesis = self._hypotheses[0]
        previous = self._ekf.pose.copy()
        window_xy, window_theta = self._windows(delta)
        if delta is None:  # no odometry: constant velocity, with noise as wide as the search window
            self._ekf.predict(hypothesis.motion, np.diag([window_xy / 3, window_xy / 3, window_theta / 3]) ** 2)
        else:
            self._ekf.predict(delta, odometry_noise(delta, cfg.odom_sigma_xy_m, cfg.odom_sigma_theta_rad,
                                                    cfg.odom_sigma_xy_per_m, cfg.odom_sigma_theta_per_m,
                                                    cfg.odom_sigma_theta_per_rad))
        result = match_scan(self.grid, points, self._ekf.pose, window_xy_m=window_xy, window_theta_rad=window_theta,
                            angular_step_rad=cfg.match_angular_step_rad)
        score = 0.0 if result is None else result.score
        good = result is not None and score >= cfg.lost_score
        if good and result is not None and not self._ekf.correct(result.pose, result.covariance, cfg.gate_chi2):
            # the wheels may have slipped (mostly a turn): widen the prediction by a slip and gate again
            slipped = PoseEKF(self._ekf.pose, self._ekf.covariance + np.diag(
                [cfg.slip_sigma_xy_m, cfg.slip_sigma_xy_m, cfg.slip_sigma_theta_rad]) ** 2)
            good = slipped.correct(result.pose, result.covariance, cfg.gate_chi2)
            if good:
                self._ekf.reset(slipped.pose, slipped.covariance)
        self._bad = 0 if good else self._bad + 1
        hypothesis.motion = relative(previous, self._ekf.pose)
        hypothesis.pose, hypothesis.covariance, hypothesis.score = (
            self._ekf.pose.copy(),
            self._ekf.covariance.copy(),
            score,
        )
        if self._bad >= cfg.lost_after:
            return None
        return LocalizationUpdate(self._ekf.pose.copy(), self._ekf.covariance.copy(), TRACKING, score, 1.0, 1)

    def _report(self, converged: bool = False, kidnapped: bool = False) -> LocalizationUpdate:
        if not self._hypotheses:
            return LocalizationUpdate(np.full(3, np.nan), np.full((3, 3), np.nan), self.status, float("nan"), 0.0, 0,
                                      converged, kidnapped)
        best = self._hypotheses[0]
        return LocalizationUpdate(best.pose.copy(), best.covariance.copy(), self.status, best.score,
                                  float(self._probabilities()[0]), len(self._hypotheses), converged, kidnapped)

