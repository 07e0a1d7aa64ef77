"""`trundle perceive LOG --pipeline color|markers|features -o OUT.mcap`: detections over a log's images.

Every image (sensor_msgs/Image or CompressedImage) of the chosen topics goes through one
pipeline; the detections are written as visualization_msgs/ImageMarker that Foxglove draws
over the image, stamped and framed like the image. Foxglove keeps the latest ImageMarker per
topic, so each frame gets exactly one marker per topic (all detections of the frame in it, an
empty one when there are none):

- color:    ``<image>/color_ellipses`` (LINE_LIST, each region's equivalent ellipse) and
            ``<image>/color_centroids`` (POINTS);
- markers:  ``<image>/aruco_outlines`` (LINE_LIST, each marker's quadrilateral) and, with
            ``--marker-size`` and the camera's CameraInfo in the log, each marker's pose on
            ``/tf`` as ``<camera frame> -> aruco_<id>``;
- features: ``<image>/keypoints`` (POINTS) and ``<image>/keypoint_orientations`` (LINE_LIST,
            from each keypoint a tick of half its size along its orientation).

The images and camera infos are copied into the output (unless ``--no-images``), so it opens
on its own. A summary (text, or one JSON object with ``--json``) ends the run.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import UserError
from trundle.logs.reader import LogReader
from trundle.logs.writer import Logger
from trundle.perception.color import ColorSegmentation, HsvTemplate, segment_color, template_histograms
from trundle.perception.images import decode_image
from trundle.perception.markers import MarkerDetector, marker_pose
from trundle.tools.cli.progress import Progress

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
GREEN, YELLOW, CYAN, MAGENTA = (0.0, 1.0, 0.0, 1.0), (1.0, 1.0, 0.0, 1.0), (0.0, 1.0, 1.0, 1.0), (1.0, 0.0, 1.0, 1.0)
ELLIPSE_VERTICES = 36
MAX_QUEUED = 500            # wait for the logger rather than let it drop messages
Detections = tuple[int, list[tuple[str, m.Message]]]   # count and the (topic, message) pairs to write


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("file", help="MCAP log with images")
    p.add_argument("--pipeline", required=True, choices=("color", "markers", "features"))
    p.add_argument("-o", "--output", required=True, help="output MCAP file")
    p.add_argument("--topics", nargs="+", help="image topics (default: every Image and CompressedImage topic)")
    p.add_argument("--no-images", action="store_true", help="write only the detections, not the images")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    c = p.add_argument_group("color pipeline (textbook HSV: H degrees, S and V in [0, 1])")
    c.add_argument("--lower", help="fast path: lower HSV bound, e.g. 15,0.6,0.5")
    c.add_argument("--upper", help="fast path: upper HSV bound, e.g. 45,1,1 (H below lower wraps through 0)")
    c.add_argument("--template", help="image of the colour (back-projection path)")
    c.add_argument("--template-mask", help="mask image selecting the template's pixels (non-zero)")
    c.add_argument("--bins", type=int, default=32, help="histogram bins per channel (default 32)")
    c.add_argument("--weights", default="0.5,0.3,0.2", help="H,S,V back-projection weights (default 0.5,0.3,0.2)")
    c.add_argument("--level", type=int, default=128, help="likeness threshold 0..255 (default 128)")
    c.add_argument("--blur", type=float, default=2.0, help="Gaussian blur sigma of the likeness, px (default 2)")
    c.add_argument("--min-area", type=int, default=50, help="smallest region, px (default 50)")
    c.add_argument("--max-area", type=int, help="largest region, px")
    c.add_argument("--max-aspect", type=float, help="largest ellipse axis ratio a/b")
    c.add_argument("--min-extent", type=float, default=0.0, help="smallest fraction of its box a region fills")
    k = p.add_argument_group("markers pipeline")
    k.add_argument("--dictionary", default="DICT_6X6_250", help="ArUco dictionary (default DICT_6X6_250)")
    k.add_argument("--refinement", default="subpix", help="corner refinement: subpix, none, contour, apriltag")
    k.add_argument("--marker-size", type=float, help="printed marker side in metres (enables poses)")
    k.add_argument("--camera-info", help="CameraInfo topic (default: <camera namespace>/camera_info)")
    f = p.add_argument_group("features pipeline")
    f.add_argument("--method", default="orb", help="detector name known to trundle.perception.features (default orb)")
    f.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="detector parameter (repeatable)")
    p.set_defaults(func=run)


def _triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise UserError(f"{name} needs three comma-separated numbers, got {text!r}")
    return values  # type: ignore[return-value]


def _value(text: str) -> Any:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def _read_image(path: str, flags: int) -> np.ndarray:
    image = cv2.imread(path, flags)
    if image is None:
        raise UserError(f"cannot read image {path}")
    return image


def camera_info_topic(image_topic: str) -> str:
    """``/ns/image_raw/compressed`` -> ``/ns/camera_info`` (the image_transport convention)."""
    namespace = image_topic.rsplit("/image", 1)[0] if "/image" in image_topic else image_topic.rsplit("/", 1)[0]
    return f"{namespace}/camera_info"


def _marker(msg: m.CompressedImage | m.Image, ns: str, kind: int, points: np.ndarray,
            color: tuple[float, float, float, float], scale: float = 2.0) -> m.ImageMarker:
    return m.ImageMarker(msg.stamp_ns, msg.frame_id, ns, 0, kind, scale=scale, outline_color=color,
                         points=np.asarray(points, dtype=np.float64).reshape(-1, 2))


def _closed_line_list(polygons: list[np.ndarray]) -> np.ndarray:
    """LINE_LIST points (pairs) drawing each (K, 2) polygon closed."""
    if not polygons:
        return np.zeros((0, 2))
    return np.concatenate([np.stack([p, np.roll(p, -1, axis=0)], axis=1).reshape(-1, 2) for p in polygons])


def ellipse_outline(centre: tuple[float, float], a: float, b: float, theta: float,
                    vertices: int = ELLIPSE_VERTICES) -> np.ndarray:
    """(vertices, 2) points on the ellipse with semi-axes a, b rotated by theta (image coordinates)."""
    t = np.linspace(0.0, 2 * math.pi, vertices, endpoint=False)
    c, s = math.cos(theta), math.sin(theta)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.column_stack([centre[0] + c * x - s * y, centre[1] + s * x + c * y])


class Pipeline:
    """One image pipeline: ``process`` a decoded frame into detections, ``summary`` at the end."""

    def camera_info(self, topic: str, info: m.CameraInfo) -> None:
        """A calibration seen in the log (used by pipelines that need one)."""

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray) -> Detections:
        raise NotImplementedError

    def summary(self) -> dict[str, Any]:
        raise NotImplementedError


class ColorPipeline(Pipeline):
    """Regions of one colour: HSV bounds (fast path) or a template's histograms."""

    def __init__(self, args: argparse.Namespace) -> None:
        lower, upper = _triple(args.lower, "--lower"), _triple(args.upper, "--upper")
        weights = _triple(args.weights, "--weights")
        if (lower is None) != (upper is None):
            raise UserError("--lower and --upper go together")
        if (lower is None) == (args.template is None):
            raise UserError("the color pipeline needs either --template or --lower and --upper")
        if not 1 <= args.bins <= 180:
            raise UserError("--bins must be 1..180")
        if min(weights) < 0 or sum(weights) <= 0:
            raise UserError("--weights must be non-negative and not all zero")
        self.template: HsvTemplate | None = None
        if args.template:
            mask = _read_image(args.template_mask, cv2.IMREAD_GRAYSCALE) if args.template_mask else None
            try:
                self.template = template_histograms(_read_image(args.template, cv2.IMREAD_COLOR), mask, args.bins)
            except ValueError as error:
                raise UserError(f"template: {error}") from None
        self.options = dict(lower=lower, upper=upper, weights=weights, blur_sigma=args.blur, level=args.level,
                            min_area=args.min_area, max_area=args.max_area, max_aspect=args.max_aspect,
                            min_extent=args.min_extent)
        self.regions = 0

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray) -> Detections:
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        found: ColorSegmentation = segment_color(bgr, self.template, **self.options)
        self.regions += len(found.regions)
        outlines = [ellipse_outline(r.centroid, r.a, r.b, r.theta) for r in found.regions]
        centroids = np.array([r.centroid for r in found.regions]).reshape(-1, 2)
        return len(found.regions), [
            (f"{topic}/color_ellipses",
             _marker(msg, "color_ellipses", m.LINE_LIST, _closed_line_list(outlines), GREEN)),
            (f"{topic}/color_centroids", _marker(msg, "color_centroids", m.POINTS, centroids, YELLOW, 4.0))]

    def summary(self) -> dict[str, Any]:
        return {"regions": self.regions}


class MarkerPipeline(Pipeline):
    """ArUco ids and corners; poses when the marker size and the camera's CameraInfo are known."""

    def __init__(self, args: argparse.Namespace) -> None:
        if args.marker_size is not None and args.marker_size <= 0:
            raise UserError("--marker-size must be positive (metres)")
        self.detector = MarkerDetector(args.dictionary, args.refinement)
        self.size = args.marker_size
        self.camera_info_override = args.camera_info
        self.cameras: dict[str, m.CameraInfo] = {}
        self.ids: collections.Counter[int] = collections.Counter()
        self.poses = 0
        self.poses_missing_camera_info = 0
        self.poses_failed = 0

    def camera_info(self, topic: str, info: m.CameraInfo) -> None:
        self.cameras[topic] = info

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray) -> Detections:
        markers = self.detector.detect(image)
        self.ids.update(marker.id for marker in markers)
        out: list[tuple[str, m.Message]] = [(f"{topic}/aruco_outlines", _marker(
            msg, "aruco_outlines", m.LINE_LIST, _closed_line_list([k.corners for k in markers]), MAGENTA))]
        if self.size is None or not markers:
            return len(markers), out
        camera = self.cameras.get(self.camera_info_override or camera_info_topic(topic))
        if camera is None:
            self.poses_missing_camera_info += len(markers)
            return len(markers), out
        transforms = []
        for marker in markers:
            try:
                pose = marker_pose(marker, camera, self.size)
            except ValueError:      # no solver found a pose (degenerate corners)
                self.poses_failed += 1
                continue
            transforms.append(m.TransformStamped(msg.stamp_ns, msg.frame_id or camera.frame_id, f"aruco_{marker.id}",
                                                 pose.translation, pose.quaternion()))
        self.poses += len(transforms)
        if transforms:
            out.append(("/tf", m.TFMessage(tuple(transforms))))
        return len(markers), out

    def summary(self) -> dict[str, Any]:
        return {"marker_ids": {str(k): v for k, v in sorted(self.ids.items())}, "markers": sum(self.ids.values()),
                "poses": self.poses, "poses_missing_camera_info": self.poses_missing_camera_info,
                "poses_failed": self.poses_failed}


class FeaturePipeline(Pipeline):
    """Local features from ``trundle.perception.features.detect(image, method, **params)``."""

    def __init__(self, args: argparse.Namespace) -> None:
        try:
            from trundle.perception.features import METHODS, available, detect
        except ImportError:
            raise UserError("the features pipeline needs trundle.perception.features, which is not installed") from None
        if args.method not in METHODS:
            raise UserError(f"unknown feature detector {args.method!r} (choose from {', '.join(METHODS)})")
        if not available(args.method):
            raise UserError(f"{args.method} is not in this OpenCV build (cv2 {cv2.__version__})")
        self.detect = detect
        self.method = args.method
        self.params: dict[str, Any] = {}
        for item in args.param:
            key, sep, value = item.partition("=")
            if not sep or not key:
                raise UserError(f"--param needs KEY=VALUE, got {item!r}")
            self.params[key] = _value(value)
        self.keypoints = 0

    def process(self, topic: str, msg: m.CompressedImage | m.Image, image: np.ndarray) -> Detections:
        keypoints = self.detect(image, self.method, **self.params)
        self.keypoints += len(keypoints)
        oriented = np.isfinite(keypoints.angle)
        tips = keypoints.xy[oriented] + 0.5 * keypoints.size[oriented, None] * np.column_stack(
            [np.cos(keypoints.angle[oriented]), np.sin(keypoints.angle[oriented])])
        ticks = np.stack([keypoints.xy[oriented], tips], axis=1).reshape(-1, 2)
        return len(keypoints), [
            (f"{topic}/keypoints", _marker(msg, "keypoints", m.POINTS, keypoints.xy, CYAN, 3.0)),
            (f"{topic}/keypoint_orientations", _marker(msg, "keypoint_orientations", m.LINE_LIST, ticks, CYAN, 1.0))]

    def summary(self) -> dict[str, Any]:
        return {"keypoints": self.keypoints, "method": self.method}


PIPELINES: dict[str, type[Pipeline]] = {"color": ColorPipeline, "markers": MarkerPipeline, "features": FeaturePipeline}


def run(args: argparse.Namespace) -> int:
    source, output = Path(args.file), Path(args.output)
    if output.exists() and source.exists() and output.resolve() == source.resolve():
        raise UserError("the output must not be the input log")
    reader = LogReader(source)
    info = reader.info()
    images = sorted(t for t, i in info.topics.items() if i.ros_type in IMAGE_TYPES)
    topics = args.topics or images
    missing = [t for t in topics if t not in images]
    if missing:
        raise UserError(f"not an image topic in {source.name}: {', '.join(missing)} "
                        f"(images: {', '.join(images) or 'none'})")
    if not topics:
        raise UserError(f"no Image or CompressedImage topic in {source.name}")
    pipeline = PIPELINES[args.pipeline](args)
    wanted = {camera_info_topic(t) for t in topics} | ({args.camera_info} if args.camera_info else set())
    info_topics = sorted(t for t in wanted if t in info.topics and info.topics[t].ros_type == CAMERA_INFO_TYPE)
    frames, corrupt, per_frame = 0, collections.Counter(), []
    progress = Progress("perceive", sum(info.topics[t].count for t in topics))
    with Logger(output, salvage=False, metadata={"perceive": json.dumps(vars(args), default=str)}) as logger:
        def write(topic: str, ros_type: str, data: bytes, log_time_ns: int) -> None:
            while logger.queue_length >= MAX_QUEUED and logger.error is None:
                time.sleep(0.001)
            logger.write_encoded(topic, ros_type, data, log_time_ns)

        for raw in reader.raw_messages(topics + info_topics):
            if not args.no_images:
                write(raw.topic, raw.ros_type, raw.data, raw.log_time_ns)
            try:
                msg = ros2.decode(raw.ros_type, raw.data)
                if isinstance(msg, m.CameraInfo):
                    pipeline.camera_info(raw.topic, msg)
                    continue
                image = decode_image(msg)
            except Exception as error:  # a corrupt message or image is counted and skipped, never fatal
                corrupt[f"{raw.topic}: {type(error).__name__}: {error}"[:160]] += 1
                continue
            count, detections = pipeline.process(raw.topic, msg, image)
            for topic, detection in detections:
                write(topic, *ros2.encode(detection), raw.log_time_ns)
            per_frame.append(count)
            frames += 1
            progress.update(frames + sum(corrupt.values()), f"{frames} frames")
        progress.close()
    summary = {"log": str(source), "output": str(output), "pipeline": args.pipeline, "image_topics": topics,
               "frames": frames, "corrupt_messages": sum(corrupt.values()), "corrupt_reasons": dict(corrupt),
               "detections_per_frame": _stats(per_frame), **pipeline.summary(),
               "written": {t: s.written for t, s in sorted(logger.stats.items())},
               "dropped": sum(s.dropped for s in logger.stats.values())}
    _print(summary, args.json)
    return 0 if frames else 1


def _stats(values: list[int]) -> dict[str, float]:
    if not values:
        return {"mean": 0.0, "min": 0, "max": 0}
    return {"mean": float(np.mean(values)), "min": int(min(values)), "max": int(max(values))}


def _print(summary: dict[str, Any], as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    lines = [f"{summary['pipeline']} pipeline over {', '.join(summary['image_topics'])}",
             f"frames: {summary['frames']} processed, {summary['corrupt_messages']} corrupt messages skipped"]
    lines += [f"  skipped {n}x {reason}" for reason, n in summary["corrupt_reasons"].items()]
    stats = summary["detections_per_frame"]
    lines.append(f"detections per frame: mean {stats['mean']:.2f}, min {stats['min']}, max {stats['max']}")
    for key in ("regions", "markers", "marker_ids", "poses", "poses_missing_camera_info", "poses_failed", "keypoints"):
        if key in summary:
            lines.append(f"{key.replace('_', ' ')}: {summary[key]}")
    lines.append(f"wrote {summary['output']}:")
    lines += [f"  {topic:<40} {n:>7} msgs" for topic, n in summary["written"].items()]
    print("\n".join(lines))
