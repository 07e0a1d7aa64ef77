"""The odometry check learns how far odometry and laser disagree on this log and flags the
increments the laser contradicts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.fusion.odometry.check import OdometryCheck

MODEL = np.diag([0.01 ** 2, 0.01 ** 2, math.radians(1.0) ** 2])  # configured noise of an increment
MATCH = np.diag([0.002 ** 2, 0.002 ** 2, math.radians(0.1) ** 2])


def trained(scale: float, samples: int = 100, seed: int = 0) -> OdometryCheck:
    check = OdometryCheck()
    rng = np.random.default_rng(seed)
    for e in rng.normal(0.0, scale * np.sqrt(np.diag(MODEL)), (samples, 3)):
        check.accept(e, MATCH, MODEL)
    return check


def test_configured_model_until_warmed_up() -> None:
    check = OdometryCheck(warmup=10)
    np.testing.assert_allclose(check.noise(MODEL), MODEL)
    for _ in range(9):
        check.accept(np.zeros(3), MATCH, MODEL)
    np.testing.assert_allclose(check.noise(MODEL), MODEL)


@pytest.mark.parametrize("seed", range(4))
def test_learns_the_noise_level_of_the_log(seed: int) -> None:
    check = trained(0.1, samples=1000, seed=seed)  # wheels ten times better than the configured model
    np.testing.assert_allclose(np.sqrt(check.kappa2()), 0.1, rtol=0.25)
    np.testing.assert_allclose(np.sqrt(np.diag(check.noise(MODEL))), 0.1 * np.sqrt(np.diag(MODEL)), rtol=0.25)


def test_flags_a_heading_glitch_but_not_normal_noise() -> None:
    check = trained(0.3, seed=1)
    assert check.is_outlier(np.array([0.0, 0.0, math.radians(7.0)]), MATCH, MODEL)  # a third of a 20 deg glitch
    assert not check.is_outlier(np.array([0.003, -0.003, math.radians(0.3)]), MATCH, MODEL)  # one sigma


def test_a_direction_the_scan_does_not_constrain_weighs_nothing() -> None:
    check = trained(0.3, seed=2)
    corridor = np.diag([1.0, 0.002 ** 2, math.radians(0.1) ** 2])  # the match knows nothing along x
    assert not check.is_outlier(np.array([0.5, 0.0, 0.0]), corridor, MODEL)  # slip along the axis: no contradiction
    assert check.is_outlier(np.array([0.0, 0.05, 0.0]), corridor, MODEL)  # sideways: contradiction
    assert check.distance2(np.zeros(3), corridor, MODEL) == pytest.approx(0.0)


def test_an_error_that_repeats_counts_as_it_adds_up() -> None:
    """A wrong wheel radius: every increment 0.2 model sigma too long, with noise of 0.05 sigma. Per step
    that looks like wheels five times better than the model; summed over the span of 10 increments it
    is 2 sigma against sqrt(10) model sigma, so the level must be about 10 * 0.2^2 / 0.455 along x."""
    check = OdometryCheck(span=10)
    rng = np.random.default_rng(3)
    sigma = np.sqrt(np.diag(MODEL))
    for noise in rng.normal(0.0, 0.05, (300, 3)):
        check.accept((np.array([0.2, 0.0, 0.0]) + noise) * sigma, MATCH, MODEL)
    kappa2 = check.kappa2()
    assert kappa2[0] == pytest.approx(10 * 0.2 ** 2 / 0.454936423119572, rel=0.1)
    assert kappa2[1] < 0.02 and kappa2[2] < 0.02  # the other axes: their noise only
