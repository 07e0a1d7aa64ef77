"""The iSAM/GTSAM text graph reader against GTSAM itself: the same factors and values (the Victoria
Park counts GTSAM's own test asserts), the same chi2 at the initial values, and our optimum within
1 % of GTSAM's Levenberg-Marquardt optimum on the same graph."""

from __future__ import annotations

import math
from pathlib import Path

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.optimization.factor_graph import BETWEEN, RANGE_BEARING
from trundle.fusion.optimization.isam_graph import edge_covariance, landmark_sigmas, read_isam_graph
from trundle.logs.errors import UserError

VICTORIA = Path(__file__).resolve().parents[1] / "../shared/data/victoria-park/gtsam_victoria_park.txt"
needs_victoria = pytest.mark.skipif(not VICTORIA.is_file(), reason=f"Victoria Park graph not found at {VICTORIA}")


def _gtsam_chi2(path: Path, optimise: bool) -> tuple[float, int, int]:
    graph, values = gtsam.load2D(str(path))
    if optimise:
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return 2.0 * graph.error(values), graph.size(), values.size()


@needs_victoria
def test_victoria_park_loads_with_gtsams_counts():
    read = read_isam_graph(VICTORIA)
    g = read.graph
    assert g.num_factors == 10_608 and len(g) == 7_120   # GTSAM's testDataset asserts these
    assert len(g.factors(BETWEEN)[0]) == 6_968 and len(g.factors(RANGE_BEARING)[0]) == 3_640
    assert len(g.poses) == 6_969 and len(g.points) == 151 and read.nonuniform_landmarks == 0
    chi2, factors, values = _gtsam_chi2(VICTORIA, optimise=False)
    assert (factors, values) == (10_608, 7_120)
    assert g.chi2() == pytest.approx(chi2, rel=1e-9)


@needs_victoria
def test_victoria_park_prefix_optimum_matches_gtsam(tmp_path):
    """The first 2,000 lines (a few loops through the park) as a graph of their own."""
    prefix = tmp_path / "victoria_prefix.txt"
    prefix.write_text("".join(VICTORIA.read_text().splitlines(keepends=True)[:2000]))
    g = read_isam_graph(prefix).graph
    result = g.optimize(max_iterations=200)
    theirs, _, _ = _gtsam_chi2(prefix, optimise=True)
    assert result.converged
    assert g.chi2() <= theirs * 1.01


@pytest.mark.slow
@needs_victoria
def test_victoria_park_optimum_within_one_percent_of_gtsam():
    g = read_isam_graph(VICTORIA).graph
    g.optimize(max_iterations=400)
    theirs, _, _ = _gtsam_chi2(VICTORIA, optimise=True)
    assert abs(g.chi2() - theirs) <= 0.01 * theirs


def test_noise_layouts_follow_gtsams_load2d():
    np.testing.assert_array_equal(edge_covariance([1e-4, 0, 0, 4e-6, 0, 4e-6]), np.diag([1e-4, 4e-6, 4e-6]))
    # GTSAM's "GRAPH" layout: v1 v2 v3 v4 v5 v6 -> [v1 v2 v5; v2 v3 v6; v5 v6 v4]
    np.testing.assert_array_equal(edge_covariance([1.0, 0, 2.0, 3.0, 0, 0]), np.diag([1.0, 2.0, 3.0]))
    with pytest.raises(ValueError, match="layout"):
        edge_covariance([1.0, 0.5, 0.0, 1.0, 0.0, 1.0])
    assert landmark_sigmas(0.4, 0.4) == pytest.approx((math.sqrt(0.4), math.sqrt(0.04)))
    assert landmark_sigmas(0.4, 0.2) is None


def test_small_graph_by_hand(tmp_path):
    path = tmp_path / "g.txt"
    path.write_text("ODOMETRY 0 1 1.0 0.0 0.5 0.01 0 0 0.01 0 0.01\n"
                    "LANDMARK 1 7 2.0 0.0 0.4 0 0.4\n"
                    "BR 0 7 0.1 3.0 0.05 0.2\n")
    read = read_isam_graph(path)
    g = read.graph
    np.testing.assert_allclose(g.poses, [[0, 0, 0], [1, 0, 0.5]])
    # the point is placed by its first sighting: 2 m ahead of pose 1
    np.testing.assert_allclose(g.points, [[1 + 2 * math.cos(0.5), 2 * math.sin(0.5)]])
    index, z, info = g.factors(RANGE_BEARING)
    np.testing.assert_array_equal(index, [[1, 0], [0, 0]])
    np.testing.assert_allclose(z, [[2.0, 0.0], [3.0, 0.1]])
    np.testing.assert_allclose(info[0], np.diag([1 / 0.4, 1 / 0.04]))
    np.testing.assert_allclose(info[1], np.diag([1 / 0.2 ** 2, 1 / 0.05 ** 2]))
    assert read.point_ids == [7] and read.pose_ids == [0, 1]


def test_bad_files_are_one_clear_error(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("ODOMETRY 0 1 1.0 0.0 0.5 0.01 0 0 0.01 0 0.01\nODOMETRY 1 2 x 0 0 0.01 0 0 0.01 0 0.01\n")
    with pytest.raises(UserError, match=r"bad.txt:2: not an iSAM 2-D graph line"):
        read_isam_graph(path)
    path.write_text("")
    with pytest.raises(UserError, match="no ODOMETRY"):
        read_isam_graph(path)
    with pytest.raises(UserError, match="no such graph file"):
        read_isam_graph(tmp_path / "missing.txt")


tokens = st.one_of(st.sampled_from(["ODOMETRY", "LANDMARK", "BR", "EDGE2", "VERTEX2", "#", "FOO"]),
                   st.integers(-3, 5).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                   st.text("0123456789.-e", max_size=5))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(tokens, max_size=13), max_size=6))
def test_any_text_parses_or_is_a_user_error(tmp_path_factory, lines):
    path = tmp_path_factory.mktemp("fuzz") / "g.txt"
    path.write_text("\n".join(" ".join(line) for line in lines))
    try:
        read = read_isam_graph(path)
    except UserError:
        return
    assert np.all(np.isfinite(read.graph.poses)) and np.all(np.isfinite(read.graph.points))
