"""RANSAC and its models: hand-computed values and exact recovery from synthetic data.

Synthetic data is noise-free, so the recovered model must equal the one that generated it (to
round-off) and the inlier mask must be exactly the generating points; outliers are drawn far
(>= 10x the band) from the true model so that none can be an inlier by chance.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.perception.ransac import (
    RansacResult,
    camera_motion_from_odometry,
    find_essential,
    find_fundamental,
    find_homography,
    fit_essential,
    fit_homography,
    fit_line,
    homography_residuals,
    line_residuals,
    motion_prior_mask,
    project,
    ransac,
    required_trials,
    sampson_distance,
)

SETTINGS = settings(max_examples=40, deadline=None)
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz]))[0]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _same_up_to_scale(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    return min(np.abs(a - b).max(), np.abs(a + b).max())


# --- general function ----------------------------------------------------------------------------


def test_required_trials_matches_the_textbook_formula() -> None:
    # k = log(1 - p) / log(1 - w^s): w = 0.5, s = 4, p = 0.99 -> 71.36
    assert required_trials(0.5, 4, 0.99) == pytest.approx(math.log(0.01) / math.log(1 - 0.0625))
    assert required_trials(0.5, 4, 0.99) == pytest.approx(71.36, abs=0.01)
    assert required_trials(1.0, 4, 0.99) == 0.0
    assert required_trials(0.0, 4, 0.99) == math.inf


def test_ransac_degenerate_and_short_inputs() -> None:
    points = np.zeros((10, 2))
    always_degenerate = ransac(points, lambda p: None, line_residuals, 2, 1.0, max_trials=37)
    assert always_degenerate == RansacResult(None, always_degenerate.inliers, 37)
    assert not always_degenerate.inliers.any()
    short = ransac(points[:1], fit_line, line_residuals, 2, 1.0)
    assert short.model is None and short.trials == 0 and short.inliers.shape == (1,)
    with pytest.raises(ValueError):
        ransac((points, points[:5]), fit_homography, homography_residuals, 4, 1.0)


def test_ransac_is_reproducible_by_default_and_stops_early() -> None:
    rng = np.random.default_rng(5)
    x = rng.uniform(-10, 10, 200)
    points = np.column_stack([x, 0.5 * x + 1.0])
    points[:20] += rng.uniform(5, 10, (20, 2))
    first = ransac(points, fit_line, line_residuals, 2, 0.01)
    again = ransac(points, fit_line, line_residuals, 2, 0.01)
    assert first.trials == again.trials and np.array_equal(first.inliers, again.inliers)
    # 90 % inliers, 2-point samples: about 3 trials give 99 % confidence
    assert first.trials <= math.ceil(required_trials(0.9, 2, 0.99))


# --- line ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("points", "expected"), [
    ([[2, 0], [2, 5]], (2.0, 0.0)),                       # x = 2
    ([[0, 3], [7, 3], [-1, 3]], (3.0, math.pi / 2)),       # y = 3
    ([[0, -1], [3, -1]], (1.0, -math.pi / 2)),             # y = -1: normal points down
    ([[0, 2], [2, 0], [1, 1]], (math.sqrt(2), math.pi / 4)),   # x + y = 2
    ([[-2, 0], [-2, 1]], (2.0, math.pi)),                  # x = -2
])
def test_fit_line_hand_computed(points: list, expected: tuple[float, float]) -> None:
    r, alpha = fit_line(np.array(points, dtype=float))
    assert r == pytest.approx(expected[0], abs=1e-12)
    assert alpha == pytest.approx(expected[1], abs=1e-12)


def test_fit_line_is_total_least_squares() -> None:
    # symmetric scatter about y = x: TLS gives the diagonal exactly (ordinary LS in y would not)
    points = np.array([[0, 1], [1, 0], [2, 3], [3, 2]], dtype=float)
    r, alpha = fit_line(points)
    assert alpha == pytest.approx(-math.pi / 4) and r == pytest.approx(0.0, abs=1e-12)
    assert line_residuals((r, alpha), points) == pytest.approx(np.full(4, math.sqrt(0.5)))


def test_fit_line_degenerate() -> None:
    assert fit_line(np.array([[1.0, 2.0]])) is None
    assert fit_line(np.array([[1.0, 2.0], [1.0, 2.0], [1.0, 2.0]])) is None


@SETTINGS
@given(st.floats(0.0, 20.0), st.floats(-math.pi, math.pi), st.integers(10, 80), st.integers(0, 60),
       st.integers(0, 2**32 - 1))
def test_ransac_line_exact_recovery(r: float, alpha: float, n_in: int, n_out: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    normal = np.array([math.cos(alpha), math.sin(alpha)])
    along = rng.uniform(-30, 30, n_in)
    inliers = r * normal + along[:, None] * np.array([-normal[1], normal[0]])
    offsets = rng.uniform(0.5, 10, n_out) * rng.choice([-1, 1], n_out)
    outliers = r * normal + offsets[:, None] * normal + rng.uniform(-30, 30, n_out)[:, None] * np.array(
        [-normal[1], normal[0]])
    points = np.vstack([inliers, outliers])
    found = ransac(points, fit_line, line_residuals, 2, 0.05, rng=seed)
    assert found.inliers.tolist() == [True] * n_in + [False] * n_out
    assert line_residuals(found.model, inliers).max() < 1e-9
    assert found.model[0] >= 0


# --- homography ----------------------------------------------------------------------------------


def test_fit_homography_known_translation_and_degenerate_sample() -> None:
    src = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    h = fit_homography(src, src + [3.0, -2.0])
    assert h == pytest.approx(np.array([[1, 0, 3], [0, 1, -2], [0, 0, 1]]), abs=1e-12)
    collinear = np.array([[0, 0], [1, 1], [2, 2], [5, 0]], dtype=float)
    assert fit_homography(collinear, collinear) is None
    assert fit_homography(src[:3], src[:3]) is None


@st.composite
def homographies(draw) -> np.ndarray:
    a = draw(st.floats(0.6, 1.4))
    theta = draw(st.floats(-math.pi, math.pi))
    shear = draw(st.floats(-0.3, 0.3))
    p = [draw(st.floats(-4e-4, 4e-4)), draw(st.floats(-4e-4, 4e-4))]
    c, s = math.cos(theta), math.sin(theta)
    h = np.array([[a * c, -a * s + shear, draw(st.floats(-100, 100))],
                  [a * s, a * c, draw(st.floats(-100, 100))], [p[0], p[1], 1.0]])
    return h


@SETTINGS
@given(homographies(), st.integers(8, 150), st.floats(0.0, 1.0), st.integers(0, 2**32 - 1))
def test_ransac_homography_exact_recovery(h: np.ndarray, n_in: int, outlier_share: float, seed: int) -> None:
    n_out = int(outlier_share * n_in)  # up to 50 % outliers: 2000 trials give > 99.9 % confidence
    rng = np.random.default_rng(seed)
    src = rng.uniform(0, 640, (n_in + n_out, 2))
    dst = project(h, src)
    dst[n_in:] += rng.uniform(30, 200, (n_out, 2)) * rng.choice([-1, 1], (n_out, 2))
    found = find_homography(src, dst, threshold=3.0, rng=seed)
    assert found.inliers.tolist() == [True] * n_in + [False] * n_out
    assert _same_up_to_scale(found.model, h) < 1e-8
    assert found.model[2, 2] == pytest.approx(1.0)


# --- fundamental and essential ---------------------------------------------------------------------


def _two_views(seed: int, n: int, rotation: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    world = rng.uniform([-3, -2, 4], [3, 2, 12], (n, 3))
    cam2 = world @ rotation.T + t
    x1 = world @ K.T
    x2 = cam2 @ K.T
    return x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]


def _far_from_epipolar(
    f: np.ndarray, x1: np.ndarray, rng: np.random.Generator, n: int
) -> tuple[np.ndarray, np.ndarray]:
    src = rng.uniform(0, 640, (4 * n, 2))
    dst = rng.uniform(0, 640, (4 * n, 2))
    far = sampson_distance(f, src, dst) > 20.0
    return src[far][:n], dst[far][:n]


motions = st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-0.2, 0.2),
                    st.floats(-1, 1), st.floats(-0.3, 0.3), st.floats(-1, 1)).filter(
    lambda m: math.hypot(m[3], m[4], m[5]) > 0.2)


@SETTINGS
@given(motions, st.integers(20, 120), st.floats(0.0, 0.4), st.integers(0, 2**32 - 1))
def test_ransac_fundamental_exact_recovery(motion: tuple, n_in: int, outlier_share: float, seed: int) -> None:
    n_out = int(outlier_share * n_in)  # 8-point samples: keep >= 70 % inliers
    rotation, t = _rotation(*motion[:3]), np.array(motion[3:])
    x1, x2 = _two_views(seed, n_in, rotation, t)
    truth = np.linalg.inv(K).T @ _skew(t) @ rotation @ np.linalg.inv(K)
    o1, o2 = _far_from_epipolar(truth, x1, np.random.default_rng(seed + 1), n_out)
    # noise-free data: a tight band, since near-degenerate motions (straight ahead) let a wrong
    # model pass within a pixel of every true pair
    found = find_fundamental(np.vstack([x1, o1]), np.vstack([x2, o2]), threshold=0.05, rng=seed)
    assert found.inliers.tolist() == [True] * n_in + [False] * len(o1)
    assert _same_up_to_scale(found.model, truth) < 1e-6
    assert np.linalg.matrix_rank(found.model, tol=1e-9) == 2


def test_fit_essential_five_point_contains_the_truth() -> None:
    rotation, t = _rotation(0.05, 0.1, -0.02), np.array([0.3, 0.05, 0.1])
    x1, x2 = _two_views(1, 5, rotation, t)
    n1 = (x1 - K[:2, 2]) / 500.0
    n2 = (x2 - K[:2, 2]) / 500.0
    solutions = fit_essential(n1, n2)
    assert min(_same_up_to_scale(e, _skew(t) @ rotation) for e in solutions) < 1e-9


@SETTINGS
@given(motions, st.integers(20, 100), st.integers(0, 30), st.integers(0, 2**32 - 1))
def test_ransac_essential_exact_recovery(motion: tuple, n_in: int, n_out: int, seed: int) -> None:
    rotation, t = _rotation(*motion[:3]), np.array(motion[3:])
    x1, x2 = _two_views(seed, n_in, rotation, t)
    truth_f = np.linalg.inv(K).T @ _skew(t) @ rotation @ np.linalg.inv(K)
    o1, o2 = _far_from_epipolar(truth_f, x1, np.random.default_rng(seed + 1), n_out)
    found = find_essential(np.vstack([x1, o1]), np.vstack([x2, o2]), K, threshold=0.05, rng=seed)
    assert found.inliers.tolist() == [True] * n_in + [False] * len(o1)
    assert _same_up_to_scale(found.model.essential, _skew(t) @ rotation) < 1e-6
    assert found.model.rotation == pytest.approx(rotation, abs=1e-6)
    assert found.model.translation == pytest.approx(t / np.linalg.norm(t), abs=1e-6)


def test_essential_rejects_points_behind_the_cameras() -> None:
    rotation, t = _rotation(0.02, -0.05, 0.01), np.array([0.8, 0.1, 0.2])
    x1, x2 = _two_views(7, 60, rotation, t)
    # points behind both cameras satisfy the epipolar constraint exactly but are not physical
    world = np.random.default_rng(8).uniform([-3, -2, -12], [3, 2, -4], (15, 3))
    b1, b2 = world @ K.T, (world @ rotation.T + t) @ K.T
    b1, b2 = b1[:, :2] / b1[:, 2:], b2[:, :2] / b2[:, 2:]
    truth_f = np.linalg.inv(K).T @ _skew(t) @ rotation @ np.linalg.inv(K)
    assert sampson_distance(truth_f, b1, b2).max() < 1e-9
    found = find_essential(np.vstack([x1, b1]), np.vstack([x2, b2]), K, threshold=0.5)
    assert found.inliers.tolist() == [True] * 60 + [False] * 15
    assert found.model.translation == pytest.approx(t / np.linalg.norm(t), abs=1e-6)


# --- motion prior --------------------------------------------------------------------------------


def test_camera_motion_from_odometry_hand_computed() -> None:
    # forward 1 m: the camera looks along base x, so scene points come 1 m closer (z - 1)
    rotation, t = camera_motion_from_odometry(1.0, 0.0, 0.0)
    assert rotation == pytest.approx(np.eye(3)) and t == pytest.approx([0.0, 0.0, -1.0])
    # 90 deg left turn: a point straight ahead ends up on the camera's right (+x)
    rotation, t = camera_motion_from_odometry(0.0, 0.0, math.pi / 2)
    assert rotation @ [0.0, 0.0, 1.0] == pytest.approx([1.0, 0.0, 0.0]) and t == pytest.approx(np.zeros(3))
    # 0.5 m to the left: points move to the camera's right
    _, t = camera_motion_from_odometry(0.0, 0.5, 0.0)
    assert t == pytest.approx([0.5, 0.0, 0.0])


def test_motion_prior_rejects_physically_impossible_matches() -> None:
    rotation, t = camera_motion_from_odometry(0.5, 0.0, 0.05)
    x1, x2 = _two_views(3, 50, rotation, t)
    assert motion_prior_mask(x1, x2, rotation, t, K).all()
    # odometry a little off (heading 0.6 deg, distance 10 %): true matches still pass
    noisy_r, noisy_t = camera_motion_from_odometry(0.55, 0.0, 0.06)
    assert motion_prior_mask(x1, x2, noisy_r, noisy_t, K).all()
    # swapped in time (driving backwards: points converge to the focus of expansion) and
    # shuffled matches are impossible for a robot driving forward, once the parallax exceeds
    # the tolerance
    rotation, t = camera_motion_from_odometry(2.0, 0.0, 0.0)
    x1, x2 = _two_views(3, 200, rotation, t)
    moved = np.sqrt(((x2 - x1) ** 2).sum(axis=1)) > 2 * 20.0
    assert moved.sum() > 20
    assert motion_prior_mask(x1, x2, rotation, t, K).all()
    assert not motion_prior_mask(x2[moved], x1[moved], rotation, t, K).any()
    # straight ahead the epipolar lines run radially from the principal point: a match moved
    # 50 px across its line is off every physical ray (away from the focus of expansion, where
    # a small move of x1 already swings the line by that much)
    radial = x2 - K[:2, 2]
    across = np.column_stack([-radial[:, 1], radial[:, 0]]) / np.linalg.norm(radial, axis=1, keepdims=True)
    off_centre = np.linalg.norm(x1 - K[:2, 2], axis=1) > 100
    assert off_centre.sum() > 50
    assert not motion_prior_mask(x1[off_centre], (x2 + 50.0 * across)[off_centre], rotation, t, K).any()


def test_motion_prior_pure_rotation_and_in_find_essential() -> None:
    rotation, t = camera_motion_from_odometry(0.0, 0.0, 0.1)
    x1, x2 = _two_views(4, 40, rotation, np.zeros(3))
    assert motion_prior_mask(x1, x2, rotation, t, K, threshold=1.0).all()
    assert not motion_prior_mask(x1, x1 + 60.0, rotation, t, K, threshold=20.0).any()
    # with a prior, a consistent-looking outlier set behind the camera never reaches RANSAC
    rotation, t = camera_motion_from_odometry(0.6, 0.05, 0.04)
    x1, x2 = _two_views(5, 40, rotation, t)
    found = find_essential(np.vstack([x1, x2[:5]]), np.vstack([x2, x1[:5]]), K, prior=(rotation, t))
    assert found.inliers.tolist() == [True] * 40 + [False] * 5
