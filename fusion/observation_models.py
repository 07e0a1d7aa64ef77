"""Observation models of a point landmark or another pose seen from a planar pose, with their Jacobians.

A robot at pose ``(x, y, theta)`` (map frame) sees a point ``(lx, ly)`` at range
``r = |l - t|`` (m) and bearing ``b = atan2(ly - y, lx - x) - theta`` (rad, counter-clockwise from
the robot's x axis, wrapped to [-pi, pi)), or at the position ``R(theta)^T (l - t)`` in its own
frame. Every function takes a batch: poses (N, 3) and points (N, 2) row by row. The inverse model
places a new landmark from one sighting (EKF-SLAM's augmentation, a graph's initial guess).
A pose ``x_j`` measured as ``z`` in the frame of pose ``x_i`` (odometry, a scan match, a loop
closure) has the g2o ``EDGE_SE2`` error ``t2v(z^-1 (x_i^-1 x_j))`` (:func:`between_error`).
"""

from __future__ import annotations

import numpy as np

from trundle.fusion.geometry import wrap_angle


def range_bearing(poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted ``(range, bearing)`` (N, 2) and its Jacobians (N, 2, 3) by the pose, (N, 2, 2) by the point."""
    x, lm = np.asarray(poses, np.float64).reshape(-1, 3), np.asarray(points, np.float64).reshape(-1, 2)
    dx, dy = lm[:, 0] - x[:, 0], lm[:, 1] - x[:, 1]
    q = np.maximum(dx * dx + dy * dy, 1e-18)
    r = np.sqrt(q)
    z = np.stack([r, wrap_angle(np.arctan2(dy, dx) - x[:, 2])], axis=1)
    d_point = np.stack([np.stack([dx / r, dy / r], 1), np.stack([-dy / q, dx / q], 1)], 1)
    d_pose = np.zeros((len(x), 2, 3))
    d_pose[:, :, :2] = -d_point
    d_pose[:, 1, 2] = -1.0
    return z, d_pose, d_point


def relative_position(poses: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted position ``R^T (l - t)`` (N, 2) in the robot frame and its Jacobians by the pose and the point."""
    x, lm = np.asarray(poses, np.float64).reshape(-1, 3), np.asarray(points, np.float64).reshape(-1, 2)
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    dx, dy = lm[:, 0] - x[:, 0], lm[:, 1] - x[:, 1]
    z = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)
    rt = np.stack([np.stack([c, s], 1), np.stack([-s, c], 1)], 1)
    d_pose = np.zeros((len(x), 2, 3))
    d_pose[:, :, :2] = -rt
    d_pose[:, 0, 2] = z[:, 1]
    d_pose[:, 1, 2] = -z[:, 0]
    return z, d_pose, rt


def point_from_range_bearing(poses: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inverse model: map points (N, 2) seen at ``z = (range, bearing)`` (N, 2) from ``poses``, and
    the Jacobians (N, 2, 3) by the pose and (N, 2, 2) by the measurement."""
    x, z = np.asarray(poses, np.float64).reshape(-1, 3), np.asarray(z, np.float64).reshape(-1, 2)
    angle = x[:, 2] + z[:, 1]
    c, s = np.cos(angle), np.sin(angle)
    points = np.stack([x[:, 0] + z[:, 0] * c, x[:, 1] + z[:, 0] * s], axis=1)
    d_pose = np.zeros((len(x), 2, 3))
    d_pose[:, 0, 0] = d_pose[:, 1, 1] = 1.0
    d_pose[:, 0, 2] = -z[:, 0] * s
    d_pose[:, 1, 2] = z[:, 0] * c
    d_z = np.stack([np.stack([c, -z[:, 0] * s], 1), np.stack([s, z[:, 0] * c], 1)], 1)
    return points, d_pose, d_z


def between_error(poses_i: np.ndarray, poses_j: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors ``t2v(z^-1 (x_i^-1 x_j))`` (N, 3) of poses ``x_j`` measured as ``z`` in the frame of poses ``x_i``
    (metres, metres, radians wrapped to [-pi, pi)) and their Jacobians (N, 3, 3) by ``x_i`` and by ``x_j``."""
    xi, xj = np.asarray(poses_i, np.float64).reshape(-1, 3), np.asarray(poses_j, np.float64).reshape(-1, 3)
    z = np.asarray(z, np.float64).reshape(-1, 3)
    ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    # relative pose x_i^-1 x_j
    rx, ry = ci * dx + si * dy, -si * dx + ci * dy
    # z^-1 (x_i^-1 x_j): rotate (r - t_z) by -theta_z
    ux, uy = rx - z[:, 0], ry - z[:, 1]
    e = np.stack([cz * ux + sz * uy, -sz * ux + cz * uy,
                  wrap_angle(xj[:, 2] - xi[:, 2] - z[:, 2])], axis=1)
    # R_z^T R_i^T, shape (N, 2, 2)
    c, s = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
    rot = np.stack([np.stack([c, s], 1), np.stack([-s, c], 1)], 1)
    # derivative of R_z^T R_i^T (t_j - t_i) with respect to theta_i
    d_theta = np.stack([-s * dx + c * dy, -c * dx - s * dy], 1)
    n = len(xi)
    jac_i = np.zeros((n, 3, 3))
    jac_j = np.zeros((n, 3, 3))
    jac_i[:, :2, :2] = -rot
    jac_i[:, :2, 2] = d_theta
    jac_i[:, 2, 2] = -1.0
    jac_j[:, :2, :2] = rot
    jac_j[:, 2, 2] = 1.0
    return e, jac_i, jac_j
