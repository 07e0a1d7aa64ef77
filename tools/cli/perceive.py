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
import math
from pathlib import Path
from typing import Any

from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text
from trundle.perception.features import METHODS
from trundle.tools.cli.damage import say_damage
from trundle.tools.cli.progress import Progress
from trundle.tools.config.arguments import non_negative, non_negative_int, number_in, positive, positive_int
from trundle.tools.jobs.perceive import perceive_log


def register(p: argparse.ArgumentParser) -> None:
    p.description = __doc__
    p.add_argument("file", help="MCAP log with images")
    p.add_argument("--pipeline", required=True, choices=("color", "markers", "features"),
                   help="color: regions of one colour; markers: ArUco markers; features: keypoints (see above)")
    p.add_argument("-o", "--output", required=True, help="output MCAP file (must not exist)")
    p.add_argument("--topics", nargs="+", help="image topics (default: every Image and CompressedImage topic)")
    p.add_argument("--no-images", action="store_true", help="write only the detections, not the images")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    c = p.add_argument_group("color pipeline (textbook HSV: H degrees, S and V in [0, 1])")
    c.add_argument("--lower", help="fast path: lower HSV bound, e.g. 15,0.6,0.5")
    c.add_argument("--upper", help="fast path: upper HSV bound, e.g. 45,1,1 (H below lower wraps through 0)")
    c.add_argument("--template", help="image of the colour (back-projection path)")
    c.add_argument("--template-mask", help="mask image selecting the template's pixels (non-zero)")
    c.add_argument(
        "--bins", type=number_in(1, 180, whole=True), default=32, help="histogram bins per channel (default 32)"
    )
    c.add_argument("--weights", default="0.5,0.3,0.2", help="H,S,V back-projection weights (default 0.5,0.3,0.2)")
    c.add_argument(
        "--level", type=number_in(0, 255, whole=True), default=128, help="likeness threshold 0..255 (default 128)"
    )
    c.add_argument("--blur", type=non_negative, default=2.0, help="Gaussian blur sigma of the likeness, px (default 2)")
    c.add_argument("--min-area", type=non_negative_int, default=50, help="smallest region, px (default 50)")
    c.add_argument("--max-area", type=positive_int, help="largest region, px")
    c.add_argument("--max-aspect", type=number_in(1.0), help="largest ellipse axis ratio a/b (>= 1)")
    c.add_argument(
        "--min-extent", type=number_in(0.0, 1.0), default=0.0, help="smallest fraction of its box a region fills"
    )
    k = p.add_argument_group("markers pipeline")
    k.add_argument("--dictionary", default="DICT_6X6_250", help="ArUco dictionary (default DICT_6X6_250)")
    k.add_argument("--refinement", default="edges", choices=("edges", "subpix", "none", "contour", "apriltag"),
                   help="corner refinement (default edges: sub-pixel corners refined on the marker's edges)")
    k.add_argument("--marker-size", type=positive, help="printed marker side in metres (enables poses)")
    k.add_argument("--camera-info", help="CameraInfo topic (default: <camera namespace>/camera_info)")
    f = p.add_argument_group("features pipeline")
    f.add_argument("--method", default="orb", metavar="NAME",
                   help=f"keypoint detector: {', '.join(METHODS)} (default orb)")
    f.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="detector parameter (repeatable)")
    p.set_defaults(func=run)


def _triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    """``"a,b,c"`` as three finite floats (None for None); anything else (also nan, inf) is a UserError
    naming the option ``name``."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise UserError(f"{name} needs three comma-separated finite numbers, got {text!r}")
    return values[0], values[1], values[2]


def _value(text: str) -> Any:
    """A ``--param`` value as int, float or bool if it reads as one, else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def _params(items: list[str]) -> dict[str, Any]:
    """The ``--param KEY=VALUE`` items as a dict."""
    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UserError(f"--param needs KEY=VALUE, got {item!r}")
        params[key] = _value(value)
    return params


def pipeline_options(args: argparse.Namespace) -> dict[str, Any]:
    """The chosen pipeline's keyword arguments from its option group."""
    if args.pipeline == "color":
        return dict(lower=_triple(args.lower, "--lower"), upper=_triple(args.upper, "--upper"), template=args.template,
                    template_mask=args.template_mask, bins=args.bins, weights=_triple(args.weights, "--weights"),
                    level=args.level, blur_sigma=args.blur, min_area=args.min_area, max_area=args.max_area,
                    max_aspect=args.max_aspect, min_extent=args.min_extent)
    if args.pipeline == "markers":
        return dict(dictionary=args.dictionary, refinement=args.refinement, marker_size=args.marker_size)
    return dict(method=args.method, params=_params(args.param))


def run(args: argparse.Namespace) -> int:
    """Run the perceive job with the chosen pipeline and print its summary; exit code 1 without frames."""
    summary = perceive_log(Path(args.file), Path(args.output), args.pipeline, pipeline_options(args),
                           topics=args.topics, images=not args.no_images, camera_info=args.camera_info,
                           provenance=vars(args), progress=Progress)
    say_damage(args, summary["log_damage"])
    _print(summary, args.json)
    return 0 if summary["frames"] else 1


def _print(summary: dict[str, Any], as_json: bool) -> None:
    """The job's summary as one JSON object, or as lines of text."""
    if as_json:
        print(json_text(summary, indent=2))
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
