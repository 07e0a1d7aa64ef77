"""RobustWindow: median and MAD scale of the last values, against numpy over the same values."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.optimization.robust_window import MAD_TO_SIGMA, RobustWindow

values = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 20), st.integers(0, 3), st.lists(st.lists(values, min_size=3, max_size=3), max_size=60))
def test_median_and_scale_are_those_of_the_last_values(size, dims, rows):
    window = RobustWindow(size)
    for k, row in enumerate(rows, start=1):
        value = np.array(row[:dims]) if dims else row[0]
        window.add(value)
        last = np.array([r[:dims] if dims else r[0] for r in rows[max(0, k - size):k]])
        assert len(window) == len(last)
        assert np.array_equal(window.median(), np.median(last, axis=0))
        assert np.array_equal(window.scale(), MAD_TO_SIGMA * np.median(np.abs(last - np.median(last, axis=0)), axis=0))
        assert np.array_equal(window.scale(about_zero=True), MAD_TO_SIGMA * np.median(np.abs(last), axis=0))


def test_empty_window_is_nan():
    window = RobustWindow(5)
    assert len(window) == 0 and np.isnan(window.median()) and np.isnan(window.scale())


odd_values = st.one_of(values, st.sampled_from([0.0, -0.0, 1.0, np.nan, np.inf, -np.inf]))


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 1200), st.integers(0, 3), st.integers(0, 2**32 - 1), st.integers(0, 2500),
       st.lists(st.lists(odd_values, min_size=3, max_size=3), max_size=20))
def test_long_windows_and_odd_values_match_numpy_to_the_bit(size, dims, seed, count, odd):
    """Windows up to the odometry check's 1,000 values, ties, signed zeros, NaN and infinities: the sorted
    components give numpy's median and scales to the bit (NaN where numpy gives NaN)."""
    rng = np.random.default_rng(seed)
    rows = [list(r) for r in np.round(rng.normal(0.0, 1.0, (count, 3)), int(rng.integers(0, 4)))] + odd
    rng.shuffle(rows)
    window = RobustWindow(size)

    def same(actual, expected):
        actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
        assert actual.shape == expected.shape
        assert np.array_equal(np.isnan(actual), np.isnan(expected))
        keep = ~np.isnan(expected)
        assert np.array_equal(actual[keep].view(np.uint64), expected[keep].view(np.uint64))

    with np.errstate(invalid="ignore"):
        for k, row in enumerate(rows, start=1):
            window.add(np.array(row[:dims]) if dims else row[0])
            if k % 97 and k != len(rows):   # every 97th value and the last: medians read off at many lengths
                continue
            last = np.array([r[:dims] if dims else r[0] for r in rows[max(0, k - size):k]])
            median = np.median(last, axis=0)
            same(window.median(), median)
            same(window.scale(), MAD_TO_SIGMA * np.median(np.abs(last - median), axis=0))
            same(window.scale(about_zero=True), MAD_TO_SIGMA * np.median(np.abs(last), axis=0))
