"""The estimator registry and the parts of the grid SLAM: every estimator built by name, the local
trajectory builder's insertions, no class in fusion/slam/ over ~250 lines."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from tests.planar_world import ROOM, scan
from trundle.fusion.slam.backend import PoseGraphBackend
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.estimators import ESTIMATORS, EstimatorInputs, choices, make_estimator, resolve
from trundle.fusion.slam.grid_slam import Slam
from trundle.fusion.slam.landmark_grid_slam import LandmarkConstraints
from trundle.fusion.slam.landmark_slam import EkfLandmarkSlam, GraphLandmarkSlam
from trundle.fusion.slam.local import LocalTrajectoryBuilder
from trundle.fusion.slam.stats import SlamStats
from trundle.logs import messages as m
from trundle.logs.errors import UsageError

SLAM = Path(__file__).resolve().parents[1] / "fusion" / "slam"


def test_the_registry_lists_exactly_the_estimators_and_builds_each() -> None:
    assert list(ESTIMATORS) == ["grid", "grid-landmarks", "ekf", "landmark-graph"]
    assert choices() == ("graph", "grid", "grid-landmarks", "ekf", "landmark-graph")
    built = {name: make_estimator(name, EstimatorInputs(landmark_topic="/marks")) for name in ESTIMATORS}
    assert type(built["grid"]) is Slam and built["grid"].landmark_constraints is None
    assert type(built["grid-landmarks"]) is Slam
    assert isinstance(built["grid-landmarks"].landmark_constraints, LandmarkConstraints)
    assert built["grid-landmarks"].landmark_constraints.topic == "/marks"
    assert type(built["ekf"]) is EkfLandmarkSlam and built["ekf"].landmark_topic == "/marks"
    assert type(built["landmark-graph"]) is GraphLandmarkSlam and built["landmark-graph"].landmark_topic == "/marks"
    for estimator in built.values():  # the protocol: results of an empty run
        estimator.finish()
        stamps, poses = estimator.trajectory()
        assert len(stamps) == 0 and poses.shape == (0, 3) and isinstance(estimator.report(), dict)
    assert built["grid"].landmarks() is None and built["ekf"].build_map() is None
    with pytest.raises(UsageError, match="unknown estimator 'kalman'"):
        make_estimator("kalman")


def test_the_automatic_choice_fits_the_log() -> None:
    assert resolve(None, scans=True, landmarks=False) == "grid"
    assert resolve("graph", scans=True, landmarks=True) == "grid-landmarks"
    assert resolve("graph", scans=False, landmarks=True) == "landmark-graph"
    assert resolve("ekf", scans=True, landmarks=False) == "ekf"
    with pytest.raises(UsageError, match="choose graph, grid, grid-landmarks, ekf, landmark-graph"):
        resolve("kalman", scans=True, landmarks=True)


def _room_scan(stamp_ns: int, pose: tuple[float, float, float]) -> m.LaserScan:
    return scan(ROOM, np.array(pose), stamp_ns=stamp_ns)


def test_the_local_builder_returns_what_it_inserted() -> None:
    config = SlamConfig.from_mapping({"keyframes": {"distance_m": 0.2}})
    builder = LocalTrajectoryBuilder(config, SlamStats())
    mount = np.zeros(3)
    first = builder.add_scan(_room_scan(0, (0.0, 0.0, 0.0)), mount)
    assert first.insertion is not None and first.insertion.node == 0 and first.insertion.edge is None
    assert first.keyframe == 0 and np.allclose(first.offset, 0.0)
    assert len(builder.submaps.submaps[0].nodes) == 1 and builder.submaps.submaps[0].nodes[0] == 0
    near = builder.add_scan(_room_scan(100_000_000, (0.05, 0.0, 0.0)), mount)  # 5 cm: no keyframe
    assert near.insertion is None and near.keyframe == 0
    far = builder.add_scan(_room_scan(200_000_000, (0.3, 0.0, 0.0)), mount)
    inserted = far.insertion
    assert inserted is not None and inserted.node == 1 and far.keyframe == 1 and np.allclose(far.offset, 0.0)
    assert np.array_equal(inserted.pose_local, far.pose_local) and inserted.stamp_ns == 200_000_000
    measurement, covariance, heading = inserted.edge
    assert np.allclose(measurement, far.pose_local - first.pose_local) and heading == first.pose_local[2]
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    assert builder.submaps.submaps[0].nodes[-1] == 1 and builder.stats.keyframes == 2 and builder.stats.scans == 3
    backend = PoseGraphBackend(config, builder.stats, builder.submaps)
    assert [backend.add_keyframe(i) for i in (first.insertion, inserted)] == [0, 1] and len(backend.graph) == 2


def test_no_class_in_fusion_slam_is_over_250_lines() -> None:
    long = []
    for path in SLAM.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 250:
                long.append(f"{path.name}:{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert not long


def test_nothing_in_tools_builds_an_estimator_but_the_registry() -> None:
    tools = Path(__file__).resolve().parents[1] / "tools"
    for path in tools.rglob("*.py"):
        text = path.read_text()
        for name in ("Slam(", "LandmarkGridSlam(", "EkfLandmarkSlam(", "GraphLandmarkSlam(", "LandmarkConstraints("):
            assert f" {name}" not in text and f"({name}" not in text and f"={name}" not in text, (path, name)
