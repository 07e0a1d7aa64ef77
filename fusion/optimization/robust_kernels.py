"""Robust kernels (M-estimators) of squared whitened errors: every robust cost in the tree is one of these.

A kernel maps a squared whitened error ``s = e^T I e`` (chi2 units, dimensionless) to a loss
``rho(s)`` that grows more slowly than ``s`` beyond the kernel's width ``k`` (in whitened units,
so ``k^2`` in chi2 units), so that an outlier pulls less. Iteratively reweighted least squares
minimises ``sum rho(s)`` by weighting each error's normal-equation rows with ``w = rho'(s)``:

- ``None``: least squares, ``rho = s``, ``w = 1``;
- ``"huber"``: ``rho = s`` for ``s <= k^2``, else ``2 k sqrt(s) - k^2`` (linear in ``|e|``),
  ``w = min(1, k / sqrt(s))``;
- ``"cauchy"``: ``rho = k^2 log(1 + s / k^2)``, ``w = 1 / (1 + s / k^2)``.
"""

from __future__ import annotations

import numpy as np

ROBUST_KERNELS = (None, "huber", "cauchy")
Kernel = tuple[str | None, float]   # kernel name and width k (whitened units)


def check_kernel(kernel: str | None) -> None:
    """Raise ValueError unless ``kernel`` is one of :data:`ROBUST_KERNELS`."""
    if kernel not in ROBUST_KERNELS:
        raise ValueError(f"unknown robust kernel {kernel!r}; expected one of {ROBUST_KERNELS}")


def robust_loss(squared: np.ndarray, kernel: str | None, width: float) -> tuple[np.ndarray, np.ndarray]:
    """Loss ``rho(s)`` and IRLS weight ``rho'(s)`` of squared whitened errors ``s`` (element-wise).

    ``width`` is the kernel's ``k`` in whitened units; ignored without a kernel.
    """
    s = np.asarray(squared, dtype=np.float64)
    check_kernel(kernel)
    if kernel is None:
        return s, np.ones_like(s)
    k2 = width * width
    if kernel == "huber":
        root = np.sqrt(np.maximum(s, 1e-300))
        inlier = s <= k2
        return np.where(inlier, s, 2.0 * width * root - k2), np.where(inlier, 1.0, width / root)
    return k2 * np.log1p(s / k2), 1.0 / (1.0 + s / k2)
