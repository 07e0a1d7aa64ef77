"""Multi-session acceptance on the real logs (issue 27), slow: fr079 and Intel cut in two where both
halves visit (tools/bench/session_halves.py), each half continuing the other's map; Intel's second half
onto fr079's first half. The figures come from tools/bench/bench_sessions.py, which prints them."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import shared_file
from trundle.fusion.evaluation.trajectory_errors import read_carmen_trajectory
from trundle.tools.bench.bench_sessions import DATASETS, dataset, demo, foreign
from trundle.tools.bench.session_halves import split_index

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", list(DATASETS))
def test_halves_continue_each_other(name, tmp_path) -> None:
    shared_file(DATASETS[name][0])
    figures = dataset(name, tmp_path)
    for order in ("fwd", "rev"):
        key = f"{name} {order}"
        assert figures[f"{key} placement_error_m"] <= 0.2 and figures[f"{key} placement_error_deg"] <= 3.0, figures
        assert figures[f"{key} closures_accepted"] >= 1 and figures[f"{key} closures_rejected_right"] == 0, figures
        assert figures[f"{key} relation_error_vs_single"] <= 1.1, figures
        assert figures[f"{key} revisit_error_vs_single"] <= 1.1, figures
        assert figures[f"{key} map_check"] == "passed", figures


def test_another_buildings_log_is_refused_or_a_part_of_its_own(tmp_path) -> None:
    shared_file(DATASETS["intel"][0])
    shared_file(DATASETS["fr079"][0])
    figures = foreign(tmp_path)
    assert figures["foreign exit code"] == 2 and figures["foreign stderr lines"] == 1, figures
    assert not figures["foreign new area placed"] and figures["foreign new area cross edges"] == 0, figures
    assert figures["foreign new area gap m"] > 0, figures


@pytest.mark.parametrize("name", list(DATASETS))
def test_the_cut_is_where_both_halves_go(name) -> None:
    reference = read_carmen_trajectory(shared_file(DATASETS[name][0]))
    k = split_index(reference.poses, reference.stamps_ns)
    assert 0.4 * len(reference) <= k <= 0.6 * len(reference)
    gap = 60 * 10**9
    stamps, positions = reference.stamps_ns, reference.poses[:, :2]
    for side in (stamps < stamps[k] - gap, stamps > stamps[k] + gap):
        assert np.hypot(*(positions[side] - positions[k]).T).min() < 1.0


def test_demo_world_second_run_continues_the_first(tmp_path) -> None:
    """Two demo runs (seeds 0 and 1, the second from another corner of the route), the second continuing
    the first's map: every marker within 5 cm of the world file, the map check passing."""
    figures = demo(tmp_path)
    assert figures["demo placed"] and figures["demo closures accepted"] >= 1, figures
    assert figures["demo markers mapped"] == figures["demo markers in world"], figures
    assert figures["demo marker max error m"] <= 0.05 and figures["demo map check"] == "passed", figures
