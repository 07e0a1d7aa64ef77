"""Simulated wheel odometry from a reference trajectory: systematic drift plus seeded random noise.

Used to feed a SLAM run with odometry whose error is known when only corrected poses exist (the
GMapping-corrected Intel log). Each step between consecutive reference poses, of length ``s``
and turn ``dtheta``, becomes an odometry step with

- translation scaled by ``1 + scale_error`` (systematic) times ``1 + N(0, scale_noise)``,
- heading ``dtheta + heading_drift_rad_per_m * s`` (systematic) ``+ N(0, heading_noise_rad_per_sqrt_m^2 * s
  + (turn_noise * dtheta)^2)``,

and the steps are chained from the first reference pose, so the error grows with distance like
real dead reckoning does.
"""

from __future__ import annotations

import math

import numpy as np

from trundle.fusion.geometry import relative, wrap_angle


def drifting_odometry(reference: np.ndarray, *, scale_error: float = 0.05,
                      heading_drift_rad_per_m: float = math.radians(2.0), scale_noise: float = 0.02,
                      heading_noise_rad_per_sqrt_m: float = math.radians(0.5), turn_noise: float = 0.02,
                      seed: int = 0) -> np.ndarray:
    """Odometry poses (N, 3) for reference poses (N, 3), starting at ``reference[0]``; see the module doc."""
    reference = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    if len(reference) < 2:
        return reference.copy()
    rng = np.random.default_rng(seed)
    steps = relative(reference[:-1], reference[1:])
    length = np.hypot(steps[:, 0], steps[:, 1])
    scale = (1.0 + scale_error) * (1.0 + rng.normal(0.0, scale_noise, len(steps)))
    heading_sigma = np.sqrt(heading_noise_rad_per_sqrt_m ** 2 * length + (turn_noise * steps[:, 2]) ** 2)
    noisy = np.column_stack(
        [
            steps[:, 0] * scale,
            steps[:, 1] * scale,
            steps[:, 2] + heading_drift_rad_per_m * length + rng.normal(0.0, 1.0, len(steps)) * heading_sigma,
        ]
    )
    heading = reference[0, 2] + np.concatenate([[0.0], np.cumsum(noisy[:, 2])])
    c, s = np.cos(heading[:-1]), np.sin(heading[:-1])
    moves = np.column_stack([c * noisy[:, 0] - s * noisy[:, 1], s * noisy[:, 0] + c * noisy[:, 1]])
    xy = reference[0, :2] + np.vstack([[0.0, 0.0], np.cumsum(moves, axis=0)])
    return np.column_stack([xy, wrap_angle(heading)])
