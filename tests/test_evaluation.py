"""SLAM evaluation: relation error, ATE and RPE against hand-computed values, file readers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.evaluation.trajectory_errors import (
    Relations,
    Trajectory,
    absolute_trajectory_error,
    align_se2,
    read_reference,
    read_relations,
    relation_error,
    relative_pose_error,
    revisit_relations,
    trajectory_relations,
)
from trundle.fusion.geometry import compose
from trundle.fusion.mapping.map_io import write_trajectory_csv
from trundle.logs.errors import DataError, UserError
from trundle.logs.stamps import seconds_ns

INTEL = Path(__file__).parents[2] / "shared" / "data" / "intel" / "intel.gfs.log"
SECOND = 1_000_000_000


def trajectory(*poses) -> Trajectory:
    return Trajectory(np.arange(len(poses)) * SECOND, np.array(poses, dtype=float))


REFERENCE = trajectory((0, 0, 0), (1, 0, 0), (2, 0, math.pi / 2))


def test_relation_error_hand_computed():
    # estimated relations (1.1, 0, 0) and (1.0, 0.2, pi/2 + 0.1) against (1, 0, 0) and (1, 0, pi/2):
    # translational errors 0.1 and 0.2 m, rotational 0 and 0.1 rad
    estimate = trajectory((0, 0, 0), (1.1, 0, 0), (2.1, 0.2, math.pi / 2 + 0.1))
    error = relation_error(estimate, trajectory_relations(REFERENCE))
    assert (error.count, error.missing) == (2, 0)
    assert error.translation_abs_m.mean == pytest.approx(0.15)
    assert error.translation_abs_m.std == pytest.approx(0.05)
    assert error.translation_sq_m2.mean == pytest.approx(0.025)
    assert error.translation_sq_m2.std == pytest.approx(0.015)
    deg = math.degrees(0.1)
    assert error.rotation_abs_deg.mean == pytest.approx(deg / 2)
    assert error.rotation_abs_deg.std == pytest.approx(deg / 2)
    assert error.rotation_sq_deg2.mean == pytest.approx(deg ** 2 / 2)
    assert error.rotation_sq_deg2.std == pytest.approx(deg ** 2 / 2)
    assert error.translation_max_m == pytest.approx(0.2)
    assert error.rotation_max_deg == pytest.approx(deg)


def test_relation_is_taken_in_the_first_pose_frame():
    # facing +y and moving 1 m along +y is a 1 m step forward: no error against (1, 0, 0)
    estimate = Trajectory([0, SECOND], [[0, 0, math.pi / 2], [0, 1, math.pi / 2]])
    relations = Relations([0], [SECOND], [[1.0, 0.0, 0.0]])
    error = relation_error(estimate, relations)
    assert error.translation_abs_m.mean == pytest.approx(0.0, abs=1e-12)
    assert error.rotation_abs_deg.mean == pytest.approx(0.0, abs=1e-12)


def test_rotational_error_wraps():
    estimate = Trajectory([0, SECOND], [[0, 0, 3.1], [0, 0, -3.1]])  # turned by 2 pi - 6.2 rad
    error = relation_error(estimate, Relations([0], [SECOND], [[0.0, 0.0, 0.0]]))
    assert error.rotation_abs_deg.mean == pytest.approx(math.degrees(2 * math.pi - 6.2))


def test_missing_poses_are_counted_and_tolerance_applies():
    estimate = Trajectory([0, SECOND + 400_000], [[0, 0, 0], [1, 0, 0]])  # 0.4 ms late
    relations = Relations([0, 0], [SECOND, 5 * SECOND], [[1, 0, 0], [2, 0, 0]])
    error = relation_error(estimate, relations)
    assert (error.count, error.missing) == (1, 1)
    with pytest.raises(DataError, match="timestamps"):
        relation_error(estimate, relations, tolerance_ns=100_000)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 31), st.floats(-50, 50), st.floats(-50, 50), st.floats(-math.pi, math.pi))
def test_rigid_motion_of_the_whole_estimate_costs_nothing(seed, x, y, theta):
    rng = np.random.default_rng(seed)
    steps = np.column_stack([rng.uniform(0, 1, 30), rng.normal(0, 0.1, 30), rng.normal(0, 0.5, 30)])
    poses = [np.zeros(3)]
    for step in steps:
        poses.append(compose(poses[-1], step))
    reference = Trajectory(np.arange(31) * SECOND, np.array(poses))
    moved = Trajectory(reference.stamps_ns, compose(np.array([x, y, theta]), reference.poses))
    error = relation_error(moved, trajectory_relations(reference, 3))
    assert error.translation_abs_m.mean < 1e-9 and error.rotation_abs_deg.mean < 1e-9
    ate = absolute_trajectory_error(moved, reference)
    assert ate.rmse_m < 1e-8 and ate.rotation_rmse_deg < 1e-7
    # the alignment undoes the motion: alignment (+) moved = reference
    np.testing.assert_allclose(compose(np.array(ate.alignment_xyt), moved.poses), reference.poses, atol=1e-8)


def test_align_se2_hand_computed():
    # (-1, 0.1), (1, -0.1) onto (-1, 0), (1, 0): rotation atan2(0.2, 2), each point 0.005 m off
    alignment = align_se2([[-1, 0.1], [1, -0.1]], [[-1, 0], [1, 0]])
    np.testing.assert_allclose(alignment, [0.0, 0.0, math.atan2(0.2, 2.0)], atol=1e-12)
    ate = absolute_trajectory_error(trajectory((-1, 0.1, 0), (1, -0.1, 0)), trajectory((-1, 0, 0), (1, 0, 0)))
    assert ate.rmse_m == pytest.approx(math.sqrt(1.01) - 1.0)
    assert ate.max_m == pytest.approx(math.sqrt(1.01) - 1.0)
    assert ate.rotation_rmse_deg == pytest.approx(math.degrees(math.atan2(0.2, 2.0)))
    raw = absolute_trajectory_error(trajectory((-1, 0.1, 0), (1, -0.1, 0)), trajectory((-1, 0, 0), (1, 0, 0)),
                                    align=False)
    assert raw.rmse_m == pytest.approx(0.1)


def test_rpe_hand_computed():
    estimate = trajectory((0, 0, 0), (1.1, 0, 0), (2.1, 0.2, math.pi / 2 + 0.1))
    rpe = relative_pose_error(estimate, REFERENCE, step=1)
    assert rpe.count == 2
    assert rpe.translation_rmse_m == pytest.approx(math.sqrt((0.01 + 0.04) / 2))
    assert rpe.translation_mean_m == pytest.approx(0.15)
    assert rpe.rotation_rmse_deg == pytest.approx(math.degrees(0.1) / math.sqrt(2))
    # over two steps: estimate (2.1, 0.2, pi/2 + 0.1) vs reference (2, 0, pi/2)
    rpe2 = relative_pose_error(estimate, REFERENCE, step=2)
    assert rpe2.count == 1
    assert rpe2.translation_rmse_m == pytest.approx(math.hypot(0.1, 0.2))
    assert rpe2.rotation_mean_deg == pytest.approx(math.degrees(0.1))


def test_relations_file_exact_times(tmp_path):
    path = tmp_path / "intel.relations"
    path.write_text("1232658478.161285 1232658644.149293 1.031273 -0.003531 0 0 -0 -0.009755\n"
                    "# comment\n\n1232658644.149293 1232658645.1 0.5 0 0 0 0 0.1\n")
    relations = read_relations(path)
    assert relations.t1_ns.tolist() == [1232658478161285000, 1232658644149293000]
    assert relations.t2_ns.tolist() == [1232658644149293000, 1232658645100000000]
    np.testing.assert_allclose(relations.deltas, [[1.031273, -0.003531, -0.009755], [0.5, 0, 0.1]])
    assert isinstance(read_reference(path), Relations)
    assert seconds_ns("0.000000001") == 1


@pytest.mark.parametrize("line", ["1 2 3", "1 2 a 0 0 0 0 0", "1 2 nan 0 0 0 0 0", "inf 2 0 0 0 0 0 0",
                                  "1 -1 0 0 0 0 0 0"])
def test_bad_relations_line_is_a_data_error(tmp_path, line):
    path = tmp_path / "x.relations"
    path.write_text("1 2 0 0 0 0 0 0\n" + line + "\n")
    with pytest.raises(DataError, match=r"x\.relations:2"):
        read_relations(path)


def test_trajectory_csv_and_carmen_references(tmp_path):
    path = tmp_path / "trajectory.csv"
    write_trajectory_csv(path, [1232658478161285000, 1232658478261285000], [[1.5, -2.25, 0.125], [1.75, -2.0, -3.0]])
    again = read_reference(path)
    assert isinstance(again, Trajectory)
    assert again.stamps_ns.tolist() == [1232658478161285000, 1232658478261285000]
    np.testing.assert_array_equal(again.poses, [[1.5, -2.25, 0.125], [1.75, -2.0, -3.0]])
    path.write_text("t_ns,x,y,theta\n1,2,x,4\n")
    with pytest.raises(DataError, match="trajectory"):
        read_reference(path)
    with pytest.raises(UserError, match="no such reference or trajectory file"):
        read_reference(tmp_path / "absent.csv")
    carmen = tmp_path / "run.clf"
    carmen.write_text("FLASER 3 1.0 2.0 3.0 0.5 0.25 0.1 0.5 0.25 0.1 1232658478.161285 host 0.5\n"
                      "ODOM 0 0 0 0 0 0 1232658478.2 host 0.6\n")
    reference = read_reference(carmen)
    assert abs(int(reference.stamps_ns[0]) - 1232658478161285000) < 1000  # float seconds: < 1 us off
    np.testing.assert_allclose(reference.poses, [[0.5, 0.25, 0.1]])


@pytest.mark.skipif(not INTEL.exists(), reason=f"{INTEL} absent (shared data)")
def test_intel_reference_and_drifting_odometry():
    from trundle.fusion.odometry.drift import drifting_odometry

    reference = read_reference(INTEL)
    assert isinstance(reference, Trajectory) and len(reference) == 910
    relations = trajectory_relations(reference)
    perfect = relation_error(reference, relations)
    assert perfect.count == 909 and perfect.translation_abs_m.mean == 0.0
    # 5 % scale error only: every relation's translational error is 5 % of its length
    drift = Trajectory(reference.stamps_ns, drifting_odometry(reference.poses, scale_error=0.05,
                                                              heading_drift_rad_per_m=0.0, scale_noise=0.0,
                                                              heading_noise_rad_per_sqrt_m=0.0, turn_noise=0.0))
    error = relation_error(drift, relations)
    lengths = np.hypot(relations.deltas[:, 0], relations.deltas[:, 1])
    assert error.translation_abs_m.mean == pytest.approx(0.05 * lengths.mean(), rel=1e-6)
    assert error.rotation_abs_deg.mean == pytest.approx(0.0, abs=1e-9)
    assert absolute_trajectory_error(drift, reference).rmse_m > 0.5


def test_revisits_hand_computed():
    """A 40 s out-and-back along x, a pose a second: pairs within 1 m and more than 30 s apart are the
    start and the end (t = 0..4 s against t = 36..40 s); a map 0.2 m shifted on the way back errs by
    0.2 m on each."""
    xs = np.concatenate([np.arange(0.0, 20.0), np.arange(20.0, -1.0, -1.0)])  # 0..19 out, 20..0 back: 41 poses
    reference = Trajectory(np.arange(len(xs)) * SECOND, np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)]))
    relations = revisit_relations(reference, max_distance_m=1.0, min_gap_s=30.0)
    pairs = {(int(a // SECOND), int(b // SECOND)) for a, b in zip(relations.t1_ns, relations.t2_ns, strict=True)}
    assert pairs == {(a, b) for a in range(41) for b in range(a + 31, 41) if abs(xs[a] - xs[b]) <= 1.0}
    assert pairs and all(b - a > 30 for a, b in pairs)
    back = reference.poses.copy()
    back[21:, 1] += 0.2  # the way back mapped 0.2 m to the side
    error = relation_error(Trajectory(reference.stamps_ns, back), relations)
    assert error.count == len(pairs) and error.translation_abs_m.mean == pytest.approx(0.2, abs=1e-9)


def test_revisits_of_a_dense_reference_are_thinned_evenly():
    """Motion capture at 100 Hz circling a 1 m ring for 10 min: 60,000 poses, every one within 3 m of
    every other (1.8e9 pairs). The pairs are capped and spread over the whole run."""
    t = np.arange(60_000) * 10_000_000
    angle = 2 * math.pi * t * 1e-9 / 20.0
    ring = Trajectory(t, np.column_stack([np.cos(angle), np.sin(angle), angle + math.pi / 2]))
    relations = revisit_relations(ring)
    assert 0 < len(relations) <= 1_000_000
    gaps = (relations.t2_ns - relations.t1_ns) * 1e-9
    assert gaps.min() > 30.0 and gaps.max() > 500.0  # the spread reaches across the whole run


def test_slam_eval_command(tmp_path, capsys):
    from trundle.tools.cli.main import main

    result, reference = tmp_path / "trajectory.csv", tmp_path / "reference.csv"
    estimate = trajectory((0, 0, 0), (1.1, 0, 0), (2.1, 0.2, math.pi / 2 + 0.1))
    write_trajectory_csv(result, estimate.stamps_ns, estimate.poses)
    write_trajectory_csv(reference, REFERENCE.stamps_ns, REFERENCE.poses)
    assert main(["slam-eval", str(result), str(reference), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["relation_error"]["count"] == 2
    assert report["relation_error"]["translation_abs_m"]["mean"] == pytest.approx(0.15, abs=1e-6)
    assert report["rpe"]["translation_mean_m"] == pytest.approx(0.15, abs=1e-6)
    assert report["ate"]["count"] == 3
    assert report["revisits"] == {"max_distance_m": 3.0, "min_gap_s": 30.0, "count": 0}  # 3 s: never back
    assert main(["slam-eval", str(result), str(reference), "--revisit-s", "0.5", "--json"]) == 0
    revisits = json.loads(capsys.readouterr().out)["revisits"]  # every pair is within 3 m and 1-2 s apart
    assert revisits["count"] == 3 and revisits["missing"] == 0
    assert main(["slam-eval", str(result), str(reference)]) == 0
    text = capsys.readouterr().out
    assert "translation abs     0.1500 +- 0.0500 m" in text and "ATE" in text
    relations = tmp_path / "r.relations"
    relations.write_text(f"0 {1:d} 1 0 0 0 0 0\n")
    assert main(["slam-eval", str(result), str(relations), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["relation_error"]["translation_abs_m"]["mean"] == pytest.approx(0.1, abs=1e-6)
    assert "ate" not in report


@pytest.mark.parametrize(
    "args", [["absent.csv", "ref.csv"], ["traj.csv", "bad.relations"], ["traj.csv", "ref.csv", "--step", "0"]]
)
def test_slam_eval_user_errors_are_one_line(tmp_path, capsys, monkeypatch, args):
    from trundle.tools.cli.main import main

    monkeypatch.chdir(tmp_path)
    write_trajectory_csv(tmp_path / "traj.csv", REFERENCE.stamps_ns, REFERENCE.poses)
    write_trajectory_csv(tmp_path / "ref.csv", REFERENCE.stamps_ns, REFERENCE.poses)
    (tmp_path / "bad.relations").write_text("1 2 3\n")
    assert main(["slam-eval", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trundle slam-eval: ") and err.count("\n") == 1
