"""Impairments an emulated range sensor applies to true values: gain, bias, non-linearity,
hysteresis, noise and quantisation. Used by emulators and the world simulator so tests can
inject known characteristics and check that `trundle characterize` recovers them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RangeImpairment:
    """``measured = gain * v + bias + quadratic * (v - centre)^2 +- hysteresis / 2 + noise``.

    The hysteresis term is +half on a rising true value and -half on a falling one (the last
    direction is kept while the value stands still). ``noise_std`` in metres, ``quantum`` the
    output step (SCIP reports millimetres). Stateful because hysteresis remembers direction.
    """

    gain: float = 1.0
    bias: float = 0.0
    quadratic: float = 0.0
    centre: float = 0.0
    hysteresis: float = 0.0
    noise_std: float = 0.0
    quantum: float = 0.001
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._last: np.ndarray | None = None
        self._direction: np.ndarray | None = None

    def __call__(self, true: np.ndarray) -> np.ndarray:
        raw = np.asarray(true, np.float64)
        valid = np.isfinite(raw)
        v = np.where(valid, raw, 0.0)
        if self._last is None or self._direction is None or self._last.shape != v.shape:
            direction = np.ones_like(v)
        else:
            change = np.sign(v - self._last)
            direction = np.where(change != 0, change, self._direction)
        self._last, self._direction = v.copy(), direction
        out = (self.gain * v + self.bias + self.quadratic * (v - self.centre) ** 2
               + 0.5 * self.hysteresis * direction + self._rng.normal(0.0, self.noise_std, v.shape))
        if self.quantum:
            out = np.round(out / self.quantum) * self.quantum
        return np.where(valid, out, raw)
