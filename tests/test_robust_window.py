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
