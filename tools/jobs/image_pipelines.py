"""The perceive job's three image pipelines: one decoded frame in, its detections as ImageMarkers out.

- color:    ``<image>/color_ellipses`` (LINE_LIST, each region's equivalent ellipse) and
            ``<image>/color_centroids`` (POINTS);
- markers:  ``<image>/aruco_outlines`` (LINE_LIST, each marker's quadrilateral) and, with a
            marker size and the camera's CameraInfo, each marker's pose on ``/tf`` as
            ``<camera frame> -> aruco_<id>``, and, once ``/tf_static`` places the camera on the
            robot, the markers as landmark observations in ``base_link`` on ``/landmarks``;
- features: ``<image>/keypoints`` (POINTS) and ``<image>/keypoint_orientations`` (LINE_LIST,
            from each keypoint a tick of half its size along its orientation).

Each frame gets exactly one marker per topic (all detections of the frame in it, an empty one
when there are none), since Foxglove keeps the latest ImageMarker per topic.
"""

from __future__ import annotations

import collections
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.frames import BASE_FRAME, FrameTree
from trundle.logs.paths import input_file
from trundle.logs.topics import LANDMARK_TOPIC, TF_TOPIC
from trundle.perception.color import ColorSegmentation, HsvTemplate, segment_color, template_histograms
from trundle.perception.landmarks import marker_observation
from trundle.perception.markers import MarkerDetector, marker_pose
from trundle.tools.jobs.image_markers import (
    CYAN,
    GREEN,
    MAGENTA,
    YELLOW,
    closed_line_list,
    ellipse_outline,
    image_marker,
)

Detections = tuple[int, list[tuple[str, m.Message]]]   # count and the (topic, message) pairs to write
Triple = tuple[float, float, float]


def _read_image(path: str | Path, flags: int) -> np.ndarray:
    """The image file at ``path`` read with OpenCV ``flags``; an unreadable one is a UserError."""
    image = cv2.imread(str(input_file(path, "image")), flags)
    if image is None:
        raise UserError(f"cannot read image {path}")
    return image


class Pipeline:
    """One image pipeline: ``process`` a decoded frame into detections, ``summary`` at the end."""

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray,
                camera: m.CameraInfo | None) -> Detections:
        """The detections in ``image`` (decoded from ``msg`` on ``topic``; ``camera`` its calibration, if known)."""
        raise NotImplementedError

    def summary(self) -> dict[str, Any]:
        """The pipeline's totals over all frames processed, for the job's report."""
        raise NotImplementedError

    def static_transforms(self, msg: m.TFMessage) -> None:
        """A ``/tf_static`` message of the log (where the sensors sit on the robot); most pipelines ignore it."""


class ColorPipeline(Pipeline):
    """Regions of one colour: HSV bounds (fast path) or a template's histograms.

    HSV is textbook HSV (H degrees, S and V in [0, 1]); an upper H below the lower wraps through
    0. ``template_mask`` selects the template's pixels (non-zero); ``bins`` histogram bins per
    channel; ``weights`` the H, S, V back-projection weights; ``level`` the likeness threshold
    0..255; ``blur_sigma`` the likeness blur (px); areas in px; ``max_aspect`` the largest ellipse
    axis ratio a/b; ``min_extent`` the smallest fraction of its box a region fills.
    """

    def __init__(self, lower: Triple | None = None, upper: Triple | None = None, template: str | Path | None = None,
                 template_mask: str | Path | None = None, bins: int = 32, weights: Triple = (0.5, 0.3, 0.2),
                 level: int = 128, blur_sigma: float = 2.0, min_area: int = 50, max_area: int | None = None,
                 max_aspect: float | None = None, min_extent: float = 0.0) -> None:
        if (lower is None) != (upper is None):
            raise UserError("--lower and --upper go together")
        if (lower is None) == (template is None):
            raise UserError("the color pipeline needs either --template or --lower and --upper")
        if not 1 <= bins <= 180:
            raise UserError("--bins must be 1..180")
        if min(weights) < 0 or sum(weights) <= 0:
            raise UserError("--weights must be non-negative and not all zero")
        self.template: HsvTemplate | None = None
        if template:
            mask = _read_image(template_mask, cv2.IMREAD_GRAYSCALE) if template_mask else None
            try:
                self.template = template_histograms(_read_image(template, cv2.IMREAD_COLOR), mask, bins)
            except ValueError as error:
                raise UserError(f"template: {error}") from None
        self.options: dict[str, Any] = dict(lower=lower, upper=upper, weights=weights, blur_sigma=blur_sigma,
                                            level=level, min_area=min_area, max_area=max_area, max_aspect=max_aspect,
                                            min_extent=min_extent)
        self.regions = 0

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray,
                camera: m.CameraInfo | None) -> Detections:
        """Each region's ellipse outline and centroid."""
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        found: ColorSegmentation = segment_color(bgr, self.template, **self.options)
        self.regions += len(found.regions)
        outlines = [ellipse_outline(r.centroid, r.a, r.b, r.theta) for r in found.regions]
        centroids = np.array([r.centroid for r in found.regions]).reshape(-1, 2)
        return len(found.regions), [
            (f"{topic}/color_ellipses",
             image_marker(msg, "color_ellipses", m.LINE_LIST, closed_line_list(outlines), GREEN)),
            (f"{topic}/color_centroids", image_marker(msg, "color_centroids", m.POINTS, centroids, YELLOW, 4.0))]

    def summary(self) -> dict[str, Any]:
        """The number of regions found."""
        return {"regions": self.regions}


class MarkerPipeline(Pipeline):
    """ArUco ids and corners of ``dictionary`` (``refinement``: subpix, none, contour, apriltag);
    poses when the printed marker side ``marker_size`` (m) and the camera's CameraInfo are known."""

    def __init__(self, dictionary: str = "DICT_6X6_250", refinement: str = "subpix",
                 marker_size: float | None = None) -> None:
        if marker_size is not None and marker_size <= 0:
            raise UserError("--marker-size must be positive (metres)")
        self.detector = MarkerDetector(dictionary, refinement)
        self.size = marker_size
        self.frames = FrameTree()
        self.ids: collections.Counter[int] = collections.Counter()
        self.poses = 0
        self.landmark_messages = 0
        self.poses_without_mount = 0
        self.too_small = 0
        self.poses_missing_camera_info = 0
        self.poses_failed = 0

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray,
                camera: m.CameraInfo | None) -> Detections:
        """Each marker's outline, and its pose on ``/tf`` when it can be had."""
        markers = self.detector.detect(image)
        self.ids.update(marker.id for marker in markers)
        out: list[tuple[str, m.Message]] = [(f"{topic}/aruco_outlines", image_marker(
            msg, "aruco_outlines", m.LINE_LIST, closed_line_list([k.corners for k in markers]), MAGENTA))]
        if self.size is None or not markers:
            return len(markers), out
        if camera is None:
            self.poses_missing_camera_info += len(markers)
            return len(markers), out
        transforms, observations = [], []
        frame = msg.frame_id or camera.frame_id
        camera_in_base = self.frames.try_transform(BASE_FRAME, frame)
        for marker in markers:
            try:
                pose = marker_pose(marker, camera, self.size)
            except ValueError:      # no solver found a pose (degenerate corners)
                self.poses_failed += 1
                continue
            transforms.append(m.TransformStamped(msg.stamp_ns, frame, f"aruco_{marker.id}",
                                                 pose.translation, pose.quaternion()))
            landmark = None if camera_in_base is None else marker_observation(marker, pose, camera, self.size,
                                                                               camera_in_base)
            if landmark is not None:
                observations.append(landmark)
            elif camera_in_base is not None:
                self.too_small += 1
        self.poses += len(transforms)
        if camera_in_base is None:
            self.poses_without_mount += len(transforms)
        if transforms:
            out.append((TF_TOPIC, m.TFMessage(tuple(transforms))))
        if observations:
            out.append((LANDMARK_TOPIC, m.LandmarkList(msg.stamp_ns, BASE_FRAME, tuple(observations))))
            self.landmark_messages += 1
        return len(markers), out

    def static_transforms(self, msg: m.TFMessage) -> None:
        """Keep the camera's mount for the markers' landmark observations."""
        self.frames.add_static(msg)

    def summary(self) -> dict[str, Any]:
        """Markers seen per id, poses found, failed and lacking a CameraInfo, and landmark messages
        written (and poses without them for want of the camera's mount on ``/tf_static``, or for
        markers too small in the image to place)."""
        return {"marker_ids": {str(k): v for k, v in sorted(self.ids.items())}, "markers": sum(self.ids.values()),
                "poses": self.poses, "poses_missing_camera_info": self.poses_missing_camera_info,
                "poses_failed": self.poses_failed, "landmark_messages": self.landmark_messages,
                "poses_without_camera_mount": self.poses_without_mount, "too_small_for_landmarks": self.too_small}


class FeaturePipeline(Pipeline):
    """Local features from ``trundle.perception.features.detect(image, method, **params)``."""

    def __init__(self, method: str = "orb", params: Mapping[str, Any] | None = None) -> None:
        try:
            from trundle.perception.features import METHODS, available, detect
        except ImportError:
            raise UserError("the features pipeline needs trundle.perception.features, which is not installed") from None
        if method not in METHODS:
            raise UserError(f"unknown feature detector {method!r} (choose from {', '.join(METHODS)})")
        if not available(method):
            raise UserError(f"{method} is not in this OpenCV build (cv2 {cv2.__version__})")
        self.detect = detect
        self.method = method
        self.params: dict[str, Any] = dict(params or {})
        self.keypoints = 0

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray,
                camera: m.CameraInfo | None) -> Detections:
        """The keypoints, and a tick along each oriented keypoint."""
        keypoints = self.detect(image, self.method, **self.params)
        self.keypoints += len(keypoints)
        oriented = np.isfinite(keypoints.angle)
        tips = keypoints.xy[oriented] + 0.5 * keypoints.size[oriented, None] * np.column_stack(
            [np.cos(keypoints.angle[oriented]), np.sin(keypoints.angle[oriented])])
        ticks = np.stack([keypoints.xy[oriented], tips], axis=1).reshape(-1, 2)
        return len(keypoints), [
            (f"{topic}/keypoints", image_marker(msg, "keypoints", m.POINTS, keypoints.xy, CYAN, 3.0)),
            (f"{topic}/keypoint_orientations",
             image_marker(msg, "keypoint_orientations", m.LINE_LIST, ticks, CYAN, 1.0))]

    def summary(self) -> dict[str, Any]:
        """The number of keypoints and the detector."""
        return {"keypoints": self.keypoints, "method": self.method}


PIPELINES: dict[str, type[Pipeline]] = {"color": ColorPipeline, "markers": MarkerPipeline, "features": FeaturePipeline}
