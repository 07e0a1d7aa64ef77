"""Global localisation from landmarks with known map positions: the robot's pose from its sightings.

A landmark map (``landmarks.csv`` of ``trundle slam``: ids, positions, standard deviations) turns
sightings into absolute fixes. One sighting of a point fixes the robot only to a circle, so
:class:`LandmarkFixer` keeps the recent sightings (those within ``window_s`` and ``window_m`` of
motion) carried into the current robot frame by odometry; once two distinct mapped landmarks are
among them, the pose that best explains them is solved for (a weighted rigid alignment: the robot
pose as the one free variable of a :class:`trundle.fusion.optimization.factor_graph.FactorGraph` whose points
are the fixed landmarks, started at the unweighted SE(2) alignment) with its covariance. The fix
then starts tracking (global localisation) or, when it disagrees with a tracked pose again and
again, reveals a kidnapping (:meth:`trundle.fusion.localization.grid_localization.Localizer.fix`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from trundle.fusion.evaluation.trajectory_errors import align_se2
from trundle.fusion.geometry import compose, relative, rotation
from trundle.fusion.optimization.factor_graph import POSITION, FactorGraph
from trundle.logs.messages import LandmarkList

MIN_LANDMARK_SIGMA_M = 0.01   # a mapped landmark is never taken as known better than this
MOTION_SIGMA_PER_M = 0.05     # odometry error (m per m driven) of a sighting carried to the present


@dataclass(frozen=True)
class LandmarkFix:
    """A pose (map frame) with its 3x3 covariance from ``landmarks`` distinct mapped landmarks, and the
    RMS of their whitened residuals (a check of the fix: about 1 when the sightings agree)."""

    pose: np.ndarray
    covariance: np.ndarray
    landmarks: int
    rms_whitened: float


def solve_pose(observed: np.ndarray, covariances: np.ndarray, mapped: np.ndarray, mapped_cov: np.ndarray
               ) -> LandmarkFix | None:
    """The robot pose seeing landmarks at ``observed`` (K, 2, robot frame, covariances (K, 2, 2)) that
    the map has at ``mapped`` (K, 2, covariances (K, 2, 2)); None for fewer than two or a degenerate set."""
    if len(observed) < 2 or float(np.ptp(mapped, axis=0).max()) < 1e-3:
        return None
    guess = align_se2(observed, mapped)
    graph = FactorGraph()
    robot = graph.add_pose(guess)
    graph.fixed_poses = set()
    for xy, cov, where, where_cov in zip(observed, covariances, mapped, mapped_cov, strict=True):
        point = graph.add_point(where)
        graph.fixed_points.add(point)
        turn = rotation(float(guess[2]))   # a mapped landmark's uncertainty, seen from the robot
        total = cov + turn.T @ where_cov @ turn
        graph.add_position(robot, point, xy, np.linalg.inv(total))
    graph.optimize()
    covariance = graph.marginal_covariances(poses=[robot])[0][0]
    if not np.all(np.isfinite(covariance)):
        return None
    chi2 = float(graph.factor_chi2(POSITION).sum())
    return LandmarkFix(graph.pose(robot), covariance, len(observed), math.sqrt(chi2 / (2 * len(observed))))


class LandmarkFixer:
    """Recent sightings carried by odometry; a :class:`LandmarkFix` once two mapped landmarks are in them.

    ``ids``, ``positions`` (M, 2) and ``sigmas`` (M, 2): the landmark map. Sightings older than
    ``window_s`` or more than ``window_m`` of driving ago are forgotten.
    """

    def __init__(self, ids: list[str], positions: np.ndarray, sigmas: np.ndarray, window_s: float = 10.0,
                 window_m: float = 3.0) -> None:
        self.map = {name: (np.asarray(p, np.float64), np.diag(np.maximum(np.asarray(s, np.float64),
                                                                        MIN_LANDMARK_SIGMA_M) ** 2))
                    for name, p, s in zip(ids, positions, sigmas, strict=True)}
        self.window_s, self.window_m = window_s, window_m
        self._recent: list[
            tuple[int, str, np.ndarray, np.ndarray, np.ndarray, float]
        ] = []  # stamp, id, odom pose, xy, cov, path
        self._path_m = 0.0
        self._last_odometry: np.ndarray | None = None
        self.unknown = 0

    def odometry(self, pose_xyt: np.ndarray) -> None:
        """The robot's odometry pose now (odom frame), for carrying sightings to the present."""
        pose = np.asarray(pose_xyt, np.float64)
        if self._last_odometry is not None:
            self._path_m += float(np.hypot(*(pose[:2] - self._last_odometry[:2])))
        self._last_odometry = pose

    def add(self, msg: LandmarkList) -> LandmarkFix | None:
        """Add one instant's sightings; the fix from every distinct mapped landmark seen recently (if two or more)."""
        here = self._last_odometry if self._last_odometry is not None else np.zeros(3)
        for o in msg.landmarks:
            if o.id not in self.map:
                self.unknown += 1
                continue
            self._recent.append((msg.stamp_ns, o.id, here.copy(), o.translation[:2].copy(), o.position_covariance(),
                                 self._path_m))
        self._recent = [r for r in self._recent if (msg.stamp_ns - r[0]) * 1e-9 <= self.window_s
                        and self._path_m - r[5] <= self.window_m]
        latest: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for _, name, odom, xy, cov, path in self._recent:   # the newest sighting of each landmark
            moved = relative(here, odom)
            turn = rotation(float(moved[2]))
            carried = compose(moved, np.array([*xy, 0.0]))[:2]
            spread = MOTION_SIGMA_PER_M * (self._path_m - path)
            latest[name] = (carried, turn @ cov @ turn.T + np.eye(2) * spread ** 2)
        if len(latest) < 2:
            return None
        names = sorted(latest)
        return solve_pose(np.array([latest[n][0] for n in names]), np.array([latest[n][1] for n in names]),
                          np.array([self.map[n][0] for n in names]), np.array([self.map[n][1] for n in names]))
