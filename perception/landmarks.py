"""ArUco markers as landmark observations: the marker's pose in the robot frame with a covariance
propagated from the corners' pixel noise, so it grows with distance and viewing angle.

The pose solver (``trundle.perception.markers.marker_pose``) gives the marker in the camera's
optical frame. The corners' pixel noise ``sigma`` reaches the pose through the projection's
Jacobian ``J`` (8 pixel coordinates by the 6 pose parameters, from ``cv2.projectPoints``):
``cov = sigma^2 (J^T J)^-1``, the first-order covariance of a least-squares PnP fit. A far marker
is small in the image and a slanted one foreshortened, so the same pixel noise moves the pose more;
no separate distance model is needed. ``sigma`` is the larger of ``pixel_sigma`` and the fit's own
RMS reprojection error, divided by the cosine of the viewing angle: a slanted marker's edges
foreshorten and its corners smear along them (the projection alone makes a slanted marker's yaw
*better* known, and barely changes its position). The camera's pose on the robot (the tf tree of
:mod:`trundle.logs.frames`: camera mount and optical frame) carries position and covariance into
the robot frame (``base_link``): the observation's planar position and its landmark yaw, the
direction the marker faces.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from trundle.logs.messages import CameraInfo, LandmarkObservation
from trundle.perception.markers import Marker, MarkerPose, marker_object_points

PIXEL_SIGMA = 1.0  # px: corner noise of a detected marker seen face-on (sub-pixel refinement, JPEG, blur)
MIN_SIDE_PX = 30.0  # px: a smaller marker's pose is too rough for its first-order covariance (ambiguity, bias)
MIN_VIEWING_COSINE = 0.25  # beyond 75 deg off the normal the noise stops growing (detection fails first)


def viewing_cosine(pose: MarkerPose) -> float:
    """Cosine of the angle between the marker's face normal and the line of sight to its centre."""
    sight = -pose.translation / max(float(np.linalg.norm(pose.translation)), 1e-12)
    return float(np.clip(pose.rotation[:, 2] @ sight, 0.0, 1.0))


def corner_sigma(pose: MarkerPose, pixel_sigma: float = PIXEL_SIGMA) -> float:
    """Pixel noise of a marker's corners: ``pixel_sigma`` (at least the fit's RMS reprojection error)
    divided by the viewing cosine (at least ``MIN_VIEWING_COSINE``), since a slanted marker's edges
    foreshorten and blur into its corners."""
    return max(float(pixel_sigma), float(pose.error)) / max(viewing_cosine(pose), MIN_VIEWING_COSINE)


def pose_covariance(marker: Marker, pose: MarkerPose, camera: CameraInfo, size: float,
                    pixel_sigma: float = PIXEL_SIGMA) -> np.ndarray:
    """6x6 covariance of (Rodrigues vector, translation m) of a marker pose from its corners' noise
    (:func:`corner_sigma`) through the projection's Jacobian."""
    _, jacobian = cv2.projectPoints(marker_object_points(size), pose.rvec.reshape(3, 1), pose.translation.reshape(3, 1),
                                    camera.k, camera.d)
    j = jacobian[:, :6]
    return corner_sigma(pose, pixel_sigma) ** 2 * np.linalg.inv(j.T @ j)


def marker_observation(
    marker: Marker,
    pose: MarkerPose,
    camera: CameraInfo,
    size: float,
    camera_in_base: np.ndarray,
    pixel_sigma: float = PIXEL_SIGMA,
    min_side_px: float = MIN_SIDE_PX,
) -> LandmarkObservation | None:
    """The marker as a landmark seen from the robot: id, planar position, range, bearing and their
    covariance, its full pose and the variance of the yaw it faces, all in the frame of
    ``camera_in_base`` (4x4 pose of the image's optical frame in the robot frame). None when the
    marker's shortest side in the image is under ``min_side_px``: the pose of a marker that small
    (measured in the demo: 0.25 m markers beyond about 4.5 m) is off by more than its first-order
    covariance admits (the two IPPE solutions come close, the corners' quantisation biases it); None
    too for a pose or covariance that is not finite."""
    if float(np.hypot(*(np.roll(marker.corners, -1, axis=0) - marker.corners).T).min()) < min_side_px:
        return None
    if not (np.all(np.isfinite(pose.rotation)) and np.all(np.isfinite(pose.translation))):
        return None   # a solver that failed gives no landmark, never NaN data
    try:
        covariance = pose_covariance(marker, pose, camera, size, pixel_sigma)
    except np.linalg.LinAlgError:   # corners that do not fix the pose (degenerate)
        return None
    if not np.all(np.isfinite(covariance)):
        return None
    rotation, shift = camera_in_base[:3, :3], camera_in_base[:3, 3]
    position = rotation @ pose.translation + shift
    position_cov = (rotation @ covariance[3:, 3:] @ rotation.T)[:2, :2]
    orientation = rotation @ pose.rotation

    def facing(rvec: np.ndarray) -> float:
        normal = rotation @ cv2.Rodrigues(rvec)[0][:, 2]   # the marker's z axis points out of its face
        return math.atan2(normal[1], normal[0])

    yaw = facing(pose.rvec)
    step = 1e-6
    gradient = np.array([math.remainder(facing(pose.rvec + step * e) - yaw, 2 * math.pi) / step for e in np.eye(3)])
    yaw_variance = float(gradient @ covariance[:3, :3] @ gradient)
    return LandmarkObservation.from_position(str(marker.id), position[:2], position_cov, position,
                                             Rotation.from_matrix(orientation).as_quat(), max(yaw_variance, 1e-12))
