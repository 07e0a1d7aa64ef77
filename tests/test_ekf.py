"""Pose EKF: hand-computed predict and correct, gating, angle wrap, missing inputs, consistency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from trundle.fusion.odometry.ekf import GATE_CHI2_99, PoseEKF, odometry_noise


def test_gate_constant_is_the_chi2_quantile():
    assert pytest.approx(stats.chi2.ppf(0.99, 3), rel=1e-12) == GATE_CHI2_99


def test_predict_hand_computed():
    # facing +y; a 1 m step forward; F = [[1,0,-1],[0,1,0],[0,0,1]], G swaps the x/y noise
    ekf = PoseEKF([1.0, 2.0, np.pi / 2], np.diag([0.1, 0.2, 0.05]))
    ekf.predict([1.0, 0.0, 0.0], np.diag([0.01, 0.02, 0.03]))
    np.testing.assert_allclose(ekf.pose, [1.0, 3.0, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(ekf.covariance, [[0.17, 0.0, -0.05], [0.0, 0.21, 0.0], [-0.05, 0.0, 0.08]],
                               atol=1e-12)


def test_correct_hand_computed():
    # S = diag(0.08, 0.16, 0.02), K = diag(0.5, 0.25, 0.5)
    ekf = PoseEKF([0.0, 0.0, 0.0], np.diag([0.04, 0.04, 0.01]))
    assert ekf.correct([0.2, 0.4, 0.1], np.diag([0.04, 0.12, 0.01]))
    np.testing.assert_allclose(ekf.pose, [0.1, 0.1, 0.05], atol=1e-12)
    np.testing.assert_allclose(ekf.covariance, np.diag([0.02, 0.03, 0.005]), atol=1e-12)
    assert ekf.last_mahalanobis2 == pytest.approx(0.5 + 1.0 + 0.5)
    assert (ekf.accepted, ekf.rejected) == (1, 0)


def test_gating_rejects_outlier_and_leaves_state_unchanged():
    ekf = PoseEKF([0.0, 0.0, 0.0], np.diag([0.04, 0.04, 0.01]))
    before = ekf.pose.copy(), ekf.covariance.copy()
    assert not ekf.correct([3.0, 0.0, 0.0], np.diag([0.04, 0.12, 0.01]))  # d2 = 9 / 0.08 = 112.5
    assert ekf.last_mahalanobis2 == pytest.approx(112.5)
    np.testing.assert_array_equal(ekf.pose, before[0])
    np.testing.assert_array_equal(ekf.covariance, before[1])
    assert (ekf.accepted, ekf.rejected) == (0, 1)
    assert ekf.correct([3.0, 0.0, 0.0], np.diag([0.04, 0.12, 0.01]), gate_chi2=None)
    assert not ekf.correct([np.nan, 0.0, 0.0], np.eye(3))  # a NaN measurement never passes the gate


def test_correct_wraps_the_angle_innovation():
    ekf = PoseEKF([0.0, 0.0, 3.1], np.diag([0.01, 0.01, 0.01]))
    assert ekf.correct([0.0, 0.0, -3.1], np.diag([0.01, 0.01, 0.01]))
    # innovation is 2 pi - 6.2 = 0.0832, half of it applied, result wrapped into [-pi, pi)
    expected = (3.1 + 0.5 * (2 * np.pi - 6.2) + np.pi) % (2 * np.pi) - np.pi
    assert ekf.pose[2] == pytest.approx(expected, abs=1e-12)


def test_laser_missing_covariance_grows():
    ekf = PoseEKF([0.0, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-4]))
    traces = []
    for _ in range(50):
        ekf.predict([0.1, 0.0, 0.02], np.diag([1e-4, 1e-5, 1e-5]))
        traces.append(np.trace(ekf.covariance))
        assert np.all(np.linalg.eigvalsh(ekf.covariance) > 0)
    assert np.all(np.diff(traces) > 0)
    # 50 steps of 0.1 m, each then turning 0.02 rad: sum_k 0.1 e^(0.02 i k) = 0.1 (1 - e^i) / (1 - e^0.02i)
    end = 0.1 * (1 - np.exp(1j)) / (1 - np.exp(0.02j))
    assert ekf.pose[2] == pytest.approx(1.0)
    np.testing.assert_allclose(ekf.pose[:2], [end.real, end.imag], atol=1e-12)


def test_odometry_missing_tracks_with_random_walk_prediction():
    rng = np.random.default_rng(4)
    ekf = PoseEKF([0.0, 0.0, 0.0], np.diag([0.01, 0.01, 0.01]))
    truth = np.zeros(3)
    errors = []
    for _ in range(100):
        truth = truth + [0.05, 0.02, 0.01]
        ekf.predict(np.zeros(3), np.diag([0.06, 0.06, 0.02]) ** 2)
        measured = truth + rng.normal(0, [0.02, 0.02, 0.005])
        assert ekf.correct(measured, np.diag([0.02, 0.02, 0.005]) ** 2)
        errors.append(np.abs(ekf.pose - truth))
    assert np.max(errors, axis=0)[:2].max() < 0.1


def test_filter_is_consistent_nees():
    """Average normalised estimation error squared over Monte Carlo runs lies in its 95 % band."""
    rng = np.random.default_rng(11)
    runs, steps = 200, 30
    q = np.diag([0.02, 0.01, 0.01]) ** 2
    r = np.diag([0.05, 0.05, 0.02]) ** 2
    q_sigma, r_sigma = np.sqrt(np.diag(q)), np.sqrt(np.diag(r))
    nees = np.zeros(steps)
    for _ in range(runs):
        truth = np.zeros(3)
        ekf = PoseEKF(truth + rng.normal(0, r_sigma), r)
        for k in range(steps):
            u = np.array([0.3, 0.0, 0.1])
            noisy = u + rng.normal(0, q_sigma)
            c, s = np.cos(truth[2]), np.sin(truth[2])
            truth = truth + [c * noisy[0] - s * noisy[1], s * noisy[0] + c * noisy[1], noisy[2]]
            ekf.predict(u, q)
            if k % 3 == 0:
                ekf.correct(truth + rng.normal(0, r_sigma), r, gate_chi2=None)
            e = ekf.pose - truth
            e[2] = (e[2] + np.pi) % (2 * np.pi) - np.pi
            nees[k] += e @ np.linalg.solve(ekf.covariance, e)
    average = nees / runs
    low, high = stats.chi2.ppf([0.025, 0.975], 3 * runs) / runs
    inside = np.mean((average > low) & (average < high))
    assert inside > 0.8
    assert 2.5 < average.mean() < 3.5


def test_odometry_noise_hand_computed():
    # 0.3 m and 0.1 rad: sigma_xy = 0.01 + 0.2 * 0.3 = 0.07; sigma_theta = 0.02 + 0.1 * 0.3 + 0.2 * 0.1 = 0.07
    q = odometry_noise([0.0, 0.3, -0.1], sigma_xy_m=0.01, sigma_theta_rad=0.02, sigma_xy_per_m=0.2,
                       sigma_theta_per_m=0.1, sigma_theta_per_rad=0.2)
    np.testing.assert_allclose(q, np.diag([0.07 ** 2, 0.07 ** 2, 0.07 ** 2]), atol=1e-15)
