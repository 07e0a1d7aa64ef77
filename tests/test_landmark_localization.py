"""Global localisation and kidnap recovery from landmarks with known map positions, where scans alone
cannot tell: a square room looks the same from four headings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.planar_world import scan
from trundle.fusion.geometry import compose, relative, scan_to_points, voxel_filter
from trundle.fusion.localization.grid_localization import TRACKING, Localizer
from trundle.fusion.localization.landmark_localization import LandmarkFixer, solve_pose
from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
from trundle.logs import messages as m

SQUARE = (
    np.array([[-3.0, -3.0, 3.0, -3.0], [3.0, -3.0, 3.0, 3.0], [3.0, 3.0, -3.0, 3.0], [-3.0, 3.0, -3.0, -3.0]]) + 0.0123
)
MARKERS = {"5": np.array([2.9, 1.0]), "8": np.array([-1.5, 2.9]), "9": np.array([-2.9, -2.0])}


def _seen(pose: np.ndarray, names=("5", "8", "9"), sigma: float = 0.02, rng: np.random.Generator | None = None
          ) -> tuple[m.LandmarkObservation, ...]:
    out = []
    for name in names:
        local = relative(pose, np.array([*MARKERS[name], 0.0]))[:2]
        if rng is not None:
            local = local + rng.normal(0, sigma, 2)
        out.append(m.LandmarkObservation.from_position(name, local, np.eye(2) * sigma ** 2))
    return tuple(out)


def test_pose_from_three_landmarks_is_exact():
    pose = np.array([0.7, -0.4, 2.2])
    seen = _seen(pose)
    fix = solve_pose(np.array([o.translation[:2] for o in seen]), np.array([o.position_covariance() for o in seen]),
                     np.array(list(MARKERS.values())), np.zeros((3, 2, 2)) + np.eye(2) * 1e-4)
    assert fix is not None and fix.landmarks == 3
    np.testing.assert_allclose(fix.pose, pose, atol=1e-9)
    assert fix.rms_whitened < 1e-6 and np.all(np.linalg.eigvalsh(fix.covariance) > 0)
    assert solve_pose(np.zeros((1, 2)), np.eye(2)[None], np.zeros((1, 2)), np.eye(2)[None]) is None


def test_sightings_of_two_landmarks_moments_apart_are_carried_by_odometry():
    """Marker 5 seen, the robot turns and drives 1 m, marker 8 seen: the fix is the pose now."""
    fixer = LandmarkFixer(list(MARKERS), np.array(list(MARKERS.values())), np.full((3, 2), 0.01))
    first, second = np.array([0.0, 0.0, 0.3]), np.array([0.5, 0.8, 1.5])
    odometry_origin = np.array([10.0, -3.0, 1.0])   # odometry has its own frame
    fixer.odometry(compose(odometry_origin, first))
    assert fixer.add(m.LandmarkList(0, "base_link", _seen(first, ("5",)))) is None
    fixer.odometry(compose(odometry_origin, second))
    fix = fixer.add(m.LandmarkList(2_000_000_000, "base_link", _seen(second, ("8",))))
    assert fix is not None and fix.landmarks == 2
    np.testing.assert_allclose(fix.pose, second, atol=1e-6)
    fixer.add(m.LandmarkList(3_000_000_000, "base_link", (m.LandmarkObservation("99", 1.0, 0.0, np.eye(2)),)))
    assert fixer.unknown == 1


@pytest.fixture(scope="module")
def square_map() -> LogOddsGrid:
    grid = LogOddsGrid(0.05)
    for x, y in ((-1.5, -1.5), (1.5, -1.5), (1.5, 1.5), (-1.5, 1.5), (0.0, 0.0)):
        pose = np.array([x, y, 0.0])
        points = scan_to_points(scan(SQUARE, pose, beams=720))
        grid.insert_rays(pose[:2], points + pose[:2])
    return grid


def _drive(localizer: Localizer, poses: np.ndarray, fixer: LandmarkFixer | None, rng: np.random.Generator,
           kidnap_at: int | None = None):
    updates = []
    for k, pose in enumerate(poses):
        points = voxel_filter(scan_to_points(scan(SQUARE, pose, beams=360, noise_m=0.01, seed=k)), 0.05)
        delta = None if k == 0 or k == kidnap_at else relative(poses[k - 1], pose)
        updates.append(localizer.update(points, delta))
        if fixer is not None:
            fixer.odometry(pose if kidnap_at is None or k < kidnap_at else compose(np.array([0.0, 0.0, 1.0]), pose))
            fix = fixer.add(m.LandmarkList(k * 500_000_000, "base_link", _seen(pose, rng=rng)))
            if fix is not None:
                localizer.fix(fix.pose, fix.covariance)
    return updates


def test_a_square_room_needs_the_landmarks_to_localise(square_map):
    """Scans alone: four equally good places (the room turned by 90 deg) and never one answer. With
    the markers: tracking from the first sighting, on the true pose."""
    poses = np.array([[0.3 + 0.1 * k, -0.5, 0.4 + 0.05 * k] for k in range(12)])
    rng = np.random.default_rng(1)
    blind = Localizer(square_map)
    _drive(blind, poses, None, rng)
    assert blind.status != TRACKING and len(blind.hypotheses) >= 2
    localizer = Localizer(square_map)
    fixer = LandmarkFixer(list(MARKERS), np.array(list(MARKERS.values())), np.full((3, 2), 0.01))
    updates = _drive(localizer, poses, fixer, rng)
    assert localizer.stats.converged_at == [1] and localizer.status == TRACKING   # the fix after the first scan
    for pose, update in zip(poses[1:], updates[1:], strict=True):
        assert np.hypot(*(update.pose[:2] - pose[:2])) < 0.05
        assert abs(math.remainder(update.pose[2] - pose[2], 2 * math.pi)) < math.radians(2)


def test_landmarks_reveal_a_kidnapping_and_recover(square_map):
    """Carried to a spot turned by 90 deg (which the square room hides from the scans): the marker fixes
    disagree with the track, the kidnapping is found and the localizer follows the true pose again."""
    rng = np.random.default_rng(2)
    before = [[0.3 + 0.1 * k, -0.5, 0.4] for k in range(8)]
    after = [[-0.8, 0.9 - 0.1 * k, -1.1] for k in range(10)]
    poses = np.array(before + after)
    localizer = Localizer(square_map)
    fixer = LandmarkFixer(list(MARKERS), np.array(list(MARKERS.values())), np.full((3, 2), 0.01))
    updates = _drive(localizer, poses, fixer, rng, kidnap_at=len(before))
    assert localizer.stats.kidnaps_at and len(before) <= localizer.stats.kidnaps_at[0] <= len(before) + 3
    final = updates[-1]
    assert localizer.status == TRACKING and np.hypot(*(final.pose[:2] - poses[-1, :2])) < 0.05
    assert localizer.stats.fixes_rejected >= localizer.config.lost_after
