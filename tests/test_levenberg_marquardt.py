"""The one Levenberg-Marquardt core: the SE(2) retraction, hand-computed minima (dense and sparse alike),
a pose moved along SE(2), the lambda schedule, the stopping rules and Marquardt's scale invariance."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.geometry import compose, wrap_angle
from trundle.fusion.optimization.levenberg_marquardt import Settings, levenberg_marquardt, retract, solve_spd, update


def rosenbrock(scale: float = 1.0):
    """Residuals ``(10 (y - x^2), 1 - x)`` with ``y = scale * v``: the minimum is x = 1, y = 1, cost 0."""
    def residual(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = state[0], scale * state[1]
        return np.array([10.0 * (y - x * x), 1.0 - x]), np.array([[-20.0 * x, 10.0 * scale], [-1.0, 0.0]])

    def cost(state: np.ndarray) -> float:
        r = residual(state)[0]
        return float(r @ r)

    def linearize(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, jac = residual(state)
        return jac.T @ jac, jac.T @ r
    return cost, linearize


def test_retract_follows_the_exponential_map():
    """A pure turn-and-drive step moves a pose along an arc: (r sin w, r (1 - cos w)) for unit speed."""
    pose = np.array([[1.0, 2.0, 0.5]])
    w = 0.8
    step = np.array([[math.cos(0.5), math.sin(0.5), w]])  # body (1, 0, w) in map frame
    moved = retract(pose, step)[0]
    arc = np.array([math.sin(w) / w, (1 - math.cos(w)) / w, w])
    np.testing.assert_allclose(moved, compose(pose[0], arc), atol=1e-12)
    np.testing.assert_allclose(retract(pose, np.zeros((1, 3))), pose)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6))
def test_retract_is_the_additive_step_to_first_order(values):
    pose, step = np.array(values[:3])[None], 1e-4 * np.array(values[3:])[None]
    moved = retract(pose, step)[0]
    difference = moved - pose[0] - step[0]
    difference[2] = wrap_angle(difference[2])
    assert np.abs(difference).max() <= 1e-7   # second order: |step|^2 ~ 1e-7 at most


def test_update_retracts_the_poses_and_adds_the_rest():
    state = np.array([0.0, 0.0, math.pi - 0.1, 5.0, 6.0])
    moved = update(state, np.array([0.0, 0.0, 0.3, 1.0, -1.0]), poses=1)
    np.testing.assert_allclose(moved, [0.0, 0.0, -math.pi + 0.2, 6.0, 5.0], atol=1e-12)   # angle wrapped


@pytest.mark.parametrize("sparse", [False, True])
def test_rosenbrock_reaches_its_hand_computed_minimum(sparse):
    """The same loop solves a dense and a sparse problem, step for step."""
    cost, linearize = rosenbrock()
    lin = (lambda s: (sp.csc_matrix(linearize(s)[0]), linearize(s)[1])) if sparse else linearize
    x, result = levenberg_marquardt(cost, lin, np.array([-1.2, 1.0]), 0, 200,
                                    Settings(relative_tolerance=0.0, absolute_tolerance=1e-24))
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-9)
    assert result.converged and result.chi2 < 1e-20 and result.initial_chi2 == pytest.approx(24.2)
    dense_x, dense = levenberg_marquardt(cost, linearize, np.array([-1.2, 1.0]), 0, 200,
                                         Settings(relative_tolerance=0.0, absolute_tolerance=1e-24))
    assert result.iterations == dense.iterations
    np.testing.assert_allclose(x, dense_x, rtol=0, atol=1e-12)


def test_a_pose_moves_along_se2_to_the_exact_registration():
    """Points seen from a pose: sum |R(theta) p + t - q|^2 is zero exactly at the true pose, from a quarter turn off."""
    rng = np.random.default_rng(4)
    points = rng.uniform(-5, 5, (20, 2))
    truth = np.array([1.5, -2.0, 3.0])
    seen = compose(truth, np.column_stack([points, np.zeros(len(points))]))[:, :2]

    def residual(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rotated = points @ np.array([[c, -s], [s, c]]).T
        r = (rotated + pose[:2] - seen).reshape(-1)
        jac = np.zeros((len(points), 2, 3))
        jac[:, 0, 0] = jac[:, 1, 1] = 1.0
        jac[:, 0, 2], jac[:, 1, 2] = -rotated[:, 1], rotated[:, 0]
        return r, jac.reshape(-1, 3)

    def linearize(pose):
        r, jac = residual(pose)
        return jac.T @ jac, jac.T @ r

    start = truth + np.array([0.5, 0.5, math.pi / 2])
    pose, result = levenberg_marquardt(lambda p: float(residual(p)[0] @ residual(p)[0]), linearize, start, 1, 100,
                                       Settings(relative_tolerance=0.0, absolute_tolerance=1e-20))
    np.testing.assert_allclose(pose[:2], truth[:2], atol=1e-9)
    assert abs(wrap_angle(pose[2] - truth[2])) < 1e-10 and -math.pi <= pose[2] < math.pi
    assert result.converged and result.chi2 < 1e-18


def test_lambda_grows_tenfold_per_rejected_step_until_its_bound():
    """A linearisation that points uphill: every step is rejected, lambda goes 1e-5, 1e-4, ... and the
    loop stops once it passes max_lambda (500: after the 8th rejection), the state untouched."""
    calls = []

    def cost(x: np.ndarray) -> float:
        calls.append(x.copy())
        return float(x @ x)

    x, result = levenberg_marquardt(cost, lambda x: (np.eye(1), -x), np.array([1.0]), 0, 100,
                                    Settings(max_lambda=500.0))
    assert result.iterations == 8 and result.converged
    assert x[0] == 1.0 and result.chi2 == result.initial_chi2 == 1.0
    # each trial step is -g / (1 + lambda): 1 / 1.00001, 1 / 1.0001, ...
    np.testing.assert_allclose([c[0] - 1.0 for c in calls[1:]], [1.0 / (1.0 + 10.0 ** (k - 5)) for k in range(8)])


def test_lambda_falls_tenfold_per_accepted_step_down_to_its_floor():
    """On f(x) = x^2 each accepted step solves (1 + lambda) dx = -x: from lambda 1, 0.1, 0.01 and the floor 0.01."""
    calls = []

    def cost(x: np.ndarray) -> float:
        calls.append(x[0])
        return float(x @ x)

    levenberg_marquardt(cost, lambda x: (np.eye(1), x), np.array([1.0]), 0, 4,
                        Settings(initial_lambda=1.0, min_lambda=0.01, relative_tolerance=0.0, absolute_tolerance=0.0))
    expected, x = [1.0], 1.0
    for lam in (1.0, 0.1, 0.01, 0.01):
        x *= lam / (1.0 + lam)
        expected.append(x)
    np.testing.assert_allclose(calls, expected, rtol=1e-12)


def test_step_tolerance_stops_at_a_negligible_step():
    cost, linearize = rosenbrock()
    _, free = levenberg_marquardt(cost, linearize, np.array([-1.2, 1.0]), 0, 500,
                                  Settings(relative_tolerance=0.0, absolute_tolerance=0.0))
    x, stopped = levenberg_marquardt(cost, linearize, np.array([-1.2, 1.0]), 0, 500,
                                     Settings(relative_tolerance=0.0, absolute_tolerance=0.0, step_tolerance=(1e-3,)))
    assert stopped.converged and stopped.iterations < free.iterations
    np.testing.assert_allclose(x, [1.0, 1.0], atol=1e-2)


def test_marquardt_damping_is_invariant_to_the_scale_of_a_variable():
    """With lambda diag(H), rescaling y by 1000 changes nothing but y's units: the same steps, to rounding."""
    marquardt = Settings(diagonal_damping=True, min_diagonal=0.0, initial_lambda=1e-3, relative_tolerance=0.0,
                         absolute_tolerance=1e-20)
    plain_cost, plain_linearize = rosenbrock()
    scaled_cost, scaled_linearize = rosenbrock(1000.0)
    x, plain = levenberg_marquardt(plain_cost, plain_linearize, np.array([-1.2, 1.0]), 0, 500, marquardt)
    v, scaled = levenberg_marquardt(scaled_cost, scaled_linearize, np.array([-1.2, 1e-3]), 0, 500, marquardt)
    assert plain.iterations == scaled.iterations
    np.testing.assert_allclose([v[0], 1000.0 * v[1]], x, atol=1e-9)


def test_solve_spd_dense_and_sparse_agree_and_say_nan_when_singular():
    a = np.array([[4.0, 1.0], [1.0, 3.0]])
    b = np.array([1.0, 2.0])
    np.testing.assert_allclose(solve_spd(a, b), np.linalg.solve(a, b))
    np.testing.assert_allclose(solve_spd(sp.csc_matrix(a), b), np.linalg.solve(a, b))
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])
    assert np.all(np.isnan(solve_spd(singular, b)))
    assert np.all(np.isnan(solve_spd(sp.csc_matrix(singular), b)))
