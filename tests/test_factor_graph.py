"""The pose-and-point factor graph: analytic Jacobians against finite differences, exact optima of
problems solvable by hand, marginal covariances against a dense inverse, and agreement with the
pose graph on pose-only problems."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.fusion.geometry import relative
from trundle.fusion.optimization.factor_graph import BETWEEN, POINT_PRIOR, POSITION, RANGE_BEARING, FactorGraph
from trundle.fusion.optimization.pose_graph import PoseGraph


def _spd(rng: np.random.Generator, d: int) -> np.ndarray:
    a = rng.normal(size=(d, d))
    return a @ a.T + np.eye(d)


def _random_graph(seed: int) -> FactorGraph:
    rng = np.random.default_rng(seed)
    g = FactorGraph()
    for _ in range(4):
        g.add_pose(rng.normal(size=3))
    for _ in range(3):
        g.add_point(rng.normal(size=2) * 3)
    g.add_between(0, 1, rng.normal(size=3), _spd(rng, 3))
    g.add_between(2, 3, rng.normal(size=3), _spd(rng, 3))
    g.add_range_bearing(1, 0, 2.0, 0.3, _spd(rng, 2))
    g.add_range_bearing(3, 2, 1.0, -2.9, _spd(rng, 2))   # bearing error near +-pi wraps
    g.add_position(2, 1, [1.0, 2.0], _spd(rng, 2))
    g.add_point_prior(1, [0.0, 1.0], _spd(rng, 2))
    g.add_pose_prior(3, [1.0, 1.0, 3.0], _spd(rng, 3))
    return g


@pytest.mark.parametrize("seed", range(5))
def test_jacobians_match_finite_differences(seed):
    g = _random_graph(seed)
    columns = g._columns()
    pose_col, point_col, n = columns
    x, p = g.poses, g.points
    jac, r = g._system(x, p, {}, columns)
    jac = jac.toarray()
    numeric = np.zeros_like(jac)
    h = 1e-6
    free_pose, free_point = pose_col >= 0, point_col >= 0
    for c in range(n):
        dx = np.zeros(n)
        dx[c] = h
        xn, pn = x.copy(), p.copy()
        xn[free_pose] += dx[: 3 * free_pose.sum()].reshape(-1, 3)
        pn[free_point] += dx[3 * free_pose.sum():].reshape(-1, 2)
        numeric[:, c] = (g._system(xn, pn, {}, columns)[1] - r) / h
    np.testing.assert_allclose(jac, numeric, atol=2e-4 * max(1.0, np.abs(jac).max()))


def test_linear_problem_reaches_its_exact_least_squares_solution():
    """Two point priors and relative positions from a fixed pose at the origin: the optimum is the
    information-weighted mean of the two estimates of each point, computable by hand."""
    g = FactorGraph()
    g.add_pose([0.0, 0.0, 0.0])
    a = g.add_point([5.0, 5.0])
    g.add_point_prior(a, [1.0, 2.0], np.eye(2) * 4.0)     # sigma 0.5
    g.add_position(0, a, [1.3, 1.7], np.eye(2) * 1.0)     # sigma 1
    result = g.optimize()
    expected = (4.0 * np.array([1.0, 2.0]) + 1.0 * np.array([1.3, 1.7])) / 5.0
    np.testing.assert_allclose(g.points[a], expected, atol=1e-9)
    assert result.converged
    assert g.chi2() == pytest.approx(4.0 * np.sum((expected - [1.0, 2.0]) ** 2) + np.sum((expected - [1.3, 1.7]) ** 2))
    covariance = g.marginal_covariances(points=[a])[1][0]
    np.testing.assert_allclose(covariance, np.eye(2) / 5.0, atol=1e-9)


def test_range_bearing_triangulation_is_exact():
    """A point seen from two fixed poses with exact range-bearing: optimisation lands on it."""
    g = FactorGraph()
    truth = np.array([3.0, 4.0])
    for pose in ([0.0, 0.0, 0.3], [6.0, 0.0, 2.0]):
        g.add_pose(pose)
    g.fixed_poses = {0, 1}
    point = g.add_point([2.0, 2.0])
    for k, pose in enumerate(g.poses):
        d = truth - pose[:2]
        g.add_range_bearing(k, point, float(np.hypot(*d)), math.atan2(d[1], d[0]) - pose[2], np.diag([100.0, 1000.0]))
    g.optimize()
    np.testing.assert_allclose(g.points[point], truth, atol=1e-9)
    assert g.chi2() < 1e-15


def test_marginals_equal_the_dense_inverse():
    g = _random_graph(7)
    g.optimize()
    pose_col, point_col, n = columns = g._columns()
    jac = g._system(g.poses, g.points, {}, columns)[0].toarray()
    inverse = np.linalg.inv(jac.T @ jac)
    poses, points = g.marginal_covariances(poses=[1, 3], points=[0, 2])
    for k, block in zip([1, 3], poses, strict=True):
        c = pose_col[k]
        np.testing.assert_allclose(block, inverse[c:c + 3, c:c + 3], rtol=1e-8, atol=1e-12)
    for k, block in zip([0, 2], points, strict=True):
        c = point_col[k]
        np.testing.assert_allclose(block, inverse[c:c + 2, c:c + 2], rtol=1e-8, atol=1e-12)
    assert np.all(g.marginal_covariances(poses=[0])[0] == 0)   # pose 0 is fixed


def test_pose_only_graph_agrees_with_the_pose_graph():
    """A noisy loop: the factor graph built from a PoseGraph reaches the pose graph's optimum."""
    rng = np.random.default_rng(2)
    truth = np.array(
        [[2 * math.cos(a), 2 * math.sin(a), a + math.pi / 2] for a in np.linspace(0, 2 * math.pi, 13)[:-1]]
    )
    pg = PoseGraph()
    drift = truth.copy()
    drift[:, :2] += rng.normal(0, 0.2, (len(truth), 2))
    for pose in drift:
        pg.add_node(pose)
    info = np.diag([100.0, 100.0, 400.0])
    for i in range(len(truth)):
        j = (i + 1) % len(truth)
        pg.add_edge(i, j, relative(truth[i], truth[j]) + rng.normal(0, [0.05, 0.05, 0.02]), info)
    fg = FactorGraph.from_pose_graph(pg)
    pg.optimize(max_iterations=200, relative_tolerance=1e-12, absolute_tolerance=1e-15)
    fg.optimize(max_iterations=200, relative_tolerance=1e-12, absolute_tolerance=1e-15)
    assert fg.chi2() == pytest.approx(pg.chi2(), rel=1e-6)
    np.testing.assert_allclose(fg.poses, pg.poses, atol=1e-6)
    assert len(fg.factors(BETWEEN)[0]) == pg.num_edges


def test_robust_kernel_bounds_an_outlier():
    """Ten agreeing sightings and one 5 m off: without a kernel the outlier drags the point,
    with Cauchy it barely moves."""

    def solved(kernels):
        g = FactorGraph()
        g.add_pose([0.0, 0.0, 0.0])
        p = g.add_point([1.0, 0.0])
        for _ in range(10):
            g.add_position(0, p, [2.0, 0.0], np.eye(2) * 100.0)
        g.add_position(0, p, [7.0, 0.0], np.eye(2) * 100.0)
        g.optimize(kernels=kernels)
        return g.points[p]
    assert solved({})[0] == pytest.approx(2.0 + 5.0 / 11.0, abs=1e-6)
    assert abs(solved({POSITION: ("cauchy", 3.0)})[0] - 2.0) < 0.01


def test_bad_input_is_refused():
    g = FactorGraph()
    g.add_pose([0, 0, 0])
    with pytest.raises(ValueError, match="finite"):
        g.add_point([np.nan, 0])
    with pytest.raises(ValueError, match="point 0"):
        g.add_range_bearing(0, 0, 1.0, 0.0, np.eye(2))
    p = g.add_point([1, 1])
    with pytest.raises(ValueError, match="positive definite"):
        g.add_range_bearing(0, p, 1.0, 0.0, -np.eye(2))
    with pytest.raises(ValueError, match="symmetric"):
        g.add_point_prior(p, [0, 0], [[1, 1], [0, 1]])
    with pytest.raises(ValueError, match="distinct"):
        g.add_between(0, 0, [0, 0, 0], np.eye(3))
    with pytest.raises(ValueError, match="unknown"):
        g.optimize(kernels={RANGE_BEARING: ("tukey", 1.0)})
    assert g.factors(POINT_PRIOR)[0].shape == (0, 1)
