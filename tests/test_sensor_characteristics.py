"""Sensor-characteristic figures against values computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from trundle.fusion.evaluation import sensor_characteristics as sc


def test_range_dynamic_range_and_resolution() -> None:
    values = np.array([0.02, 0.021, 1.5, 5.6, np.inf, np.nan])
    r = sc.measurement_range(values, 0.02, 5.6, bits=12)
    assert r["lower"] == 0.02 and r["upper"] == 5.6
    assert r["dynamic_range"] == pytest.approx(5.58)
    assert r["dynamic_range_db"] == pytest.approx(20 * np.log10(280))  # 48.94 dB
    assert r["resolution"] == pytest.approx(0.001)
    assert r["resolution_ad"] == pytest.approx(5.58 / 4096)


def test_resolution_of_quantised_readings() -> None:
    rng = np.random.default_rng(0)
    readings = np.round(rng.uniform(1, 2, 5000) / 0.004) * 0.004
    assert sc.resolution(readings) == pytest.approx(0.004)
    assert sc.resolution(np.full(10, 3.0)) is None


def test_linearity_of_symmetric_quadratic() -> None:
    """m = v + c v^2 on a symmetric grid: gain 1, offset c*mean(v^2), max deviation 2c/3 at v=+-1
    (to the grid's mean of v^2), full scale 2 -> 100 c/3 percent."""
    v = np.linspace(-1, 1, 2001)
    c = 0.06
    lin = sc.linearity(v + c * v**2, v)
    mean_sq = np.mean(v**2)
    assert lin["gain"] == pytest.approx(1.0)
    assert lin["offset"] == pytest.approx(c * mean_sq)
    assert lin["nonlinearity"] == pytest.approx(c * (1 - mean_sq))
    assert lin["nonlinearity_percent_fs"] == pytest.approx(100 * c * (1 - mean_sq) / 2)


def test_hysteresis_of_a_two_branch_sweep() -> None:
    up = np.linspace(1, 4, 300)
    down = up[::-1]
    v = np.concatenate([up, down])
    m = np.concatenate([up + 0.015, down - 0.015])
    assert sc.hysteresis(m, v)["hysteresis"] == pytest.approx(0.03)
    with pytest.raises(ValueError):
        sc.hysteresis(up, up)


def test_timing_rate_jitter_and_drops() -> None:
    t = np.arange(400) * 25_000_000
    t = np.delete(t, [100, 101, 102, 250])  # four samples lost in two gaps
    f = sc.timing(t)
    assert f["rate_hz"] == pytest.approx(40.0)
    assert f["dropped"] == 4
    assert f["jitter_s"] == pytest.approx(0.0, abs=1e-12)
    drifting = np.cumsum(0.1 + 1e-5 * np.arange(200)) * 1e9  # period grows 1e-5 s per sample
    assert sc.timing(drifting.astype(np.int64))["period_drift"] == pytest.approx(1e-5 / 0.1, rel=0.01)


def test_errors_split_bias_from_noise() -> None:
    rng = np.random.default_rng(1)
    v = np.repeat(np.linspace(1, 3, 50), 200)
    m = v + 0.05 + rng.normal(0, 0.01, v.size)
    e = sc.errors(m, v, times_s=np.arange(v.size) * 0.01)
    assert e["bias"] == pytest.approx(0.05, abs=5e-4)
    assert e["noise_std"] == pytest.approx(0.01, rel=0.03)
    assert e["accuracy"] == pytest.approx(1 - np.mean(np.abs(m - v) / v))
    assert e["snr_db"] == pytest.approx(20 * np.log10(np.sqrt(np.mean(v**2)) / e["noise_std"]))
    assert abs(e["bias_drift_per_s"]) < 1e-4
    assert e["noise_normality_p"] > 0.001


def test_precision_pools_groups() -> None:
    groups = [np.array([1.0, 3.0]), np.array([10.0, 12.0, 14.0])]
    # pooled variance = (2 + 8) / (1 + 2)
    assert sc.precision(groups)["precision_std"] == pytest.approx(np.sqrt(10 / 3))


def test_beam_statistics_ignore_invalid() -> None:
    r = np.array([[1.0, np.inf], [3.0, 2.0], [2.0, 4.0]])
    s = sc.beam_statistics(r)
    np.testing.assert_allclose(s["mean"], [2.0, 3.0])
    np.testing.assert_allclose(s["std"], [1.0, np.sqrt(2.0)])
    np.testing.assert_allclose(s["valid_fraction"], [1.0, 2 / 3])


def test_static_intervals() -> None:
    t = np.arange(100) * 100_000_000  # 10 Hz
    speed = np.ones(100)
    speed[20:45] = 0.0  # 2.4 s still
    speed[60:65] = 0.0  # 0.4 s still: too short
    assert sc.static_intervals(t, speed, min_duration_s=1.0) == [(2_000_000_000, 4_400_000_000)]
