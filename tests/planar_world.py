"""Polygon worlds for SLAM tests (known geometry, known poses), ray cast by the world simulator."""

from __future__ import annotations

import math

import numpy as np

from trundle.logs.messages import LaserScan
from trundle.tools.sim.world import cast_rays

# Walls sit off the 5 cm / 2 cm cell lattice (as real walls do), so no reading lies on a cell edge.
_OFF = np.array([0.0123, 0.0271, 0.0123, 0.0271])

# A 10 m x 7 m room with a stub wall, a pillar and an L-shaped partition: no symmetry to fool a matcher.
ROOM = _OFF + np.array([
    [-5.0, -3.0, 5.0, -3.0], [5.0, -3.0, 5.0, 4.0], [5.0, 4.0, -5.0, 4.0], [-5.0, 4.0, -5.0, -3.0],
    [1.0, -3.0, 1.0, -0.5], [-2.0, 2.0, 0.3, 2.6], [-3.5, -1.0, -3.0, -1.0], [-3.0, -1.0, -3.0, -1.5],
    [-3.0, -1.5, -3.5, -1.5], [-3.5, -1.5, -3.5, -1.0], [3.0, 1.0, 4.0, 1.0], [3.0, 1.0, 3.0, 2.5],
])

# A 30 m long corridor 2 m wide with no features along it: scan matching is blind along x.
CORRIDOR = _OFF + np.array([[-15.0, -1.0, 15.0, -1.0], [-15.0, 1.0, 15.0, 1.0]])


def cast(walls: np.ndarray, pose: np.ndarray, angles: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """Exact ranges (m) from ``pose`` along robot-frame ``angles`` to the nearest wall segment; inf if none."""
    x, y, theta = pose
    return cast_rays(walls, (x, y), theta + np.asarray(angles, dtype=np.float64), max_range).distance


def scan(walls: np.ndarray, pose: np.ndarray, *, beams: int = 360, fov: float = 2 * math.pi, noise_m: float = 0.0,
         seed: int = 0, stamp_ns: int = 0, max_range: float = 30.0) -> LaserScan:
    """A LaserScan seen from ``pose`` with Gaussian range noise; +inf where nothing is within ``max_range``."""
    increment = fov / beams
    angle_min = -fov / 2 if fov < 2 * math.pi else -math.pi
    angles = angle_min + increment * np.arange(beams)
    ranges = cast(walls, np.asarray(pose, dtype=np.float64), angles, max_range)
    ranges = ranges + np.random.default_rng(seed).normal(0.0, noise_m, beams) * np.isfinite(ranges)
    return LaserScan(stamp_ns, "laser", angle_min, angle_min + increment * (beams - 1), increment, 0.0, 0.1,
                     0.05, max_range, ranges)
