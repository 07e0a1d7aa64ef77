"""Extended Kalman filter on a planar pose: predict with odometry, correct with scan-match poses.

State (x, y, theta) in the map frame (metres, radians) with a 3x3 covariance. ``predict``
composes an odometry increment given in the robot frame; ``correct`` fuses a full pose
measurement (e.g. a scan-to-map match) and rejects it when its Mahalanobis distance to the
prediction exceeds a chi-square gate. Either input may be missing: with no odometry, call
``predict(np.zeros(3), random_walk_cov)`` so the covariance still admits motion; with no laser,
keep predicting and the covariance grows.
"""

from __future__ import annotations

import math

import numpy as np

from trundle.fusion.geometry import compose, rotation, wrap_angle

# chi-square quantile for 3 degrees of freedom at 99 %: scipy.stats.chi2.ppf(0.99, 3)
GATE_CHI2_99 = 11.344866730144373


def odometry_noise(delta_xyt, sigma_xy_m: float = 0.01, sigma_theta_rad: float = math.radians(0.5),
                   sigma_xy_per_m: float = 0.2, sigma_theta_per_m: float = math.radians(5.0),
                   sigma_theta_per_rad: float = 0.2) -> np.ndarray:
    """3x3 covariance (robot frame) of an odometry increment for :meth:`PoseEKF.predict`.

    Standard deviations: a floor per step (wheel/laser timing) plus a share per metre travelled
    and per radian turned, ``sigma_xy = sigma_xy_m + sigma_xy_per_m * d`` and
    ``sigma_theta = sigma_theta_rad + sigma_theta_per_m * d + sigma_theta_per_rad * |dtheta|``.
    """
    u = np.asarray(delta_xyt, dtype=np.float64).reshape(3)
    distance, turn = float(np.hypot(u[0], u[1])), abs(float(u[2]))
    sxy = sigma_xy_m + sigma_xy_per_m * distance
    sth = sigma_theta_rad + sigma_theta_per_m * distance + sigma_theta_per_rad * turn
    return np.diag([sxy ** 2, sxy ** 2, sth ** 2])


class PoseEKF:
    """Pose estimate with covariance; counts accepted and rejected corrections."""

    def __init__(self, pose, covariance) -> None:
        self.pose = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        self.pose[2] = wrap_angle(self.pose[2])
        self.covariance = _symmetric(np.asarray(covariance, dtype=np.float64).reshape(3, 3))
        self.accepted = 0
        self.rejected = 0
        self.last_mahalanobis2 = float("nan")

    def predict(self, delta_xyt, noise_cov) -> None:
        """Move by ``delta_xyt`` (dx, dy, dtheta in the robot frame at the start of the motion).

        ``noise_cov`` is the 3x3 covariance of that increment, also in the robot frame.
        Covariance: ``F P F^T + G Q G^T`` with ``F = d(x (+) u)/dx``, ``G = d(x (+) u)/du``.
        """
        u = np.asarray(delta_xyt, dtype=np.float64).reshape(3)
        q = np.asarray(noise_cov, dtype=np.float64).reshape(3, 3)
        c, s = np.cos(self.pose[2]), np.sin(self.pose[2])
        f = np.eye(3)
        f[0, 2] = -s * u[0] - c * u[1]
        f[1, 2] = c * u[0] - s * u[1]
        g = np.eye(3)
        g[:2, :2] = rotation(self.pose[2])
        self.pose = compose(self.pose, u)
        self.covariance = _symmetric(f @ self.covariance @ f.T + g @ q @ g.T)

    def mahalanobis2(self, pose_xyt, cov) -> float:
        """Squared Mahalanobis distance of a pose measurement from the current estimate."""
        innovation, s = self._innovation(pose_xyt, cov)
        return float(innovation @ np.linalg.solve(s, innovation))

    def correct(self, pose_xyt, cov, gate_chi2: float | None = GATE_CHI2_99) -> bool:
        """Fuse a pose measurement with covariance ``cov``; returns False (no change) if gated out.

        ``gate_chi2`` is the largest accepted squared Mahalanobis distance of the innovation
        (default: 99 % quantile of chi-square with 3 degrees of freedom); None disables gating.
        The update uses the Joseph form so the covariance stays symmetric positive definite.
        """
        r = _symmetric(np.asarray(cov, dtype=np.float64).reshape(3, 3))
        innovation, s = self._innovation(pose_xyt, r)
        d2 = float(innovation @ np.linalg.solve(s, innovation))
        self.last_mahalanobis2 = d2
        if gate_chi2 is not None and not d2 <= gate_chi2:
            self.rejected += 1
            return False
        gain = np.linalg.solve(s.T, self.covariance.T).T  # P S^-1 (S symmetric)
        self.pose = self.pose + gain @ innovation
        self.pose[2] = wrap_angle(self.pose[2])
        joseph = np.eye(3) - gain
        self.covariance = _symmetric(joseph @ self.covariance @ joseph.T + gain @ r @ gain.T)
        self.accepted += 1
        return True

    def reset(self, pose, covariance) -> None:
        """Replace the estimate (e.g. after global localisation recovered a kidnapped robot)."""
        self.pose = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        self.pose[2] = wrap_angle(self.pose[2])
        self.covariance = _symmetric(np.asarray(covariance, dtype=np.float64).reshape(3, 3))

    def _innovation(self, pose_xyt, cov) -> tuple[np.ndarray, np.ndarray]:
        z = np.asarray(pose_xyt, dtype=np.float64).reshape(3)
        innovation = z - self.pose
        innovation[2] = wrap_angle(innovation[2])
        return innovation, self.covariance + np.asarray(cov, dtype=np.float64).reshape(3, 3)


def _symmetric(matrix: np.ndarray) -> np.ndarray:
    return 0.5 * (matrix + matrix.T)
