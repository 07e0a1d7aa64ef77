"""Unwrapping of position counters of any width or range into continuous integer counts.

A device counter that wraps modulo ``modulus`` (2**16, 2**32, a CiA 406 total measuring range,
...) is turned into an unbounded count by taking every step as the shortest way round:
the step between two readings must stay below ``modulus / 2`` in magnitude, i.e. the wheel must
not turn half the counter range between two frames. Signed and unsigned counters unwrap alike.
"""

from __future__ import annotations

import numpy as np


def wrap_delta(new: int | np.ndarray, old: int | np.ndarray, modulus: int) -> int | np.ndarray:
    """Signed step from ``old`` to ``new`` on a counter wrapping at ``modulus``, in
    ``[-modulus // 2, modulus - modulus // 2)``."""
    half = modulus // 2
    return (new - old + half) % modulus - half


def unwrap(raw: np.ndarray, modulus: int, start: int | None = None) -> np.ndarray:
    """Continuous int64 counts from a sequence of wrapped readings.

    Parameters
    ----------
    raw : integer readings in order of arrival.
    modulus : counter period (``2**bits`` or the device's measuring range), > 1.
    start : the continuous value of ``raw[0]``; default ``raw[0]`` itself.
    """
    if modulus < 2:
        raise ValueError(f"counter modulus must be at least 2, got {modulus}")
    raw = np.asarray(raw, dtype=np.int64)
    if raw.size == 0:
        return raw.copy()
    out = np.empty_like(raw)
    out[0] = raw[0] if start is None else start
    np.cumsum(wrap_delta(raw[1:], raw[:-1], modulus), out=out[1:])
    out[1:] += out[0]
    return out


class CounterUnwrapper:
    """Streaming version of :func:`unwrap` for one counter: ``update(raw) -> continuous count``."""

    def __init__(self, modulus: int) -> None:
        if modulus < 2:
            raise ValueError(f"counter modulus must be at least 2, got {modulus}")
        self.modulus = int(modulus)
        self._last_raw: int | None = None
        self.value = 0
        self.wraps = 0

    def update(self, raw: int) -> int:
        raw = int(raw)
        if self._last_raw is None:
            self.value = raw
        else:
            delta = int(wrap_delta(raw, self._last_raw, self.modulus))
            if (raw - self._last_raw) != delta:
                self.wraps += 1
            self.value += delta
        self._last_raw = raw
        return self.value

    def reset(self) -> None:
        """Forget the last reading: the next one starts a new continuous count at its raw value."""
        self._last_raw = None
