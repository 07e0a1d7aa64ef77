"""Median and MAD scale of the last values seen: what "usual" means on this log, robust to outliers.

Thresholds that must hold on logs nobody tuned for are taken relative to these: a value is
unusual when it lies more than ``k`` robust standard deviations (``1.4826 * MAD``, the normal
distribution's) from the median of the recent ones.
"""

from __future__ import annotations

import math
from bisect import bisect_left, insort
from collections import deque

import numpy as np

MAD_TO_SIGMA = 1.4826  # 1 / Phi^-1(3/4): MAD of a normal distribution in standard deviations


def _middle(low: float, high: float) -> float:
    """numpy's median of the two middle values (its mean of them: a sum from 0.0, halved)."""
    return (0.0 + (low + high)) / 2


def _kth_deviation(values: list[float], centre: float, k: int) -> float:
    """The ``k``-th smallest (0-based) of ``|v - centre|`` over the sorted ``values``, by bisection: the
    deviations fall towards ``centre`` on its left and rise on its right, two sorted runs to select from."""
    split = bisect_left(values, centre)
    left, right = split, len(values) - split   # left run: values[split - 1], values[split - 2], ...
    take = k + 1
    lo, hi = max(0, take - right), min(take, left)
    while lo < hi:   # the fewest from the left run such that the next one there is no smaller than the right's last
        i = (lo + hi) // 2
        if abs(values[split - 1 - i] - centre) < abs(values[split + take - i - 1] - centre):
            lo = i + 1
        else:
            hi = i
    i, j = lo, take - lo
    best = -math.inf
    if i:
        best = abs(values[split - i] - centre)
    if j:
        best = max(best, abs(values[split + j - 1] - centre))
    return best


class RobustWindow:
    """The last ``size`` values (scalars or fixed-length vectors) with their median and robust scale.

    Each component's values are kept sorted (a value in and the oldest out by bisection), so a median is
    read off the middle and a MAD selected by bisection (:func:`_kth_deviation`), where sorting the
    window again for each (numpy's median of a 1,000-value ring buffer, the odometry check's, each scan)
    took 22 us. Results are numpy's to the bit (``np.median`` of the same values; a window holding a NaN
    or an infinity is handed to numpy as it is)."""

    def __init__(self, size: int = 50) -> None:
        self.size = int(size)
        self._shape: tuple[int, ...] | None = None   # of the values, set by the first
        self._values: deque[list[float]] = deque()   # components of each value held, oldest first
        self._sorted: list[list[float]] = []   # per component, its finite values held, ascending
        self._odd = 0   # values held with a NaN or infinite component: numpy's median takes those windows
        self._cache: dict[bool | str, np.ndarray] = {}   # median and scales until the next value

    def __len__(self) -> int:
        return len(self._values)

    def add(self, value: float | np.ndarray) -> None:
        value = np.asarray(value, np.float64)
        if self._shape is None:
            self._shape = value.shape
            self._sorted = [[] for _ in range(value.size)]
        elif value.shape != self._shape:   # as the ring buffer took it: broadcast to the first value's shape
            value = np.broadcast_to(value, self._shape)
        components = value.reshape(-1).tolist()
        if len(self._values) == self.size:
            oldest = self._values.popleft()
            for held, v in zip(self._sorted, oldest, strict=True):
                if math.isfinite(v):
                    del held[bisect_left(held, v)]
            self._odd -= not all(map(math.isfinite, oldest))
        self._values.append(components)
        for held, v in zip(self._sorted, components, strict=True):
            if math.isfinite(v):
                insort(held, v)
        self._odd += not all(map(math.isfinite, components))
        self._cache.clear()

    def _array(self) -> np.ndarray:
        """The values held as numpy's median takes them (count, *shape)."""
        assert self._shape is not None
        return np.array(list(self._values), np.float64).reshape(len(self._values), *self._shape)

    def _shaped(self, components: list[float]) -> np.ndarray:
        assert self._shape is not None
        if not self._shape:
            return np.float64(components[0])  # type: ignore[return-value]   # as np.median of scalars gives it
        return np.array(components, np.float64).reshape(self._shape)

    def median(self) -> np.ndarray:
        """Median per component (NaN while empty)."""
        if not self._values:
            return np.asarray(np.nan)
        if "median" not in self._cache:
            if self._odd:
                self._cache["median"] = np.median(self._array(), axis=0)
            else:
                n = len(self._values)
                half = n // 2
                self._cache["median"] = self._shaped(
                    [0.0 + held[half] if n % 2 else _middle(held[half - 1], held[half]) for held in self._sorted])
        return self._cache["median"].copy()

    def scale(self, about_zero: bool = False) -> np.ndarray:
        """Robust standard deviation ``1.4826 * median(|v - median|)`` per component (NaN while empty).

        ``about_zero`` measures the spread about 0 instead of the median (``1.4826 * median(|v|)``):
        a constant bias then counts as spread, as it should for errors that ought to be zero.
        """
        if not self._values:
            return np.asarray(np.nan)
        if about_zero not in self._cache:
            if self._odd:
                centre = 0.0 if about_zero else self.median()
                self._cache[about_zero] = MAD_TO_SIGMA * np.median(np.abs(self._array() - centre), axis=0)
            else:
                n = len(self._values)
                half = n // 2
                centres = [0.0] * len(self._sorted) if about_zero else np.reshape(self.median(), -1).tolist()
                mads = []
                for held, centre in zip(self._sorted, centres, strict=True):
                    if n % 2:
                        mad = 0.0 + _kth_deviation(held, centre, half)
                    else:
                        mad = _middle(_kth_deviation(held, centre, half - 1), _kth_deviation(held, centre, half))
                    mads.append(MAD_TO_SIGMA * mad)
                self._cache[about_zero] = self._shaped(mads)
        return self._cache[about_zero].copy()
