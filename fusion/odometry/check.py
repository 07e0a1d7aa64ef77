"""Odometry is evidence, not truth: each increment is tested against the scan match, and its noise learned.

Wheel odometry fails in ways no noise model covers: a heading glitch of twenty degrees in half a
second, a wheel spinning on a smooth floor, a reading paired with the other wheel's from another
instant. The laser sees the same motion, so each odometry increment is compared with the scan
match of that step: their disagreement ``e = odometry_pose^-1 (+) match_pose`` (robot frame).

How far odometry and laser normally disagree is learned from the log: the configured noise model
``Q(u)`` (a floor plus a share per metre and per radian, :func:`trundle.fusion.odometry.ekf.odometry_noise`)
gives the shape, and a factor per axis, ``kappa^2``, the level: the median of ``e^2 / Q`` over the
recent increments that were used, divided by the median of a squared standard normal (so a
Gaussian disagreement of variance ``kappa^2 Q`` gives ``kappa^2``). The disagreement holds the
match's error too, so the learned noise errs on the safe side. ``kappa^2 Q(u)`` is the odometry
noise a filter should use on this log (a 40 Hz laser on good wheels: about a tenth of the
model's standard deviation). An increment whose squared Mahalanobis disagreement under
``kappa^2 Q(u) + R`` (``R`` the match's covariance, large along a corridor's axis, so that
direction weighs little) exceeds the chi-square 99.9 % quantile is an outlier: the laser
contradicts it. Until ``warmup`` increments are known, ``kappa = 1`` (the model as configured).

One increment's disagreement cannot show an error that repeats: a wrong wheel radius or a drifting
heading adds the same small amount at every step, and a filter that takes that for independent
noise of that size trusts the wheels far more than they deserve over a metre. So the same ratio is
also taken over the sum of ``span`` consecutive used increments (the sum of their disagreements
against the sum of their model variances): independent noise gives the same ``kappa^2``, an error
that repeats up to ``span`` times more, and the level used is the larger of the two. Sums of
overlapping spans are far from independent, so their median is taken over ``span`` times the
history (at 40 Hz, the last 25 s) to be as steady as the per-increment one.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from trundle.fusion.optimization.robust_window import RobustWindow

CHI2_3DOF_999 = 16.266236196238129  # scipy.stats.chi2.ppf(0.999, 3)
CHI2_1DOF_MEDIAN = 0.454936423119572  # scipy.stats.chi2.ppf(0.5, 1): median of a squared standard normal
MIN_KAPPA2 = 1e-4  # odometry is never taken as more than 100 times better than its configured model


class OdometryCheck:
    """Robust test of odometry increments against scan matches, and the odometry noise level they show."""

    def __init__(self, history: int = 100, warmup: int = 10, span: int = 10) -> None:
        self.warmup = int(warmup)
        self._ratios = RobustWindow(history)
        self._span_ratios = RobustWindow(history * span)
        self._recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=span)
        self._kappa2: np.ndarray | None = None  # the medians, kept until the next accepted increment

    def kappa2(self) -> np.ndarray:
        """Learned noise level per axis (x, y, theta) relative to the configured model (1 until warmed up)."""
        if len(self._ratios) < self.warmup:
            return np.ones(3)
        if self._kappa2 is None:
            level = self._ratios.median()
            if len(self._span_ratios) >= self.warmup:
                level = np.maximum(level, self._span_ratios.median())
            self._kappa2 = np.maximum(level, MIN_KAPPA2)
        return self._kappa2.copy()

    def noise(self, model_covariance: np.ndarray) -> np.ndarray:
        """The odometry noise (3x3, robot frame) of an increment whose configured noise is ``model_covariance``."""
        scale = np.sqrt(self.kappa2())
        return model_covariance * np.outer(scale, scale)

    def distance2(self, disagreement: np.ndarray, match_covariance: np.ndarray,
                  model_covariance: np.ndarray) -> float:
        """Squared Mahalanobis disagreement of one increment with its match (both covariances robot frame)."""
        e = np.asarray(disagreement, np.float64)
        covariance = self.noise(model_covariance) + np.asarray(match_covariance, np.float64)
        return float(e @ np.linalg.solve(covariance, e))

    def is_outlier(self, disagreement: np.ndarray, match_covariance: np.ndarray, model_covariance: np.ndarray) -> bool:
        """Does the laser contradict this increment?"""
        return self.distance2(disagreement, match_covariance, model_covariance) > CHI2_3DOF_999

    def accept(self, disagreement: np.ndarray, match_covariance: np.ndarray, model_covariance: np.ndarray) -> None:
        """Learn from an increment that was used."""
        e = np.asarray(disagreement, np.float64)
        variance = np.maximum(np.diag(model_covariance), 1e-300)
        self._ratios.add(e * e / CHI2_1DOF_MEDIAN / variance)
        self._kappa2 = None
        self._recent.append((e, variance))
        if len(self._recent) == self._recent.maxlen:
            total = np.sum([d for d, _ in self._recent], axis=0)
            self._span_ratios.add(total * total / CHI2_1DOF_MEDIAN / np.sum([v for _, v in self._recent], axis=0))

    def interrupt(self) -> None:
        """An increment was not used (rejected): the next sum starts after it."""
        self._recent.clear()
