"""Pose-graph back end: hand-computed optima, the between error's Jacobians, g2o I/O, robust kernels, Intel vs GTSAM."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.geometry import wrap_angle
from trundle.fusion.observation_models import between_error
from trundle.fusion.optimization.pose_graph import PoseGraph, read_g2o
from trundle.logs.errors import UserError

INTEL_G2O = Path(__file__).parents[2] / "shared" / "data" / "intel-posegraph" / "input_INTEL.g2o"
needs_intel = pytest.mark.skipif(not INTEL_G2O.exists(), reason=f"{INTEL_G2O} absent (shared data)")
IDENTITY = np.eye(3)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (+) b written out independently of the module under test."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2])])


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 (+) b."""
    c, s = np.cos(a[2]), np.sin(a[2])
    d = b[:2] - a[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(b[2] - a[2])])


def line_graph(loop_measurement: float, loop_info: float = 1.0) -> PoseGraph:
    graph = PoseGraph()
    for x in (0.0, 0.9, 2.5):
        graph.add_node([x, 0.0, 0.0])
    graph.add_edge(0, 1, [1.0, 0.0, 0.0], IDENTITY)
    graph.add_edge(1, 2, [1.0, 0.0, 0.0], IDENTITY)
    graph.add_edge(0, 2, [loop_measurement, 0.0, 0.0], np.diag([loop_info, 1.0, 1.0]))
    return graph


def test_linear_chain_hand_computed_optimum():
    # minimise (x1-1)^2 + (x2-x1-1)^2 + (x2-2.3)^2  ->  x1 = 1.1, x2 = 2.2, chi2 = 3 * 0.01
    graph = line_graph(2.3)
    result = graph.optimize()
    assert result.converged
    np.testing.assert_allclose(graph.poses, [[0, 0, 0], [1.1, 0, 0], [2.2, 0, 0]], atol=1e-9)
    assert result.chi2 == pytest.approx(0.03, abs=1e-10)
    assert graph.chi2() == pytest.approx(0.03, abs=1e-10)


def test_information_weights_the_loop_edge():
    # loop information 4: 2 x1 = x2 and (x2-x1-1) + 4 (x2-2.3) = 0  ->  x1 = 10.2/9
    graph = line_graph(2.3, loop_info=4.0)
    graph.optimize()
    np.testing.assert_allclose(graph.poses[1:, 0], [10.2 / 9, 20.4 / 9], atol=1e-9)


def test_huber_kernel_hand_computed_optimum():
    # false loop closure at 10 m. Least squares: 2 x1 = x2, 2 x2 - x1 = 11 -> x1 = 11/3.
    # Huber (k = 1) caps the loop's gradient at 2: 2 x1 = x2, x2 - x1 - 1 = 1 -> x1 = 2, x2 = 4.
    plain = line_graph(10.0)
    plain.optimize()
    np.testing.assert_allclose(plain.poses[1:, 0], [11 / 3, 22 / 3], atol=1e-8)
    robust = line_graph(10.0)
    result = robust.optimize(robust_kernel="huber", kernel_width=1.0, max_iterations=200,
                             relative_tolerance=1e-14, absolute_tolerance=0.0)
    np.testing.assert_allclose(robust.poses[1:, 0], [2.0, 4.0], atol=1e-6)
    assert result.chi2 == pytest.approx(1.0 + 1.0 + (2 * 6.0 - 1.0), abs=1e-6)  # 1 + 1 + huber(36)


def test_square_loop_recovers_exact_square_across_the_angle_wrap():
    truth = np.array([[0, 0, 0], [1, 0, np.pi / 2], [1, 1, -np.pi], [0, 1, -np.pi / 2]], dtype=float)
    graph = PoseGraph()
    rng = np.random.default_rng(3)
    graph.add_node(truth[0])
    for pose in truth[1:]:
        graph.add_node(pose + np.r_[rng.normal(0, 0.2, 2), rng.normal(0, 0.3)])
    for i, j in ((0, 1), (1, 2), (2, 3), (0, 3)):
        graph.add_edge(i, j, between(truth[i], truth[j]), IDENTITY)
    result = graph.optimize()
    assert result.chi2 < 1e-16
    np.testing.assert_allclose(graph.poses[:, :2], truth[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(graph.poses[:, 2] - truth[:, 2]), 0, atol=1e-9)


def random_consistent_graph(rng: np.random.Generator, n: int = 60, loops: int = 20) -> tuple[PoseGraph, np.ndarray]:
    """Exact measurements of a random walk with loop closures; dead-reckoning start badly wrong."""
    truth = np.zeros((n, 3))
    for k in range(1, n):
        truth[k] = compose(truth[k - 1], [rng.uniform(0.2, 1.0), rng.normal(0, 0.1), rng.normal(0, 0.6)])
    graph = PoseGraph()
    graph.add_node(truth[0])
    for k in range(1, n):
        graph.add_node(rng.normal(0, 5, 3))
        graph.add_edge(k - 1, k, between(truth[k - 1], truth[k]), np.diag([100.0, 100.0, 400.0]))
    for _ in range(loops):
        i, j = sorted(rng.choice(n, 2, replace=False))
        graph.add_edge(int(i), int(j), between(truth[i], truth[j]), np.diag([50.0, 20.0, 300.0]))
    return graph, truth


def test_initialize_recovers_consistent_graph_exactly():
    graph, truth = random_consistent_graph(np.random.default_rng(7))
    graph.initialize()
    np.testing.assert_allclose(graph.poses[:, :2], truth[:, :2], atol=1e-8)
    np.testing.assert_allclose(wrap_angle(graph.poses[:, 2] - truth[:, 2]), 0, atol=1e-9)
    assert graph.chi2() < 1e-12


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-4, 4), min_size=9, max_size=9))
def test_analytic_jacobians_match_finite_differences(values):
    v = np.array(values)
    x = np.stack([v[0:3], v[3:6]])
    z = v[6:9][None, :]
    ij = np.array([[0, 1]])
    e, jac_i, jac_j = between_error(x[ij[:, 0]], x[ij[:, 1]], z)
    for node, jac in ((0, jac_i[0]), (1, jac_j[0])):
        numeric = np.zeros((3, 3))
        for k in range(3):
            step = np.zeros((2, 3))
            step[node, k] = 1e-6
            plus, minus = between_error(*(x + step), z)[0][0], between_error(*(x - step), z)[0][0]
            diff = plus - minus
            diff[2] = wrap_angle(diff[2])
            numeric[:, k] = diff / 2e-6
        np.testing.assert_allclose(jac, numeric, atol=1e-5)
    # the error is exactly t2v(z^-1 (x_i^-1 x_j)), computed independently
    expected = between(z[0], between(x[0], x[1]))
    np.testing.assert_allclose(e[0, :2], expected[:2], atol=1e-9)
    assert abs(wrap_angle(e[0, 2] - expected[2])) < 1e-9


def test_g2o_round_trip(tmp_path):
    graph, _ = random_consistent_graph(np.random.default_rng(1), n=12, loops=4)
    graph.add_edge(2, 5, [0.1, 0.2, 0.3], [[11.11, -0.25, 0.01], [-0.25, 400.0, 0.02], [0.01, 0.02, 2496.8]])
    path = tmp_path / "g.g2o"
    graph.write_g2o(path)
    text = path.read_text().splitlines()
    assert text[0].split()[0] == "VERTEX_SE2" and len(text[0].split()) == 5
    last_edge = [line for line in text if line.startswith("EDGE_SE2")][-1].split()
    assert last_edge[1:3] == ["2", "5"]
    np.testing.assert_allclose([float(t) for t in last_edge[6:]], [11.11, -0.25, 0.01, 400.0, 0.02, 2496.8])
    again = read_g2o(path)
    np.testing.assert_allclose(again.poses, graph.poses, atol=1e-8)
    for a, b in zip(again.edges, graph.edges, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-15)
    assert again.fixed == {0}


@pytest.mark.parametrize("line", ["VERTEX_SE2 0 1 2", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0", "VERTEX_XY 3 1 2",
                                  "VERTEX_SE2 0 a 0 0"])
def test_g2o_bad_line_is_a_user_error(tmp_path, line):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n" + line + "\n")
    with pytest.raises(UserError, match=r"bad\.g2o:3"):
        read_g2o(path)


def test_g2o_edge_to_unknown_vertex_and_bad_information_are_user_errors(tmp_path):
    path = tmp_path / "g.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(UserError, match="vertex"):
        read_g2o(path)
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n")
    with pytest.raises(UserError, match="positive definite"):
        read_g2o(path)


def test_fixed_vertices_do_not_move():
    graph = line_graph(2.3)
    graph.fixed = {0, 2}
    graph.optimize()
    np.testing.assert_allclose(graph.poses[[0, 2], 0], [0.0, 2.5])
    assert graph.poses[1, 0] == pytest.approx((1.0 + 1.5) / 2)  # (x1-1)^2 + (2.5-x1-1)^2


@needs_intel
def test_intel_converges_to_gtsam_final_error():
    graph = read_g2o(INTEL_G2O)
    assert len(graph) == 1228 and graph.num_edges == 1483
    graph.initialize()
    start = graph.poses
    result = graph.optimize()
    assert result.converged and result.chi2 < 1e-4 * result.initial_chi2
    assert result.chi2 == pytest.approx(graph.chi2())
    from trundle.tools.bench.bench_pose_graph import gtsam_problem, gtsam_solve

    gtsam_chi2, gtsam_poses, _ = gtsam_solve(*gtsam_problem(INTEL_G2O, start))
    assert result.chi2 == pytest.approx(gtsam_chi2, rel=0.01)
    assert np.abs(gtsam_poses[:, :2] - graph.poses[:, :2]).max() < 0.05


@needs_intel
def test_intel_robust_kernel_ignores_false_loop_closures():
    clean = read_g2o(INTEL_G2O)
    clean.initialize()
    clean.optimize()
    reference = clean.poses
    clean.optimize(robust_kernel="cauchy")
    robust_reference = clean.poses
    ij, _, info = clean.edges
    loop_info = info[ij[:, 1] - ij[:, 0] > 1]
    rng = np.random.default_rng(0)
    graph = read_g2o(INTEL_G2O)
    real = graph.num_edges
    for _ in range(40):
        i, j = sorted(rng.choice(len(reference), 2, replace=False))
        graph.add_edge(int(i), int(j), [rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-np.pi, np.pi)],
                       loop_info[rng.integers(len(loop_info))])
    graph.poses = reference
    graph.optimize(max_iterations=20)
    plain_shift = np.hypot(*(graph.poses[:, :2] - reference[:, :2]).T)
    assert plain_shift.max() > 2.0  # least squares bends the map towards the false closures
    graph.poses = reference
    result = graph.optimize(robust_kernel="cauchy")
    assert result.converged
    robust_shift = np.hypot(*(graph.poses[:, :2] - robust_reference[:, :2]).T)
    assert robust_shift.max() < 0.3 and robust_shift.mean() < 0.1
    chi2 = graph.edge_chi2()
    assert chi2[real:].min() > 100.0  # every false closure stands out
    assert np.percentile(chi2[:real], 99) < 10.0
