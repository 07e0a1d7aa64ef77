"""Sensor characteristics as the textbook defines them, computed from logged readings.

Plain functions over numpy arrays: range and dynamic range, resolution, sensitivity and
linearity against a reference sweep, hysteresis, bandwidth (rate, jitter, period drift,
dropped samples), accuracy, precision, systematic error (bias and its drift) and random
error (noise, its distribution, SNR). Values are in the sensor's SI unit (metres, radians),
times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorClass:
    """A sensor's place in the textbook's classification table."""

    proprioceptive: bool
    active: bool
    application: str

    def as_dict(self) -> dict[str, str]:
        return {"sense": "proprioceptive" if self.proprioceptive else "exteroceptive",
                "energy": "active" if self.active else "passive", "application": self.application}


SENSOR_CLASSES = {
    "laser": SensorClass(False, True, "ranging: mapping, localization, obstacle detection (time of flight)"),
    "wheel_encoder": SensorClass(True, True, "wheel/motor motion: odometry, speed control"),
    "camera": SensorClass(False, False, "vision: features, markers, colour tracking"),
}


def measurement_range(values: np.ndarray, stated_min: float | None = None, stated_max: float | None = None,
                      bits: int | None = None) -> dict[str, float | None]:
    """Observed lower/upper limits, dynamic range (difference and dB) and resolution.

    ``values`` are valid readings (non-finite ones are ignored). The dynamic range in dB is
    ``20 log10(ymax / ymin)`` over the observed positive limits. With ``bits`` the A/D style
    resolution ``(stated_max - stated_min) / 2**bits`` is reported too.
    """
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ValueError("no finite readings")
    lower, upper = float(v.min()), float(v.max())
    db = 20.0 * np.log10(upper / lower) if lower > 0 and upper > 0 else None
    out: dict[str, float | None] = {
        "lower": lower, "upper": upper, "stated_lower": stated_min, "stated_upper": stated_max,
        "dynamic_range": upper - lower, "dynamic_range_db": None if db is None else float(db),
        "resolution": resolution(v),
    }
    if bits is not None and stated_min is not None and stated_max is not None:
        out["resolution_ad"] = (stated_max - stated_min) / 2.0**bits
    return out


def resolution(values: np.ndarray, tolerance: float = 1e-9) -> float | None:
    """Smallest change the readings show: the least gap between distinct values.

    Gaps below ``tolerance`` (float rounding of one quantised value) are merged, and the gaps
    within 1.5x of the smallest are averaged (median), since float32 storage makes one quantum
    come out a little different at different magnitudes. None when every reading is equal.
    """
    v = np.unique(np.asarray(values, np.float64)[np.isfinite(values)])
    gaps = np.diff(v)
    gaps = gaps[gaps > tolerance]
    if not gaps.size:
        return None
    # float32 storage spreads one quantum over a few neighbouring gaps: take their median
    return float(np.median(gaps[gaps <= 1.5 * gaps.min()]))


def linearity(measured: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Least-squares line ``measured = gain * reference + offset`` and the worst deviation from it.

    ``nonlinearity_percent_fs`` is the largest |residual| as a percentage of the full-scale
    output span (max - min of the fitted line over the reference range).
    """
    m, v = _paired(measured, reference)
    gain, offset = np.polyfit(v, m, 1)
    residual = m - (gain * v + offset)
    full_scale = abs(gain) * (v.max() - v.min())
    return {
        "gain": float(gain),
        "offset": float(offset),
        "nonlinearity": float(np.abs(residual).max()),
        "nonlinearity_percent_fs": float(100.0 * np.abs(residual).max() / full_scale) if full_scale else float("nan"),
        "r_squared": float(1.0 - residual.var() / m.var()) if m.var() > 0 else float("nan"),
    }


def hysteresis(measured: np.ndarray, reference: np.ndarray, bins: int = 50) -> dict[str, float]:
    """Largest difference between the rising and falling parts of a sweep at the same true value.

    Samples are split by the sign of the reference's change; each branch is averaged in
    ``bins`` reference bins over the span both branches cover, and the bins are compared.
    """
    m, v = _paired(measured, reference)
    direction = np.sign(np.gradient(v))
    rising, falling = direction > 0, direction < 0
    if rising.sum() < 2 or falling.sum() < 2:
        raise ValueError("hysteresis needs a sweep that rises and falls")
    lo = max(v[rising].min(), v[falling].min())
    hi = min(v[rising].max(), v[falling].max())
    edges = np.linspace(lo, hi, bins + 1)
    up = _binned_mean(v[rising], m[rising], edges)
    down = _binned_mean(v[falling], m[falling], edges)
    both = np.isfinite(up) & np.isfinite(down)
    if not both.any():
        raise ValueError("the rising and falling parts of the sweep do not overlap")
    diff = np.abs(up[both] - down[both])
    span = m.max() - m.min()
    return {
        "hysteresis": float(diff.max()),
        "hysteresis_percent_fs": float(100 * diff.max() / span) if span else float("nan"),
    }


def timing(stamps_ns: np.ndarray) -> dict[str, float]:
    """Bandwidth figures from measurement stamps: rate, jitter, period drift and dropped samples.

    The nominal period is the median interval; an interval of k nominal periods counts k - 1
    dropped samples. ``period_drift`` is the slope of the period over time (s per s).
    """
    t = np.sort(np.asarray(stamps_ns, np.int64)) * 1e-9
    if t.size < 3:
        raise ValueError("timing needs at least three stamps")
    periods = np.diff(t)
    nominal = float(np.median(periods))
    missing = np.maximum(np.round(periods / nominal) - 1, 0)
    regular = periods[missing == 0]
    drift = float(np.polyfit(t[1:][missing == 0] - t[0], regular, 1)[0]) if regular.size > 2 else 0.0
    return {"rate_hz": 1.0 / nominal, "mean_rate_hz": (t.size - 1) / (t[-1] - t[0]),
            "period_s": nominal, "jitter_s": float(regular.std()), "period_drift": drift,
            "dropped": int(missing.sum()), "samples": int(t.size), "duration_s": float(t[-1] - t[0])}


def errors(measured: np.ndarray, reference: np.ndarray, times_s: np.ndarray | None = None) -> dict[str, float]:
    """Accuracy, systematic error (bias, its drift) and random error (noise, distribution, SNR).

    accuracy = 1 - mean(|m - v| / |v|); bias = mean(m - v); bias drift = slope of (m - v) over
    ``times_s`` (unit per s); noise = std of the error about its linear trend in the reference
    (so gain and offset errors are systematic, not noise); SNR = 20 log10(rms(v) / noise) dB.
    """
    from scipy import stats  # ~1 s to import: only when figures are computed, not at CLI start

    m, v = _paired(measured, reference)
    e = m - v
    trend = np.polyval(np.polyfit(v, e, 1), v) if np.ptp(v) > 0 else np.full_like(e, e.mean())
    noise = e - trend
    sigma = float(noise.std(ddof=1))
    out = {
        "accuracy": float(1.0 - np.mean(np.abs(e) / np.abs(v))),
        "bias": float(e.mean()),
        "noise_std": sigma,
        "snr_db": float(20 * np.log10(np.sqrt(np.mean(v**2)) / sigma)) if sigma > 0 else float("inf"),
        "noise_skewness": float(stats.skew(noise)),
        "noise_excess_kurtosis": float(stats.kurtosis(noise)),
        "samples": int(m.size),
    }
    if noise.size >= 20 and sigma > 0:
        out["noise_normality_p"] = float(stats.normaltest(noise).pvalue)
    if times_s is not None:
        t = np.asarray(times_s, np.float64)[_finite_pairs(measured, reference)]
        out["bias_drift_per_s"] = float(np.polyfit(t - t[0], e, 1)[0]) if np.ptp(t) > 0 else 0.0
    return out


def sweep_figures(measured: np.ndarray, reference: np.ndarray, hold: np.ndarray,
                  times_s: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """All reference figures for a stepped sweep, where the true value holds for a while.

    ``hold`` numbers each stretch during which the reference held one value (consecutive
    samples of one hold share a number). Averaging each hold removes the noise, so:
    random error = the spread inside holds (pooled, with its distribution and SNR);
    hysteresis = the largest gap between rising and falling holds at the same true value;
    linearity = the line through the per-value means of both branches (hysteresis-free);
    systematic error = the mean error, and its drift = slope over time of each hold's mean
    error after the static curve is removed. Turning points (levels met from one side only) are
    left out of the line when other levels were met from both sides.
    """
    from scipy import stats  # ~1 s to import: only when figures are computed, not at CLI start

    m, v = np.asarray(measured, np.float64), np.asarray(reference, np.float64)
    keep = _finite_pairs(m, v)
    m, v, h = m[keep], v[keep], np.asarray(hold)[keep]
    t = None if times_s is None else np.asarray(times_s, np.float64)[keep]
    holds, index = np.unique(h, return_inverse=True)
    counts = np.bincount(index)
    hold_m = np.bincount(index, m) / counts
    hold_v = np.bincount(index, v) / counts
    order = np.argsort([t[index == k].mean() if t is not None else k for k in range(holds.size)]) if t is not None \
        else np.arange(holds.size)
    direction = np.zeros(holds.size)
    direction[order[1:]] = np.sign(np.diff(hold_v[order]))
    direction[order[0]] = direction[order[1]] if holds.size > 1 else 0.0
    residual = m - hold_m[index]
    dof = m.size - holds.size
    sigma = float(np.sqrt((residual**2).sum() / dof)) if dof > 0 else float("nan")
    levels, level_index = np.unique(hold_v, return_inverse=True)
    curve = np.bincount(level_index, hold_m) / np.bincount(level_index)
    rising = np.bincount(level_index, direction > 0, minlength=levels.size) > 0
    falling = np.bincount(level_index, direction < 0, minlength=levels.size) > 0
    both = rising & falling
    gaps = [
        abs(hold_m[(level_index == k) & (direction > 0)].mean() - hold_m[(level_index == k) & (direction < 0)].mean())
        for k in np.flatnonzero(both)
    ]
    # The hysteresis-free curve: levels met from both sides (a turning point is met from one).
    static = both if both.sum() >= 3 else np.ones(levels.size, bool)
    span = float(curve[static].max() - curve[static].min())
    out = {
        "sensitivity": linearity(curve[static], levels[static]) if static.sum() >= 3 else {},
        "hysteresis": {"hysteresis": float(max(gaps)) if gaps else float("nan"),
                       "hysteresis_percent_fs": float(100 * max(gaps) / span) if gaps and span else float("nan"),
                       "levels_compared": len(gaps)},
        "errors": {
            "accuracy": float(1.0 - np.mean(np.abs(m - v) / np.abs(v))),
            "bias": float(np.mean(m - v)),
            "noise_std": sigma,
            "snr_db": float(20 * np.log10(np.sqrt(np.mean(v**2)) / sigma)) if sigma > 0 else float("inf"),
            "noise_skewness": float(stats.skew(residual)),
            "noise_excess_kurtosis": float(stats.kurtosis(residual)),
            "samples": int(m.size),
            "holds": int(holds.size),
        },
        "precision": {"precision_std": sigma, "groups": int(holds.size), "samples": int(m.size)},
    }
    if t is not None and holds.size > 2:
        hold_t = np.bincount(index, t) / counts
        drift_error = hold_m - curve[level_index]
        out["errors"]["bias_drift_per_s"] = float(np.polyfit(hold_t - hold_t.min(), drift_error, 1)[0])
    return out


def precision(groups: list[np.ndarray]) -> dict[str, float]:
    """Spread of repeated measurements of one true value: pooled standard deviation over groups."""
    groups = [np.asarray(g, np.float64)[np.isfinite(g)] for g in groups]
    groups = [g for g in groups if g.size >= 2]
    if not groups:
        raise ValueError("precision needs repeated measurements")
    dof = sum(g.size - 1 for g in groups)
    pooled = np.sqrt(sum(((g - g.mean()) ** 2).sum() for g in groups) / dof)
    return {"precision_std": float(pooled), "groups": len(groups), "samples": int(sum(g.size for g in groups))}


def beam_statistics(ranges: np.ndarray) -> dict[str, np.ndarray]:
    """Per-beam mean, standard deviation and valid fraction over a (scans, beams) block.

    Used on static stretches, where every scan measures the same scene: each beam's spread is
    its precision (random error).
    """
    r = np.asarray(ranges, np.float64)
    valid = np.isfinite(r)
    count = valid.sum(axis=0)
    safe = np.where(valid, r, 0.0)
    mean = np.divide(safe.sum(axis=0), count, out=np.full(r.shape[1], np.nan), where=count > 0)
    var = np.divide(((safe - mean) ** 2 * valid).sum(axis=0), count - 1, out=np.full(r.shape[1], np.nan),
                    where=count > 1)
    return {"mean": mean, "std": np.sqrt(var), "valid_fraction": count / max(r.shape[0], 1)}


def static_intervals(stamps_ns: np.ndarray, speeds: np.ndarray, threshold: float = 1e-3,
                     min_duration_s: float = 1.0) -> list[tuple[int, int]]:
    """Stretches where the robot stands still: ``|speed| < threshold`` for ``min_duration_s``.

    ``speeds`` (N,) or (N, k) per stamp (e.g. wheel speeds, or linear and angular velocity);
    returns (start_ns, end_ns) pairs.
    """
    t = np.asarray(stamps_ns, np.int64)
    s = np.abs(np.asarray(speeds, np.float64)).reshape(t.size, -1).max(axis=1)
    still = np.concatenate([[False], s < threshold, [False]])
    edges = np.flatnonzero(np.diff(still.astype(np.int8)))
    out = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if (t[b - 1] - t[a]) * 1e-9 >= min_duration_s:
            out.append((int(t[a]), int(t[b - 1])))
    return out


def _finite_pairs(measured: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.isfinite(np.asarray(measured, np.float64)) & np.isfinite(np.asarray(reference, np.float64))


def _paired(measured: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m = np.asarray(measured, np.float64)
    v = np.asarray(reference, np.float64)
    if m.shape != v.shape:
        raise ValueError("measured and reference need the same shape")
    keep = _finite_pairs(m, v)
    if keep.sum() < 3:
        raise ValueError("fewer than three finite measured/reference pairs")
    return m[keep], v[keep]


def _binned_mean(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> np.ndarray:
    index = np.digitize(x, edges) - 1
    inside = (index >= 0) & (index < edges.size - 1)
    sums = np.bincount(index[inside], y[inside], minlength=edges.size - 1)
    counts = np.bincount(index[inside], minlength=edges.size - 1)
    return np.divide(sums, counts, out=np.full(edges.size - 1, np.nan), where=counts > 0)
