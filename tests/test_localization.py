"""Localisation on a fixed map: global search, convergence from an unknown start, kidnap recovery.

Two maps: the simulated office of ``tools/sim/worlds`` (exact ground truth, scans from the world
simulator) and the Intel Research Lab map built from the GMapping-corrected poses of
``intel.gfs.log`` (every other scan; the localizer then runs on the scans left out).
"""

from __future__ import annotations

import json
import math
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from trundle.fusion.geometry import compose, inverse, relative, scan_to_points, transform_points, voxel_filter
from trundle.fusion.localization.grid_localization import (
    CoarseMap,
    Localizer,
    LocalizerConfig,
    coarse_map,
    correlate_headings,
    global_search,
    grid_from_map,
)
from trundle.fusion.mapping.map_io import read_trajectory_csv
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.fusion.odometry.drift import drifting_odometry

INTEL = Path(__file__).parents[2] / "shared" / "data" / "intel" / "intel.gfs.log"


def angle_error(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2 * math.pi))


class Office:
    """The simulated office: route poses, scans (robot-frame points) and a map built from exact scans."""

    def __init__(self) -> None:
        from trundle.tools.sim.world import LaserModel, load_world, simulate_scan

        self.world = load_world()
        self.model = LaserModel(beams=361, range_max=20.0)
        self._simulate = simulate_scan
        self.grid = LogOddsGrid(0.05)
        for pose in self.route(1.0):
            self.grid.insert_rays(pose[:2], transform_points(pose, self.points(pose)))

    def route(self, step_m: float) -> np.ndarray:
        poses = []
        for a, b in pairwise(self.world.route):
            n = max(1, int(np.hypot(*(b - a)) / step_m))
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            poses += [[*(a + (b - a) * k / n), heading] for k in range(n)]
        return np.array(poses)

    def points(self, pose: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        ranges = self._simulate(self.world, tuple(pose), self.model, rng)
        angles = self.model.angles()
        ok = np.isfinite(ranges)
        return voxel_filter(np.column_stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])]), 0.05)


@pytest.fixture(scope="module")
def office() -> Office:
    return Office()


def test_correlate_headings_hand_computed():
    # one point 1 cell ahead: the score at a cell is the field one cell ahead of it
    field = np.zeros((5, 5), np.float32)
    field[2, 3] = 1.0
    coarse = CoarseMap(field, np.ones((5, 5), bool), np.zeros(2), 1.0)
    scores = correlate_headings(coarse, np.array([[1.0, 0.0]]), np.array([0.0, math.pi / 2]))
    assert scores[0, 2, 2] == 1.0 and scores[0].sum() == 1.0  # facing +x from (2, 2) sees (2, 3)
    assert scores[1, 2, 3] == 0.0 and scores[1, 1, 3] == 1.0  # facing +y from row 1 sees row 2
    assert scores[1].sum() == 1.0


def test_coarse_map_bounds_the_fine_likelihood(office):
    coarse = coarse_map(office.grid, 0.2)
    assert coarse.resolution == pytest.approx(0.2)
    fine = office.grid.likelihood_field(0.2)
    rows, cols = np.nonzero(fine > 0.5)
    assert np.all(coarse.field[rows // 4, cols // 4] >= fine[rows, cols] - 1e-6)
    assert 0.05 < coarse.free.mean() < 0.9


def test_global_search_finds_the_true_pose_first(office):
    rng = np.random.default_rng(2)
    for pose in office.route(0.3)[[40, 150]]:
        found = global_search(office.grid, office.points(pose, rng))
        best = found[0]
        assert np.hypot(*(best.pose[:2] - pose[:2])) < 0.1
        assert angle_error(best.pose[2], pose[2]) < math.radians(2.0)
        assert best.score > 0.7
        assert all(r.score <= best.score for r in found)


def run(localizer: Localizer, truth: np.ndarray, points: list[np.ndarray], odometry: np.ndarray | None):
    updates = []
    for k in range(len(truth)):
        delta = None if odometry is None or k == 0 else relative(odometry[k - 1], odometry[k])
        updates.append(localizer.update(points[k], delta))
    return updates


def test_office_converges_from_unknown_start_without_touching_the_map(office):
    rng = np.random.default_rng(5)
    path = office.route(0.3)
    truth = path[60:80]
    points = [office.points(p, rng) for p in truth]
    odometry = drifting_odometry(truth, seed=3)
    before, version = office.grid.log_odds.copy(), office.grid.version
    localizer = Localizer(office.grid)
    updates = run(localizer, truth, points, odometry)
    converged = [k for k, u in enumerate(updates) if u.converged]
    assert converged and converged[0] < 20
    for u, pose in zip(updates[converged[0]:], truth[converged[0]:], strict=True):
        assert u.status == "tracking"
        assert np.hypot(*(u.pose[:2] - pose[:2])) < 0.1
        assert angle_error(u.pose[2], pose[2]) < math.radians(2.0)
    assert localizer.stats.kidnaps_at == []
    np.testing.assert_array_equal(office.grid.log_odds, before)
    assert office.grid.version == version


def test_office_kidnapping_is_detected_and_recovered(office):
    rng = np.random.default_rng(6)
    path = office.route(0.3)
    truth = np.vstack([path[10:22], path[120:140]])  # carried 30 m away after scan 12
    points = [office.points(p, rng) for p in truth]
    steps = relative(truth[:-1], truth[1:])
    steps[11] = steps[10]  # the wheels report an ordinary step while the robot is carried
    odometry = [truth[0]]
    for step in steps:
        odometry.append(compose(odometry[-1], step))
    odometry = np.array(odometry)
    localizer = Localizer(office.grid)
    updates = run(localizer, truth, points, odometry)
    assert localizer.stats.converged_at[0] < 12
    kidnap = [k for k, u in enumerate(updates) if u.kidnapped]
    assert kidnap and 12 <= kidnap[0] <= 14
    recovered = [k for k in localizer.stats.converged_at if k > kidnap[0]]
    assert recovered and recovered[0] - 12 < 20
    for u, pose in zip(updates[recovered[0]:], truth[recovered[0]:], strict=True):
        assert np.hypot(*(u.pose[:2] - pose[:2])) < 0.1


class Intel:
    """Map from the even scans of intel.gfs.log at GMapping's poses; the odd scans to localise."""

    def __init__(self) -> None:
        from trundle.logs.importers.carmen import infer_no_return, read_carmen, to_scan

        log = read_carmen(INTEL)
        no_return = infer_no_return(log)
        lasers = [laser for laser in log.lasers if laser.kind == "FLASER"]
        scans = [to_scan(laser, "laser", no_return) for laser in lasers]
        self.poses = np.array([laser.pose for laser in lasers])
        self.grid = LogOddsGrid(0.05)
        for scan, pose in zip(scans[::2], self.poses[::2], strict=True):
            self.grid.insert_rays(pose[:2], transform_points(pose, scan_to_points(scan, range_max=20.0)))
        self.points = [voxel_filter(scan_to_points(scan, range_max=20.0), 0.05) for scan in scans]
        self.odometry = drifting_odometry(self.poses, seed=1)  # 5 % scale, 2 deg/m drift plus noise


@pytest.fixture(scope="module")
def intel() -> Intel:
    if not INTEL.exists():
        pytest.skip(f"{INTEL} absent (shared data)")
    return Intel()


@pytest.mark.parametrize("start", [1, 251, 501, 751])
def test_intel_converges_within_20_scans(intel, start):
    index = np.arange(start, start + 40, 2)  # odd scans: not in the map
    localizer = Localizer(intel.grid)
    updates = run(localizer, intel.poses[index], [intel.points[k] for k in index], intel.odometry[index])
    converged = [k for k, u in enumerate(updates) if u.converged]
    assert converged and converged[0] < 20
    errors = [
        np.hypot(*(u.pose[:2] - p[:2]))
        for u, p in zip(updates[converged[0] :], intel.poses[index][converged[0] :], strict=True)
    ]
    assert max(errors) < 0.15
    assert localizer.stats.kidnaps_at == []


def test_intel_without_odometry(intel):
    index = np.arange(301, 313)
    localizer = Localizer(intel.grid)
    updates = run(localizer, intel.poses[index], [intel.points[k] for k in index], None)
    assert localizer.stats.converged_at and localizer.stats.converged_at[0] < 20
    assert np.hypot(*(updates[-1].pose[:2] - intel.poses[index[-1]][:2])) < 0.15


def test_intel_kidnapping_is_detected_and_recovered(intel):
    index = np.concatenate([np.arange(101, 131, 2), np.arange(601, 641, 2)])
    splice = 15
    odometry = intel.odometry[index].copy()
    # after the splice the odometry continues from where the robot was, with an ordinary step
    step = relative(intel.odometry[index[splice - 2]], intel.odometry[index[splice - 1]])
    shift = compose(compose(odometry[splice - 1], step), inverse(odometry[splice]))
    odometry[splice:] = compose(shift, odometry[splice:])
    before = intel.grid.log_odds.copy()
    localizer = Localizer(intel.grid, LocalizerConfig(lost_after=2))
    updates = run(localizer, intel.poses[index], [intel.points[k] for k in index], odometry)
    kidnap = [k for k, u in enumerate(updates) if u.kidnapped]
    assert localizer.stats.converged_at[0] < splice
    assert kidnap and splice <= kidnap[0] <= splice + 2
    recovered = [k for k in localizer.stats.converged_at if k > kidnap[0]]
    assert recovered and recovered[0] - splice < 20
    for u, pose in zip(updates[recovered[0]:], intel.poses[index][recovered[0]:], strict=True):
        assert np.hypot(*(u.pose[:2] - pose[:2])) < 0.15
    np.testing.assert_array_equal(intel.grid.log_odds, before)


EXP2 = Path(__file__).parents[2] / "shared" / "data" / "breezyslam" / "exp2.dat"


@pytest.mark.slow
@pytest.mark.skipif(not EXP2.exists(), reason=f"{EXP2} absent (shared data)")
def test_exp2_converges_and_recovers_on_its_slam_map():
    """exp2 (real URG-04LX scans, real wheel odometry): map by our SLAM, then localise from unknown starts."""
    from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
    from trundle.fusion.slam.grid_slam import Slam
    from trundle.logs.importers.breezyslam import ROBOT, messages, read_dat

    slam = Slam(odometry=DiffDriveOdometry(ROBOT["wheel_radius_m"], ROBOT["track_m"]),
                laser_pose=(ROBOT["laser_x_m"], 0.0, 0.0))
    scans, odometry = [], []
    for topic, msg, _ in messages(read_dat(EXP2)[0]):
        slam.process(topic, msg)
        if topic == "/scan":
            scans.append(voxel_filter(scan_to_points(msg, np.array([ROBOT["laser_x_m"], 0.0, 0.0])), 0.05))
            odometry.append(slam.odometry_at(msg.stamp_ns))
    slam.finish()
    reference = slam.trajectory()[1]
    grid = slam.build_map()
    odometry = np.array(odometry)
    for start in range(0, 620, 60):
        index = np.arange(start, min(start + 20, len(scans)))
        localizer = Localizer(grid)
        updates = run(localizer, reference[index], [scans[k] for k in index], odometry[index])
        assert localizer.stats.converged_at and localizer.stats.converged_at[0] < 20
        assert localizer.stats.kidnaps_at == []
        assert np.hypot(*(updates[-1].pose[:2] - reference[index[-1]][:2])) < 0.15
    index = np.concatenate([np.arange(50, 65), np.arange(400, 420)])  # carried 4.3 m after scan 15
    spliced = odometry[index].copy()
    shift = compose(compose(spliced[14], relative(spliced[13], spliced[14])), inverse(spliced[15]))
    spliced[15:] = compose(shift, spliced[15:])
    localizer = Localizer(grid)
    updates = run(localizer, reference[index], [scans[k] for k in index], spliced)
    kidnap = localizer.stats.kidnaps_at
    assert kidnap and 15 <= kidnap[0] <= 17
    recovered = [k for k in localizer.stats.converged_at if k > kidnap[0]]
    assert recovered and recovered[0] - 15 < 20
    assert np.hypot(*(updates[-1].pose[:2] - reference[index[-1]][:2])) < 0.15


def test_localize_command_on_a_spliced_intel_log(intel, tmp_path, capsys):
    """`trundle localize` on a saved map and an MCAP whose scans jump 500 scans ahead half way."""
    from trundle.fusion.mapping.map_io import save_map
    from trundle.logs.importers import write_log
    from trundle.logs.importers.carmen import CarmenLog, messages, read_carmen
    from trundle.tools.cli.main import main

    lasers = [laser for laser in read_carmen(INTEL).lasers if laser.kind == "FLASER"]
    index = np.concatenate([np.arange(101, 131, 2), np.arange(601, 641, 2)])
    odometry = intel.odometry[index].copy()
    shift = compose(compose(odometry[14], relative(odometry[13], odometry[14])), inverse(odometry[15]))
    odometry[15:] = compose(shift, odometry[15:])  # the wheels saw an ordinary step at the splice
    spliced = CarmenLog(lasers=[lasers[k] for k in index], order=[("laser", k) for k in range(len(index))])
    write_log(messages(spliced, odometry="laser", laser_odometry=odometry), tmp_path / "spliced.mcap", metadata={})
    save_map(intel.grid.to_message(0), tmp_path / "map")
    before = (tmp_path / "map.pgm").read_bytes()
    assert main(["localize", str(tmp_path / "spliced.mcap"), "--map", str(tmp_path / "map.yaml"),
                 "-o", str(tmp_path / "poses.csv"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["scans"] == 35 and report["odometry"]
    assert report["converged_at_scans"][0] < 15
    assert 15 <= report["kidnaps_detected_at_scans"][0] <= 17
    assert len(report["converged_at_scans"]) == 2 and report["converged_at_scans"][1] - 15 < 20
    assert np.hypot(*(np.array(report["final_pose"][:2]) - intel.poses[index[-1]][:2])) < 0.15
    assert (tmp_path / "map.pgm").read_bytes() == before
    stamps, poses = read_trajectory_csv(tmp_path / "poses.csv")
    assert len(stamps) == report["tracked_scans"]


def test_localize_command_user_errors(tmp_path, capsys):
    from trundle.tools.cli.main import main

    assert main(["localize", str(tmp_path / "absent.mcap"), "--map", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trundle localize: ") and err.count("\n") == 1


def test_grid_from_map_is_trinary_and_read_only():
    from trundle.logs.messages import OccupancyGrid

    data = np.array([[100, 0, -1], [70, 20, 0]], np.int8)
    grid = grid_from_map(OccupancyGrid(0, "map", 0.1, -1.0, 2.0, 0.0, data))
    assert grid.resolution == pytest.approx(0.1) and grid.origin.tolist() == [-1.0, 2.0]
    np.testing.assert_array_equal(grid.occupied(), [[True, False, False], [True, False, False]])
    np.testing.assert_array_equal(grid.observed, data >= 0)
    assert np.all(grid.log_odds[data == 0] < 0) and grid.log_odds[0, 2] == 0
    with pytest.raises(ValueError):
        grid.insert_rays([-0.95, 2.05], [[-0.75, 2.05]])  # the map cannot be written
    from trundle.logs.errors import UserError
    with pytest.raises(UserError, match="rotated"):
        grid_from_map(OccupancyGrid(0, "map", 0.1, 0.0, 0.0, 0.5, data))
