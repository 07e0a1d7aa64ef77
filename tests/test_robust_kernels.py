"""Robust kernels: hand-computed losses and weights, and each weight is its loss's derivative."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.optimization.robust_kernels import ROBUST_KERNELS, robust_loss


def test_hand_computed_losses_and_weights():
    loss, weight = robust_loss(np.array([0.25, 4.0]), "huber", 1.0)
    np.testing.assert_allclose(loss, [0.25, 3.0])   # s within k^2; 2 k sqrt(s) - k^2 beyond
    np.testing.assert_allclose(weight, [1.0, 0.5])
    loss, weight = robust_loss(np.array([4.0]), "cauchy", 1.0)
    np.testing.assert_allclose(loss, [np.log(5.0)])
    np.testing.assert_allclose(weight, [0.2])
    loss, weight = robust_loss(np.array([9.0]), "cauchy", 3.0)
    np.testing.assert_allclose(loss, [9.0 * np.log(2.0)])
    np.testing.assert_allclose(weight, [0.5])
    loss, weight = robust_loss(np.array([0.0, 7.5]), None, 2.0)
    np.testing.assert_array_equal(loss, [0.0, 7.5])
    np.testing.assert_array_equal(weight, [1.0, 1.0])


def test_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="tukey"):
        robust_loss(np.array([1.0]), "tukey", 1.0)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(ROBUST_KERNELS), st.floats(0.0, 1e4), st.floats(0.05, 20.0))
def test_weight_is_the_derivative_of_the_loss(kernel, s, width):
    """IRLS minimises sum rho(s) only if the weight is rho'(s): central differences agree."""
    h = 1e-5 * max(s, width * width)   # the kernels' curvature scale is k^2
    s = max(s, h)
    if kernel == "huber" and abs(s - width * width) < 2 * h:   # the kink of rho' (rho itself is C1)
        return
    plus, minus = robust_loss(np.array([s + h, s - h]), kernel, width)[0]
    numeric = (plus - minus) / (2 * h)
    weight = robust_loss(np.array([s]), kernel, width)[1][0]
    assert weight == pytest.approx(numeric, rel=1e-5, abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(ROBUST_KERNELS[1:]), st.floats(0.0, 1e6), st.floats(0.05, 20.0))
def test_kernels_are_least_squares_near_zero_and_below_it_beyond(kernel, s, width):
    loss, weight = robust_loss(np.array([s]), kernel, width)
    assert 0.0 <= loss[0] <= s * (1 + 1e-12) + 1e-300   # subnormal s: a rounding of its last bits
    assert 0.0 < weight[0] <= 1.0
    small = robust_loss(np.array([1e-8 * width * width]), kernel, width)[0][0]
    assert small == pytest.approx(1e-8 * width * width, rel=1e-6)
