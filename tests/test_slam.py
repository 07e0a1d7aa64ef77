"""Online SLAM on a simulated robot in a known polygon world: drifting odometry, no odometry, laser gaps."""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np
import pytest
from pydantic import ValidationError

from tests.planar_world import ROOM, scan
from trundle.fusion.geometry import compose, relative, scan_to_points, wrap_angle
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.fusion.slam.backend import MapBuilder, MapInputs
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs import messages as m
from trundle.logs.errors import ConfigError

WAYPOINTS = np.array([(-4.2, -2.3), (0.0, -2.3), (0.0, 0.3), (4.4, 0.3), (4.4, 3.3), (-4.2, 3.3), (-4.2, -2.3)])


def loop_path(laps: int = 2, step_m: float = 0.25, turn_step_rad: float = math.radians(30.0)) -> np.ndarray:
    """Poses driving the waypoint loop ``laps`` times: straight steps, turning on the spot at corners."""
    poses = []
    heading = 0.0
    for _ in range(laps):
        for a, b in pairwise(WAYPOINTS):
            target = math.atan2(b[1] - a[1], b[0] - a[0])
            turn = wrap_angle(target - heading)
            for k in range(1, int(math.ceil(abs(turn) / turn_step_rad)) + 1):
                poses.append((a[0], a[1], heading + turn * min(1.0, k * turn_step_rad / abs(turn))))
            heading = target
            length = float(np.hypot(*(b - a)))
            for s in np.arange(0.0, length, step_m):
                poses.append((a[0] + s * math.cos(heading), a[1] + s * math.sin(heading), heading))
    return np.array(poses)


def run(truth: np.ndarray, odometry: np.ndarray | None, config: SlamConfig | None = None,
        drop: range = range(0), odometry_drop: range = range(0)) -> tuple[Slam, np.ndarray, list]:
    """Feed scans (and odometry) at 2 Hz; returns the SLAM, its trajectory in the truth frame, results.

    ``drop`` lists scans the laser misses, ``odometry_drop`` the steps odometry misses.
    """
    slam = Slam(config or SlamConfig())
    results = []
    for k, pose in enumerate(truth):
        stamp = 1_000_000_000 + k * 500_000_000
        if odometry is not None and k not in odometry_drop:
            x, y, theta = odometry[k]
            slam.process("/odom", m.Odometry(stamp, "odom", "base_link", x, y, theta))
        if k in drop:
            continue
        result = slam.process("/scan", scan(ROOM, pose, beams=271, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                            stamp_ns=stamp, max_range=10.0))
        results.append(result)
    slam.finish()
    _, poses = slam.trajectory()
    # the map frame starts at the first odometry pose (the first true pose), else at the robot
    return slam, poses if odometry is not None else compose(truth[0], poses), results


def test_tracks_a_drifting_odometry_and_closes_the_loop() -> None:
    truth = loop_path()
    odometry = drifting_odometry(truth, seed=5)
    assert np.hypot(*(odometry[-1, :2] - truth[-1, :2])) > 0.5  # the odometry alone is lost
    slam, estimate, _ = run(truth, odometry)
    error = np.hypot(*(estimate[:, :2] - truth[:, :2]).T)
    heading = np.abs(wrap_angle(estimate[:, 2] - truth[:, 2]))
    assert error.mean() < 0.03 and error.max() < 0.08
    assert math.degrees(heading.mean()) < 0.5
    assert slam.stats.loop_closures >= 3 and slam.stats.optimizations >= 1
    assert slam.stats.scans == len(truth) and slam.stats.gated_out <= 2
    steps = relative(relative(truth[:-1], truth[1:]), relative(estimate[:-1], estimate[1:]))
    assert np.hypot(steps[:, 0], steps[:, 1]).mean() < 0.02


def test_works_without_odometry() -> None:
    truth = loop_path(laps=1, turn_step_rad=math.radians(20.0))
    slam, estimate, _ = run(truth, None)
    error = np.hypot(*(estimate[:, :2] - truth[:, :2]).T)
    assert error.mean() < 0.05 and slam.stats.searched > 0


def test_recovers_after_a_laser_gap_on_odometry_alone() -> None:
    truth = loop_path(laps=1)
    odometry = drifting_odometry(truth, seed=2)
    gap = range(40, 50)
    slam, estimate, results = run(truth, odometry, drop=gap)
    kept = np.array([k for k in range(len(truth)) if k not in gap])
    error = np.hypot(*(estimate[:, :2] - truth[kept, :2]).T)
    assert error.max() < 0.08
    assert results[gap.start].matched  # the first scan after the gap, from a prediction widened by the gap


def test_odometry_gap_is_bridged_by_scan_matching() -> None:
    truth = loop_path(laps=1)
    odometry = drifting_odometry(truth, seed=3)
    slam, estimate, results = run(truth, odometry, odometry_drop=range(30, 45))
    error = np.hypot(*(estimate[:, :2] - truth[:, :2]).T)
    assert error.max() < 0.08
    assert all(r.matched for r in results[30:50])


def test_keyframes_trajectory_and_map_are_consistent() -> None:
    truth = loop_path(laps=1)
    slam, estimate, results = run(truth, drifting_odometry(truth, seed=1))
    stamps, poses = slam.trajectory()
    assert len(stamps) == len(truth) and np.all(np.diff(stamps) > 0)
    nodes = [r.node for r in results if r.node >= 0]
    assert nodes == list(range(slam.stats.keyframes)) and len(slam.graph) == slam.stats.keyframes
    np.testing.assert_allclose(slam.keyframe_poses()[0], poses[0], atol=1e-9)
    grid = slam.build_map()
    residuals = slam.map_residuals(grid)
    assert len(residuals) == slam.stats.keyframes and np.nanmean(residuals) < 0.02
    message = grid.to_message(int(stamps[-1]))
    assert message.width == grid.shape[1] and (message.data == 100).sum() == 0  # clamped: below 100 %


def test_config_from_mapping_checks_keys_and_types() -> None:
    config = SlamConfig.from_mapping({"submaps": {"resolution": 0.1}, "loop_closure": {"enabled": False},
                                      "tracking": {"search_window_xy_m": [0.2, 2]}})
    assert config.submaps.resolution == 0.1 and config.loop_closure.enabled is False
    assert config.tracking.search_window_xy_m == (0.2, 2.0) and config.submaps.scans_per_submap == 25
    # a TOML integer is a number
    assert SlamConfig.from_mapping({"submaps": {"resolution": 1}}).submaps.resolution == 1.0


@pytest.mark.parametrize("table, message", [
    ({"submaps": {"scans_per_submap": 25.7}}, "slam.submaps.scans_per_submap = 25.7: expected a whole number"),
    ({"loop_closure": {"every_keyframes": 2.5}}, "slam.loop_closure.every_keyframes = 2.5: expected a whole number"),
    ({"loop_closure": {"max_candidates": 1.9}}, "slam.loop_closure.max_candidates = 1.9: expected a whole number"),
    ({"submaps": {"resolution": "0.05"}}, "slam.submaps.resolution = '0.05': expected a number"),
    ({"submaps": {"resolution": 1e300}}, "slam.submaps.resolution = 1e+300: expected a number <= 1"),
    ({"submaps": {"resolution": float("nan")}}, "slam.submaps.resolution = nan: expected a finite number"),
    ({"submaps": {"resolution": 0}}, "slam.submaps.resolution = 0: expected a number >= 0.001"),
    ({"tracking": {"gate_chi2": float("inf")}}, "slam.tracking.gate_chi2 = inf: expected a finite number"),
    ({"loop_closure": {"enabled": 1}}, "slam.loop_closure.enabled = 1: expected true or false"),
    ({"tracking": {"search_window_xy_m": [1]}}, "slam.tracking.search_window_xy_m = [1]: expected two numbers"),
    ({"tracking": {"search_window_xy_m": [2, 1]}}, "slam.tracking.search_window_xy_m = [2, 1]: expected [low, high]"),
    ({"scan": {"min_range_m": 5, "max_range_m": 4}}, "max_range_m 4.0 must be above min_range_m 5.0"),
    ({"optimization": {"robust_kernel": "tukey"}}, "slam.optimization.robust_kernel = 'tukey': expected one of"),
    ({"resolution": 0.05}, "unknown key slam.resolution (known in [slam]: keyframes, loop_closure, map_check, "
                           "odometry, optimization, scan, sessions, submaps, tracking)"),
    ({"submaps": {"resolutoin": 0.1}}, "unknown key slam.submaps.resolutoin (known in [slam.submaps]: resolution, "
                                       "scans_per_submap)"),
])
def test_config_refuses_bad_values_in_one_line(table, message) -> None:
    with pytest.raises(ConfigError) as error:
        SlamConfig.from_mapping(table)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_config_is_frozen_and_replace_checks() -> None:
    config = SlamConfig()
    with pytest.raises(ValidationError):
        config.submaps.resolution = 0.1  # type: ignore[misc]
    assert config.replace("loop_closure", enabled=False).loop_closure.enabled is False and config.loop_closure.enabled
    with pytest.raises(ConfigError, match="scans_per_submap = 0"):
        config.replace("submaps", scans_per_submap=0)


def cast_from_the_start(inputs: MapInputs) -> LogOddsGrid:
    """The map as build_map cast it before it kept its grid: every keyframe's rays, then seen-through cleared."""
    grid = LogOddsGrid(inputs.resolution, mark_returns=True)
    for pose, points, free in zip(inputs.poses, inputs.points, inputs.free, strict=True):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rot = np.array([[c, -s], [s, c]])
        grid.insert_rays(compose(pose, inputs.mount)[:2], points @ rot.T + pose[:2],
                         None if free is None else free @ rot.T + pose[:2])
    grid.clear_seen_through()
    return grid


def test_the_map_is_built_incrementally_and_equals_the_map_cast_from_the_start() -> None:
    """New keyframes are cast onto the kept grid; a moved pose (an optimisation) casts the map again: each
    time the same cells as casting every keyframe from the start, and the kept grid is not the one returned."""
    truth = loop_path(laps=1)[::6]
    rng = np.random.default_rng(4)
    points = [scan_to_points(scan(ROOM, pose, beams=181, noise_m=0.01, seed=k, max_range=10.0))
              for k, pose in enumerate(truth)]
    free = [None if k % 2 else rng.uniform(-3.0, 3.0, (5, 2)) for k in range(len(truth))]
    mount = np.array([0.1, 0.0, 0.0])
    builder = MapBuilder()

    def inputs(count: int, poses: np.ndarray) -> MapInputs:
        return MapInputs(poses[:count].copy(), tuple(points[:count]), tuple(free[:count]), mount, 0.05)

    moved = truth.copy()
    moved[1] += (0.02, -0.01, 0.01)
    for step in (inputs(3, truth), inputs(3, truth), inputs(len(truth), truth), inputs(len(truth), moved)):
        built, expected = builder.build(step), cast_from_the_start(step)
        np.testing.assert_array_equal(built.origin, expected.origin)
        for actual, wanted in ((built.log_odds, expected.log_odds), (built.observed, expected.observed),
                               (built.returned, expected.returned)):
            np.testing.assert_array_equal(actual, wanted)
        built.log_odds[:] = 0.0   # the builder's own grid goes on unharmed


def test_submaps_out_of_reach_let_go_of_their_matching_fields_and_nothing_changes(monkeypatch) -> None:
    """Loop closure releases the matching fields of finished submaps beyond its search radius (memory follows
    the submaps near the robot, not the run's length); they are computed again, equal, on a return, so the
    trajectory is the same to the last bit as when every submap keeps them."""
    truth = loop_path()
    odometry = drifting_odometry(truth, seed=5)
    config = SlamConfig().replace("loop_closure", search_radius_m=3.0)
    released = []
    keep = LogOddsGrid.release_cache
    monkeypatch.setattr(LogOddsGrid, "release_cache", lambda grid: (released.append(grid), keep(grid)))
    slam, estimate, _ = run(truth, odometry, config)
    assert slam.stats.loop_closures >= 3
    finished = {id(submap.grid) for submap in slam.local.submaps.finished}
    assert {id(grid) for grid in released} <= finished and len({id(grid) for grid in released}) >= 2
    assert any(not grid._cache for grid in released)  # released and not matched against since
    monkeypatch.setattr(LogOddsGrid, "release_cache", lambda grid: None)
    _, kept_all, _ = run(truth, odometry, config)
    assert np.array_equal(estimate, kept_all)
