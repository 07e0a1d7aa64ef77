"""`trundle match IMG1 IMG2`: detect, describe, match and fit a homography or fundamental matrix.

Prints the keypoints per image, the matches left after each filter, the RANSAC inliers and
the model (image 1 -> image 2); `--json` prints the same as one object; `--draw OUT.png`
writes the two images side by side with inlier matches in green and rejected ones in red.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from trundle.logs.errors import UserError
from trundle.logs.outputs import json_text, write_image
from trundle.logs.paths import input_file, new_file
from trundle.perception.features import DESCRIPTORS, EDGES, METHODS, available
from trundle.perception.image_matching import PairMatch, match_images
from trundle.perception.keypoints import to_cv
from trundle.tools.config.arguments import non_negative, non_negative_int, number_in, positive, positive_int

FEATURES = [m for m in METHODS if m not in EDGES]


def register(p: argparse.ArgumentParser) -> None:
    p.add_argument("image1", help="first image (any format OpenCV reads)")
    p.add_argument("image2", help="second image")
    p.add_argument("--features", default="sift", choices=FEATURES, help="detector (default sift)")
    p.add_argument("--descriptor", choices=sorted(DESCRIPTORS),
                   help="descriptor (default: the detector's own, SIFT for detectors without one)")
    p.add_argument("--max-keypoints", type=positive_int, help="keep the strongest N keypoints per image")
    p.add_argument(
        "--ratio",
        type=number_in(0.0, 1.0, low_open=True),
        default=0.8,
        help="Lowe's ratio test, best/second best (1 = off; 0.8)",
    )
    p.add_argument("--min-difference", type=non_negative, default=0.0,
                   help="reject when second best - best distance is below this (0 = off)")
    p.add_argument("--max-distance", type=positive, default=math.inf, help="reject matches farther than this")
    p.add_argument("--no-cross-check", action="store_true", help="keep one-way nearest neighbours")
    p.add_argument("--flann", action="store_true", help="approximate FLANN search (randomised) instead of brute force")
    p.add_argument("--model", choices=("homography", "fundamental"), default="homography",
                   help="model fitted by RANSAC (homography for planar scenes or pure rotation)")
    p.add_argument("--threshold", type=positive, default=3.0, help="RANSAC inlier band in pixels (3)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="RANSAC random seed (results are reproducible)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--draw", metavar="OUT.png", help="write a picture of the matches")
    p.set_defaults(func=run)


def _read(path: str) -> np.ndarray:
    input_file(path, "image")
    image = cv2.imread(path, cv2.IMREAD_COLOR)
    if image is None:
        raise UserError(f"cannot decode image: {path}")
    return image


def draw(image1: np.ndarray, image2: np.ndarray, result: PairMatch) -> np.ndarray:
    """Side-by-side picture: RANSAC inliers green, other matches red, unmatched keypoints grey."""
    kp1, kp2 = (to_cv(f.keypoints) for f in result.features)
    matches = [cv2.DMatch(int(i), int(j), 0.0) for i, j in result.matches.pairs]
    inliers = result.fit.inliers.astype(np.uint8).tolist()
    outliers = (1 - result.fit.inliers.astype(np.uint8)).tolist()
    canvas = cv2.drawMatches(image1, kp1, image2, kp2, matches, None, matchColor=(0, 0, 255),  # type: ignore[call-overload]  # outImg None: allocated
                             singlePointColor=(160, 160, 160), matchesMask=outliers)
    return cv2.drawMatches(image1, kp1, image2, kp2, matches, canvas, matchColor=(0, 200, 0),
                           matchesMask=inliers, flags=cv2.DrawMatchesFlags_DRAW_OVER_OUTIMG
                           | cv2.DrawMatchesFlags_NOT_DRAW_SINGLE_POINTS)


def run(args: argparse.Namespace) -> int:
    if not available(args.features):
        raise UserError(f"{args.features} is not available in this OpenCV build (cv2 {cv2.__version__})")
    image1, image2 = _read(args.image1), _read(args.image2)
    out = Path(args.draw) if args.draw else None
    if out is not None:  # before the work: a picture that cannot be written is said at once
        new_file(out, "--draw")
        if not out.parent.is_dir():
            raise UserError(f"no such directory for --draw: {out.parent}")
        if not cv2.haveImageWriter(str(out)):
            raise UserError(f"--draw {out}: OpenCV writes no picture with that extension (use .png or .jpg)")
    try:
        result = match_images(image1, image2, args.features, args.descriptor, args.max_keypoints,
                              model=args.model, cross_check=not args.no_cross_check, max_ratio=args.ratio,
                              min_difference=args.min_difference, max_distance=args.max_distance,
                              flann=args.flann, threshold=args.threshold, rng=args.seed)
    except ValueError as error:
        raise UserError(str(error)) from None
    summary = {"image1": args.image1, "image2": args.image2, "features": args.features,
               "descriptor": args.descriptor or (args.features if args.features in DESCRIPTORS else "sift"),
               **result.summary()}
    if out is not None:
        write_image(out, draw(image1, image2, result))
        summary["picture"] = str(out)
    if args.json:
        print(json_text(summary, indent=2))
        return 0
    counts = ", ".join(f"{name} {n}" for name, n in summary["matches"].items())
    print(f"features:  {summary['features']} + {summary['descriptor']} descriptor ({summary['metric']})")
    print(f"keypoints: {summary['keypoints'][0]} / {summary['keypoints'][1]}")
    print(f"matches:   {counts}")
    print(f"inliers:   {summary['inliers']} ({args.model}, {args.threshold:g} px, {summary['ransac_trials']} trials)")
    model = summary[args.model]
    if model is None:
        print(f"{args.model}: none (too few matches)")
    else:
        print(f"{args.model} (image 1 -> image 2):")
        for row in model:
            print("  " + "  ".join(f"{v: .6g}" for v in row))
    if args.draw:
        print(f"picture:   {summary['picture']}")
    return 0
