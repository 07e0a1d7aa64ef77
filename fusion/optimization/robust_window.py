"""Median and MAD scale of the last values seen: what "usual" means on this log, robust to outliers.

Thresholds that must hold on logs nobody tuned for are taken relative to these: a value is
unusual when it lies more than ``k`` robust standard deviations (``1.4826 * MAD``, the normal
distribution's) from the median of the recent ones.
"""

from __future__ import annotations

from collections import deque

import numpy as np

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD of a normal distribution in standard deviations


class RobustWindow:
    """The last ``size`` values (scalars or fixed-length vectors) with their median and robust scale."""

    def __init__(self, size: int = 50) -> None:
        self._values: deque[np.ndarray] = deque(maxlen=size)
        self._cache: dict[bool | str, np.ndarray] = {}   # median and scales until the next value

    def __len__(self) -> int:
        return len(self._values)

    def add(self, value: float | np.ndarray) -> None:
        self._values.append(np.asarray(value, np.float64))
        self._cache.clear()

    def median(self) -> np.ndarray:
        """Median per component (NaN while empty)."""
        if not self._values:
            return np.asarray(np.nan)
        if "median" not in self._cache:
            self._cache["median"] = np.median(np.array(self._values), axis=0)
        return self._cache["median"].copy()

    def scale(self, about_zero: bool = False) -> np.ndarray:
        """Robust standard deviation ``1.4826 * median(|v - median|)`` per component (NaN while empty).

        ``about_zero`` measures the spread about 0 instead of the median (``1.4826 * median(|v|)``):
        a constant bias then counts as spread, as it should for errors that ought to be zero.
        """
        if not self._values:
            return np.asarray(np.nan)
        if about_zero not in self._cache:
            centre = 0.0 if about_zero else self.median()
            self._cache[about_zero] = MAD_TO_SIGMA * np.median(np.abs(np.array(self._values) - centre), axis=0)
        return self._cache[about_zero].copy()
