"""What the grid SLAM did over a run: counts of its local trajectory builder and its back end."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SlamStats:
    """Scans, keyframes and their matches (local builder); loop closures and optimisations (back end)."""

    scans: int = 0
    keyframes: int = 0
    matched: int = 0
    searched: int = 0
    gated_out: int = 0
    odometry_only: int = 0
    motion_model_only: int = 0
    odometry_rejected: int = 0
    loop_attempts: int = 0
    loop_closures: int = 0
    loop_rejected: int = 0
    loop_unverified: int = 0
    loop_paired: int = 0
    loop_inconsistent: int = 0
    optimizations: int = 0
    scores: list[float] = field(default_factory=list)
    residuals: list[float] = field(default_factory=list)


def summary(values: list[float]) -> dict[str, float]:
    """Mean, median, min, 5th percentile and max of the finite ``values`` ({} if there are none)."""
    if not values:
        return {}
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    return {"mean": float(a.mean()), "median": float(np.median(a)), "min": float(a.min()),
            "p05": float(np.percentile(a, 5)), "max": float(a.max())} if a.size else {}
