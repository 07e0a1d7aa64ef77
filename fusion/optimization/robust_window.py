"""Median and MAD scale of the last values seen: what "usual" means on this log, robust to outliers.

Thresholds that must hold on logs nobody tuned for are taken relative to these: a value is
unusual when it lies more than ``k`` robust standard deviations (``1.4826 * MAD``, the normal
distribution's) from the median of the recent ones.
"""

from __future__ import annotations

import numpy as np

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD of a normal distribution in standard deviations


class RobustWindow:
    """The last ``size`` values (scalars or fixed-length vectors) with their median and robust scale.

    The values are kept in one ring buffer (``size`` rows, laid out on the first value): the medians
    read it as it is (order does not matter to a median), where stacking a deque of arrays again for
    every median cost 0.3 ms a scan in the daemon's odometry check (1,000 values)."""

    def __init__(self, size: int = 50) -> None:
        self.size = int(size)
        self._buffer: np.ndarray | None = None
        self._count = 0   # values added so far; the newest is at (count - 1) % size
        self._cache: dict[bool | str, np.ndarray] = {}   # median and scales until the next value

    def __len__(self) -> int:
        return min(self._count, self.size)

    def add(self, value: float | np.ndarray) -> None:
        value = np.asarray(value, np.float64)
        if self._buffer is None:
            self._buffer = np.empty((self.size, *value.shape))
        self._buffer[self._count % self.size] = value
        self._count += 1
        self._cache.clear()

    def _values(self) -> np.ndarray:
        assert self._buffer is not None
        return self._buffer[:len(self)]

    def median(self) -> np.ndarray:
        """Median per component (NaN while empty)."""
        if not self._count:
            return np.asarray(np.nan)
        if "median" not in self._cache:
            self._cache["median"] = np.median(self._values(), axis=0)
        return self._cache["median"].copy()

    def scale(self, about_zero: bool = False) -> np.ndarray:
        """Robust standard deviation ``1.4826 * median(|v - median|)`` per component (NaN while empty).

        ``about_zero`` measures the spread about 0 instead of the median (``1.4826 * median(|v|)``):
        a constant bias then counts as spread, as it should for errors that ought to be zero.
        """
        if not self._count:
            return np.asarray(np.nan)
        if about_zero not in self._cache:
            centre = 0.0 if about_zero else self.median()
            self._cache[about_zero] = MAD_TO_SIGMA * np.median(np.abs(self._values() - centre), axis=0)
        return self._cache[about_zero].copy()
