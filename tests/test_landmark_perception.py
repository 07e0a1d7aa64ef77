"""Landmark observations from perception: ArUco marker poses in the robot frame with a covariance
that matches their Monte-Carlo spread and grows with distance and viewing angle; corners of
laser walls where two lines meet."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from planar_world import ROOM, scan
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from trundle.drivers.camera import OPTICAL_ROTATION
from trundle.logs import messages as m
from trundle.logs.frames import FrameTree
from trundle.perception.landmarks import marker_observation, viewing_cosine
from trundle.perception.markers import Marker, marker_object_points, marker_pose
from trundle.perception.scan_features import corner_observations, corners

CAMERA = m.CameraInfo(0, "camera_optical", 480, 640, "plumb_bob", np.zeros(5),
                      [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = 0.25


def _frames() -> FrameTree:
    """base_link -> camera 0.2 m ahead, 0.4 m up, turned 0.1 rad left -> camera_optical (REP 103)."""
    frames = FrameTree()
    frames.add_static(m.TFMessage((m.TransformStamped.planar(0, "base_link", "camera", 0.2, 0.0, 0.1, z=0.4),
                            m.TransformStamped(0, "camera", "camera_optical", (0, 0, 0), OPTICAL_ROTATION))))
    return frames


def _marker_in_camera(distance: float, facing_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A marker ``distance`` m in front of the optical centre, its face turned ``facing_deg`` from the camera."""
    a = math.radians(facing_deg)
    # marker axes in the optical frame: x right, y up, z out of the face towards the camera
    # (tilted 10 deg and off the optical axis: IPPE's closed form is degenerate for a marker centred and
    # upright in the image, which real views never are exactly)
    rotation = Rotation.from_euler("yx", [a, math.radians(10.0)]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    return rotation, np.array([0.3, -0.15, distance])


def _detected(rotation: np.ndarray, translation: np.ndarray, noise_px: float = 0.0,
              rng: np.random.Generator | None = None) -> Marker:
    pixels, _ = cv2.projectPoints(
        marker_object_points(SIZE), cv2.Rodrigues(rotation)[0], translation, CAMERA.k, CAMERA.d
    )
    pixels = pixels.reshape(4, 2)
    if noise_px:
        pixels = pixels + (rng or np.random.default_rng()).normal(0, noise_px, pixels.shape)
    return Marker(23, pixels)


def test_the_camera_optical_frame_chains_to_the_robot_frame():
    pose = _frames().transform("base_link", "camera_optical")
    np.testing.assert_allclose(pose[:3, 3], [0.2, 0.0, 0.4])
    # the optical z axis (forward) is the camera's x axis, turned 0.1 rad
    np.testing.assert_allclose(pose[:3, 2], [math.cos(0.1), math.sin(0.1), 0.0], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 1], [0.0, 0.0, -1.0], atol=1e-12)   # optical y is down
    assert _frames().try_transform("base_link", "nowhere") is None


def test_marker_observation_is_the_marker_in_the_robot_frame():
    rotation, translation = _marker_in_camera(3.0, 30.0)
    marker = _detected(rotation, translation)
    pose = marker_pose(marker, CAMERA, SIZE)
    base = _frames().transform("base_link", "camera_optical")
    o = marker_observation(marker, pose, CAMERA, SIZE, base)
    truth = base[:3, :3] @ translation + base[:3, 3]
    np.testing.assert_allclose(o.translation, truth, atol=1e-6)
    assert (o.range, o.bearing) == pytest.approx((math.hypot(*truth[:2]), math.atan2(truth[1], truth[0])), abs=1e-6)
    assert o.id == "23" and o.oriented
    # the marker faces the camera turned by 30 deg: its normal points back at the robot, rotated by 0.1 + 30 deg
    normal = (base[:3, :3] @ rotation)[:, 2]
    np.testing.assert_allclose(Rotation.from_quat(o.rotation).as_matrix()[:, 2], normal, atol=1e-6)


def test_covariance_matches_the_monte_carlo_spread():
    rng = np.random.default_rng(5)
    rotation, translation = _marker_in_camera(3.0, 20.0)
    base = _frames().transform("base_link", "camera_optical")
    exact = _detected(rotation, translation)
    truth = marker_observation(exact, marker_pose(exact, CAMERA, SIZE), CAMERA, SIZE, base, pixel_sigma=0.5)
    sigma = 0.5 / viewing_cosine(marker_pose(exact, CAMERA, SIZE))   # the noise the model expects at this angle
    samples = []
    for _ in range(400):
        marker = _detected(rotation, translation, sigma, rng)
        samples.append(marker_observation(marker, marker_pose(marker, CAMERA, SIZE), CAMERA, SIZE, base,
                                          pixel_sigma=0.5).translation[:2])
    error = np.array(samples) - truth.translation[:2]
    d2 = np.einsum("ni,ij,nj->n", error, np.linalg.inv(truth.position_covariance()), error)
    # first order: 95 % of the samples inside the 95 % ellipse (a few pose-ambiguity flips make tails)
    assert 0.88 <= np.mean(d2 <= chi2.ppf(0.95, 2)) <= 0.99
    ratio = scipy.linalg.eigh(np.cov(error[d2 <= chi2.ppf(0.999, 2)].T), truth.position_covariance(), eigvals_only=True)
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_covariance_grows_with_distance_and_viewing_angle():
    """Farther: position and yaw less certain. More slanted: the position less certain (the corner noise grows)."""
    base = _frames().transform("base_link", "camera_optical")

    def observed(distance, facing):
        rotation, translation = _marker_in_camera(distance, facing)
        marker = _detected(rotation, translation)
        return marker_observation(marker, marker_pose(marker, CAMERA, SIZE), CAMERA, SIZE, base, min_side_px=0.0)

    near, middle, far = (observed(d, 20.0) for d in (1.0, 2.0, 4.0))
    assert (
        np.trace(near.position_covariance())
        < np.trace(middle.position_covariance())
        < np.trace(far.position_covariance())
    )
    assert near.yaw_variance < middle.yaw_variance < far.yaw_variance
    straight, slanted, steep = (observed(3.0, f) for f in (20.0, 45.0, 70.0))
    assert np.trace(straight.position_covariance()) < np.trace(slanted.position_covariance()) \
        < np.trace(steep.position_covariance())


def test_a_marker_too_small_in_the_image_is_no_landmark():
    """0.25 m at 5 m is 25 px with this camera: detected, but its pose too rough to place a landmark."""
    base = _frames().transform("base_link", "camera_optical")
    rotation, translation = _marker_in_camera(5.0, 0.0)
    marker = _detected(rotation, translation)
    assert marker_observation(marker, marker_pose(marker, CAMERA, SIZE), CAMERA, SIZE, base) is None
    assert marker_observation(marker, marker_pose(marker, CAMERA, SIZE), CAMERA, SIZE, base, min_side_px=20) is not None


def test_a_failed_pose_gives_no_landmark_not_nan():
    rotation, translation = _marker_in_camera(2.0, 10.0)
    marker = _detected(rotation, translation)
    good = marker_pose(marker, CAMERA, SIZE)
    broken = dataclasses.replace(good, translation=np.full(3, np.nan))
    assert marker_observation(marker, broken, CAMERA, SIZE, _frames().transform("base_link", "camera_optical")) is None


def test_corners_are_where_walls_meet():
    """Every corner found lies within 3 cm (and 5 sigma) of a true junction of two walls of the room
    (an end of one on the other: corners and T-junctions), and at least four are found from the middle of it."""
    pose = np.array([0.5, 0.5, 0.3])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    laser = np.array([pose[0] + 0.1 * c, pose[1] + 0.1 * s, pose[2]])   # 0.1 m ahead of base_link
    found = corner_observations(scan(ROOM, laser, beams=1080, noise_m=0.005, seed=1), mount=(0.1, 0.0, 0.0))
    junctions = np.array([end for k, wall in enumerate(ROOM) for end in (wall[:2], wall[2:])
                          if any(_on_segment(end, other) for j, other in enumerate(ROOM) if j != k)])
    local = (junctions - pose[:2]) @ np.array([[c, -s], [s, c]])   # map -> robot frame
    assert len(found) >= 4
    for o in found:
        error = o.translation[:2] - local[np.argmin(np.hypot(*(local - o.translation[:2]).T))]
        assert np.hypot(*error) < 0.03
        assert error @ np.linalg.solve(o.position_covariance(), error) < 25.0


def _on_segment(point: np.ndarray, wall: np.ndarray) -> bool:
    a, b = wall[:2], wall[2:]
    u = np.clip((point - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return bool(np.hypot(*(a + u * (b - a) - point)) < 1e-9)


def test_a_straight_wall_has_no_corner():
    walls = np.array([[-10.0, 2.0, 10.0, 2.0]])
    assert corners(scan(walls, np.zeros(3), beams=720, noise_m=0.003)) == []


@settings(max_examples=60, deadline=None)
@given(st.lists(st.one_of(st.floats(0.0, 40.0), st.sampled_from([math.inf, -math.inf, math.nan])), max_size=300))
def test_corners_of_any_scan_have_positive_covariance(ranges):
    n = len(ranges)
    laser = m.LaserScan(0, "laser", -math.pi, -math.pi + 0.02 * max(n - 1, 0), 0.02, 0.0, 0.1, 0.05, 30.0, ranges)
    for o in corner_observations(laser):
        assert np.all(np.isfinite(o.covariance)) and np.all(np.linalg.eigvalsh(o.covariance) > 0)
