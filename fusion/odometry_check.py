"""Odometry is evidence, not truth: each increment is tested against the scan match.

Wheel odometry fails in ways no noise model covers: a heading glitch of twenty degrees in half a
second, a wheel spinning on a smooth floor, a reading paired with the other wheel's from another
instant. The laser sees the same motion, so each odometry increment is compared with the scan
match of that step: their disagreement ``odometry_pose^-1 (+) match_pose`` (robot frame) is
normalised by the spread of the recent disagreements on this log (robust: MAD about zero) plus
the match's own covariance, so a direction the scan does not constrain (a corridor's axis)
carries no weight. An increment whose squared normalised disagreement exceeds the chi-square
99.9 % quantile is an outlier: the laser contradicts it. Until enough disagreements are known the
odometry noise model of the increment stands in for their spread.
"""

from __future__ import annotations

import numpy as np

from trundle.fusion.robust_window import RobustWindow

CHI2_3DOF_999 = 16.266236196238129  # scipy.stats.chi2.ppf(0.999, 3)


class OdometryCheck:
    """Robust test of odometry increments against scan matches; ``floor_sigma`` (x m, y m, theta rad)
    is the least spread assumed (the matcher's own precision)."""

    def __init__(self, floor_sigma: tuple[float, float, float], history: int = 50, warmup: int = 10) -> None:
        self.floor_sigma = np.asarray(floor_sigma, np.float64)
        self.warmup = int(warmup)
        self._disagreements = RobustWindow(history)

    def spread(self, prior_covariance: np.ndarray) -> np.ndarray:
        """Covariance (3x3, robot frame) of a normal disagreement: learned, or ``prior_covariance`` at first."""
        if len(self._disagreements) < self.warmup:
            return np.asarray(prior_covariance, np.float64) + np.diag(self.floor_sigma ** 2)
        return np.diag(np.maximum(self._disagreements.scale(about_zero=True), self.floor_sigma) ** 2)

    def distance2(self, disagreement: np.ndarray, match_covariance: np.ndarray, prior_covariance: np.ndarray) -> float:
        """Squared normalised disagreement of one increment with its match."""
        e = np.asarray(disagreement, np.float64)
        covariance = self.spread(prior_covariance) + np.asarray(match_covariance, np.float64)
        return float(e @ np.linalg.solve(covariance, e))

    def is_outlier(self, disagreement: np.ndarray, match_covariance: np.ndarray, prior_covariance: np.ndarray) -> bool:
        """Does the laser contradict this increment?"""
        return self.distance2(disagreement, match_covariance, prior_covariance) > CHI2_3DOF_999

    def accept(self, disagreement: np.ndarray) -> None:
        """Record the disagreement of an increment that was used."""
        self._disagreements.add(disagreement)
