"""Point-to-line ICP between two point sets (scans, or a scan and a submap's occupied cells).

Each point of the moving set is paired with its nearest reference point (a k-d tree, SciPy) and
its error is the distance to the reference's local line, whose normal comes from the principal
axes of the reference's neighbours (Censi's PLICP error, Chen and Medioni's point-to-plane in
2-D). A robust Huber Levenberg-Marquardt refinement (the scan matcher's :func:`solve_pose`, on the
one core) follows each pairing until the pose settles. It
is a second matcher, independent of the grid: used to verify loop closures and as a baseline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from trundle.fusion.geometry import rotation
from trundle.fusion.matching.scan_matching import match_covariance, solve_pose
from trundle.fusion.optimization.robust_kernels import robust_loss


@dataclass(frozen=True)
class IcpResult:
    """Pose of the moving set in the reference frame, its covariance, fit quality and effort."""

    pose: np.ndarray
    covariance: np.ndarray
    residual_m: float
    inlier_fraction: float
    iterations: int
    converged: bool


class LineReference:
    """Reference points with a k-d tree and a line normal per point (from ``neighbours`` nearest points).

    ``flatness`` is ``1 - lambda_min / lambda_max`` of each neighbourhood (1 on a straight wall,
    0 in isotropic clutter); points below ``min_flatness`` fall back to point-to-point pairing.
    """

    def __init__(self, points: np.ndarray, neighbours: int = 5, min_flatness: float = 0.8) -> None:
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(self.points) < 3:
            raise ValueError("a reference needs at least 3 points")
        self.tree = cKDTree(self.points)
        k = min(neighbours, len(self.points))
        _, index = self.tree.query(self.points, k=k)
        near = self.points[index] - self.points[index].mean(axis=1, keepdims=True)
        sxx, syy = (near[..., 0] ** 2).mean(axis=1), (near[..., 1] ** 2).mean(axis=1)
        sxy = (near[..., 0] * near[..., 1]).mean(axis=1)
        angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the largest spread (the line)
        self.normals = np.stack([-np.sin(angle), np.cos(angle)], axis=1)
        spread = np.sqrt(((sxx - syy) / 2.0) ** 2 + sxy ** 2)
        mean = (sxx + syy) / 2.0
        self.flatness = np.where(mean + spread > 0, 1.0 - (mean - spread) / np.maximum(mean + spread, 1e-300), 0.0)
        self.is_line = self.flatness >= min_flatness


def icp(reference: LineReference | np.ndarray, points_xy: np.ndarray, initial_pose_xyt: np.ndarray, *,
        max_correspondence_m: float = 0.5, huber_m: float = 0.05, inlier_m: float = 0.1, max_iterations: int = 30,
        tolerance_m: float = 1e-4, min_std_xy_m: float = 0.01,
        min_std_theta_rad: float = math.radians(0.25)) -> IcpResult:
    """Align ``points_xy`` (moving frame) to ``reference`` starting from ``initial_pose_xyt``.

    Pairs farther apart than ``max_correspondence_m`` are ignored; residuals beyond ``huber_m``
    are down-weighted; ``inlier_m`` defines the reported inlier fraction and residual.
    Stops when a re-pairing moves the pose by less than ``tolerance_m`` (and rad).
    """
    ref = reference if isinstance(reference, LineReference) else LineReference(reference)
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    pose = np.asarray(initial_pose_xyt, dtype=np.float64).copy()
    converged = False
    iterations = 0
    state: tuple = (np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool))
    for _ in range(max_iterations):
        iterations += 1
        moved = points @ rotation(pose[2]).T + pose[:2]
        distance, index = ref.tree.query(moved, distance_upper_bound=max_correspondence_m)
        paired = np.isfinite(distance)
        index = np.where(paired, index, 0)
        targets, normals, lines = ref.points[index], ref.normals[index], ref.is_line[index]

        def evaluate(trial: np.ndarray, targets: np.ndarray = targets, normals: np.ndarray = normals,
                     lines: np.ndarray = lines, paired: np.ndarray = paired
                     ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            rot = rotation(trial[2])
            q = points @ rot.T + trial[:2]
            dq_dtheta = points @ np.array([[-rot[1, 0], -rot[0, 0]], [rot[0, 0], -rot[1, 0]]]).T
            delta = q - targets
            # point-to-line where the reference is a line, else the point-to-point distance
            along = np.einsum("ij,ij->i", delta, normals)
            dist = np.where(lines, along, np.hypot(delta[:, 0], delta[:, 1]))
            safe = np.maximum(np.hypot(delta[:, 0], delta[:, 1]), 1e-12)
            direction = np.where(lines[:, None], normals, delta / safe[:, None])
            jac = np.column_stack([direction, np.einsum("ij,ij->i", direction, dq_dtheta)])
            residual = np.where(paired, dist, 0.0)
            jac[~paired] = 0.0
            loss, weight = robust_loss(residual * residual, "huber", huber_m)
            return float(loss.sum()), residual, jac, weight, paired

        previous = pose
        pose, _, state = solve_pose(evaluate, pose, 10)
        step = np.abs(pose - previous)
        if step[0] < tolerance_m and step[1] < tolerance_m and step[2] < tolerance_m:
            converged = True
            break
    residual, jac, weight, paired = state
    inliers = paired & (np.abs(residual) <= inlier_m)
    count = int(inliers.sum())
    covariance = match_covariance(jac, residual, weight, inliers, min_std_xy_m, min_std_theta_rad)
    return IcpResult(pose, covariance, float(np.mean(np.abs(residual[inliers]))) if count else float("nan"),
                     count / max(len(points), 1), iterations, converged)
