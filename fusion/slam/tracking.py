"""Pose tracking of the local trajectory builder: an EKF predicted by odometry (or the motion model)
and corrected by scan-to-submap matches.

A match scoring as well as the recent ones on this log is believed; a poorer one only where the
prediction expects it (Mahalanobis gate). Odometry increments the laser contradicts are rejected
(:class:`trundle.fusion.odometry.check.OdometryCheck`) and the match bridges them; without odometry a
failed match is retried over the widest window, and at any heading.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from trundle.fusion.geometry import relative, rotate_covariance, wrap_angle
from trundle.fusion.mapping.submaps import Submap
from trundle.fusion.matching.scan_matching import MatchResult, match_scan, refine_pose
from trundle.fusion.odometry.check import OdometryCheck
from trundle.fusion.odometry.ekf import GATE_CHI2_99, PoseEKF, odometry_noise
from trundle.fusion.odometry.motion_model import MotionPrediction
from trundle.fusion.optimization.robust_window import RobustWindow
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.stats import SlamStats


def _mahalanobis2(prediction: np.ndarray, covariance: np.ndarray, result: MatchResult) -> float:
    """Squared Mahalanobis distance of a match from a predicted pose with ``covariance`` (both uncertain)."""
    innovation = result.pose - prediction
    innovation[2] = wrap_angle(innovation[2])
    return float(innovation @ np.linalg.solve(covariance + result.covariance, innovation))


class Tracker:
    """The tracked pose (``ekf``, local frame) and how it follows the scans; ``dense`` says whether
    the current scan samples walls densely (point-to-line refinement), set per scan."""

    def __init__(self, config: SlamConfig, stats: SlamStats) -> None:
        self.config = config
        self.stats = stats
        self.ekf: PoseEKF | None = None
        self.odometry_check = OdometryCheck()
        self.dense = True
        self._scores = RobustWindow()

    def odometry_noise(self, step: np.ndarray) -> np.ndarray:
        """The odometry noise model's covariance of one increment (robot frame)."""
        o = self.config.odometry
        return odometry_noise(step, o.sigma_xy_m, o.sigma_theta_rad, o.sigma_xy_per_m, o.sigma_theta_per_m,
                              o.sigma_theta_per_rad)

    def predict(self, odom_step: np.ndarray | None, motion: MotionPrediction) -> None:
        """Move the EKF by the odometry increment (with the noise learned on this log), or by the motion
        model's step without odometry."""
        assert self.ekf is not None
        if odom_step is not None:
            self.ekf.predict(odom_step, self.odometry_check.noise(self.odometry_noise(odom_step)))
        else:
            self.ekf.predict(motion.delta, motion.covariance)

    def matched(self, result: MatchResult) -> None:
        """Count a believed match among the recent scores (what is usual on this log)."""
        self.stats.matched += 1
        self.stats.scores.append(result.score)
        self.stats.residuals.append(result.residual_m)
        self._scores.add(result.overlap_score)

    def track(self, submap: Submap, points: np.ndarray, odom_step: np.ndarray | None,
              motion: MotionPrediction, tracked_points: Callable[[], np.ndarray]) -> tuple[MatchResult | None, bool]:
        """Match the scan and correct the EKF; returns the match used (None: prediction only) and whether it searched.

        With odometry the match starts from its increment; when the laser contradicts the increment
        that match bridges it, and when the match is poor the scan is matched again from the motion
        model alone (a glitch may have thrown the prediction beyond its window) and a good match from
        there bridges it; either way the increment is rejected. Without odometry a failed match is
        retried once over the widest window.
        """
        assert self.ekf is not None
        tracking = self.config.tracking
        before = PoseEKF(self.ekf.pose, self.ekf.covariance)
        self.predict(odom_step, motion)
        result, searched = self._match(submap, points, self.ekf.pose, self.ekf.covariance)
        usual = result is not None and self._usual(result)
        if odom_step is not None and self.config.odometry.check:
            disagreement = relative(self.ekf.pose, result.pose) if result is not None else np.zeros(3)
            match_covariance = rotate_covariance(result.covariance, -float(self.ekf.pose[2])) if result else np.eye(3)
            model = self.odometry_noise(odom_step)
            outlier = usual and self.odometry_check.is_outlier(disagreement, match_covariance, model)
            if usual and not outlier:
                assert result is not None   # usual: there is a match
                self.odometry_check.accept(disagreement, match_covariance, model)
                return self._fuse(result), searched
            self.odometry_check.interrupt()
            before.predict(motion.delta, motion.covariance)
            points = tracked_points()  # de-skewed without the odometry in question
            if not usual:  # the truth may lie outside the odometry's window: match from the motion model
                alternative, also_searched = self._match(submap, points, before.pose, before.covariance)
                searched |= also_searched
                if alternative is not None and self._usual(alternative) and self._clearly_better(alternative, result):
                    result, usual = alternative, True
            elif result is not None:
                result = refine_pose(submap.grid, points, result.pose, shaped_covariance=True, wall_lines=self.dense)
                usual = self._usual(result)
            if usual:  # the laser contradicts the odometry increment: the match bridges it
                assert result is not None   # usual: there is a match
                self.stats.odometry_rejected += 1
                self.ekf = before
                return self._fuse(result), searched
        elif odom_step is None and usual:
            assert result is not None   # usual: there is a match
            return self._fuse(result), searched
        elif odom_step is None:  # motion unlike any seen lately (a robot that turned on the spot sets off):
            # the widest window, around the prediction and around the last pose (a velocity extrapolated too far)
            widest = np.diag([(tracking.search_window_xy_m[1] / 3.0) ** 2] * 2
                             + [(tracking.search_window_theta_rad[1] / 3.0) ** 2])
            centres = [self.ekf.pose] if motion.predictor == "standstill" else [self.ekf.pose, before.pose]
            retries = [self._match(submap, points, centre, widest) for centre in centres]
            searched |= any(also for _, also in retries)
            usual_retries = [r for r, _ in retries if r is not None and self._usual(r)]
            if not usual_retries:  # a slow log's robot may turn further than the widest window between two scans
                turned = self._match_any_heading(submap, points, before.pose)
                searched = True
                if turned is not None and self._usual(turned):
                    self.ekf = PoseEKF(turned.pose, np.diag([(tracking.search_window_xy_m[1] / 3.0) ** 2] * 2
                                                            + [(math.pi / 3.0) ** 2]))
                    return self._fuse(turned), searched
            if usual_retries:
                self.ekf.covariance = self.ekf.covariance + widest
                return self._fuse(max(usual_retries, key=lambda r: r.score)), searched
        if result is not None and self.ekf.mahalanobis2(result.pose, result.covariance) <= tracking.gate_chi2:
            return self._fuse(result), searched
        if result is not None:
            self.stats.gated_out += 1
        return None, searched

    def _usual(self, result: MatchResult) -> bool:
        """Does a match fit as well as the recent ones on this log? Its score at least ``min_match_score``,
        and its score where the submap has seen anything (``overlap_score``: new space seen is no
        fault) within 4 robust sigma or 20 % of their median, whichever is wider (scores barely vary
        while the robot stands)."""
        if result.score < self.config.tracking.min_match_score:
            return False
        if len(self._scores) < 10:
            return True
        median = float(self._scores.median())
        return result.overlap_score >= min(median - 4.0 * float(self._scores.scale()), 0.8 * median)

    def _clearly_better(self, result: MatchResult, other: MatchResult | None) -> bool:
        """Does ``result`` fit clearly better than ``other`` (by a tenth of its score)? A match from a
        wider window has more chances to fit a look-alike place nearly as well. The same scan's
        matches compare by their whole score: one that puts the scan out into unknown space would
        look fine where it still overlaps."""
        return other is None or result.score >= 1.1 * other.score

    def _fuse(self, result: MatchResult) -> MatchResult:
        """Correct the EKF with a believed match. A prediction that the match puts beyond its 99 % gate
        claimed too little uncertainty: its covariance is widened by the excess first, so the match
        is not averaged with a prediction it has shown wrong."""
        assert self.ekf is not None
        d2 = self.ekf.mahalanobis2(result.pose, result.covariance)
        if d2 > GATE_CHI2_99:
            self.ekf.covariance = self.ekf.covariance * (d2 / GATE_CHI2_99)
        self.ekf.correct(result.pose, result.covariance, None)
        return result

    def _match(self, submap: Submap, points: np.ndarray, prediction: np.ndarray,
               covariance: np.ndarray) -> tuple[MatchResult | None, bool]:
        """Best match near ``prediction``: for a scan that samples walls densely, the refinement from it
        when that fits as usual where the prediction expects it (most scans, and cheap); else a
        correlative search over three standard deviations (prior-weighted), refined. A sparse scan
        (few returns per wall) gives the refinement a narrow, rough basin that holds it near the
        prediction, so the prediction's error (a wrong wheel radius) would pass into the match: it is
        always searched, which costs little with few points."""
        tracking, resolution = self.config.tracking, self.config.submaps.resolution
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:2, :2]).max()), 0.0))
        sigma_theta = math.sqrt(max(float(covariance[2, 2]), 0.0))
        refined = refine_pose(submap.grid, points, prediction, shaped_covariance=True, wall_lines=self.dense)
        if self.dense and self._usual(refined) and _mahalanobis2(prediction, covariance, refined) <= tracking.gate_chi2:
            return refined, False
        window_xy = float(np.clip(3.0 * sigma_xy, *tracking.search_window_xy_m))
        window_theta = float(np.clip(3.0 * sigma_theta, *tracking.search_window_theta_rad))
        step = tracking.search_angular_step_rad
        result = match_scan(submap.grid, points, prediction, window_xy_m=window_xy, window_theta_rad=window_theta,
                            angular_step_rad=step, min_score=tracking.min_match_score,
                            prior_std_xy_m=tracking.search_prior_scale * max(sigma_xy, resolution),
                            prior_std_theta_rad=tracking.search_prior_scale * max(sigma_theta, step),
                            shaped_covariance=True, wall_lines=self.dense)
        if result is None or refined.score > result.score:
            result = refined
        return (result if result.score >= tracking.min_match_score else None), True

    def _match_any_heading(self, submap: Submap, points: np.ndarray, centre: np.ndarray) -> MatchResult | None:
        """Best match within the widest translation window of ``centre`` at any heading (no prior on it)."""
        tracking = self.config.tracking
        reach = tracking.search_window_xy_m[1]
        return match_scan(submap.grid, points, centre, window_xy_m=reach, window_theta_rad=math.pi,
                          angular_step_rad=tracking.search_angular_step_rad, min_score=tracking.min_match_score,
                          prior_std_xy_m=tracking.search_prior_scale * reach / 3.0, shaped_covariance=True,
                          wall_lines=self.dense)
