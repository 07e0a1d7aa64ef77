"""ArUco per frame: MarkerDetector (+ marker_pose) against the bare OpenCV calls.

Frames: a synthetic 640x480 frame with 4 DICT_4X4_50 markers, and OpenCV's three 640x480
tutorial photos (DICT_6X6_250, 6 / 17 / 13 markers) from ../shared/data/aruco when present.
Baselines: ``ArucoDetector.detectMarkers`` with the same parameters (sub-pixel refinement), and
``detectMarkers`` + one ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker. Our pose adds SQPnP and
LM refinement of every candidate (see perception/markers.py), so its cost is reported as well.
Times are process CPU seconds, minimum over interleaved rounds.
Run: python tools/bench/bench_aruco.py [--repeat N]
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from trundle.logs.messages import CameraInfo
from trundle.perception.markers import (
    CORNER_REFINEMENT,
    MarkerDetector,
    dictionary_by_name,
    marker_object_points,
    marker_pose,
)
from trundle.tools.bench import report
from trundle.tools.bench.bench_color import cpu_per_call

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "aruco"
PHOTOS = ("singlemarkersoriginal.jpg", "choriginal.jpg", "chocclusion_original.jpg")
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
CAMERA = CameraInfo(0, "camera_optical", 480, 640, "plumb_bob", np.zeros(5), K)
SIZE_M = 0.1


def synthetic_frame() -> np.ndarray:
    """Four 100 px DICT_4X4_50 markers on a grey, lightly noisy 640x480 frame."""
    frame = np.full((480, 640), 200, np.uint8)
    dictionary = dictionary_by_name("DICT_4X4_50")
    for i, (x, y) in enumerate([(60, 60), (400, 80), (120, 300), (450, 320)]):
        frame[y:y + 100, x:x + 100] = cv2.aruco.generateImageMarker(dictionary, i, 100)
    noise = np.random.default_rng(0).normal(0, 3, frame.shape)
    return np.clip(frame + noise, 0, 255).astype(np.uint8)


def bare_detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = CORNER_REFINEMENT["subpix"]
    return cv2.aruco.ArucoDetector(dictionary_by_name(dictionary), params)


def bare_poses(detector: cv2.aruco.ArucoDetector, image: np.ndarray) -> int:
    corners, ids, _ = detector.detectMarkers(image)
    for c in corners:
        cv2.solvePnP(marker_object_points(SIZE_M), c.reshape(4, 2).astype(np.float64), K, CAMERA.d,
                     flags=cv2.SOLVEPNP_IPPE_SQUARE)
    return 0 if ids is None else len(ids)


def our_poses(detector: MarkerDetector, image: np.ndarray) -> int:
    markers = detector.detect(image)
    for marker in markers:
        marker_pose(marker, CAMERA, SIZE_M)
    return len(markers)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args()
    frames = {"synthetic_4x4": ("DICT_4X4_50", synthetic_frame())}
    for name in PHOTOS:
        if (DATA / name).exists():
            photo = cv2.imread(str(DATA / name))
            if photo is None:
                raise SystemExit(f"{DATA / name}: not an image")
            frames[name.removesuffix(".jpg")] = ("DICT_6X6_250", photo)
    figures: dict[str, float] = {}
    for name, (dictionary, image) in frames.items():
        ours, bare = MarkerDetector(dictionary), bare_detector(dictionary)
        count = len(ours.detect(image))
        if count != len(bare.detectMarkers(image)[0]):
            raise SystemExit(f"{name}: marker counts differ")
        best = dict.fromkeys(("ours", "bare", "ours_pose", "bare_pose"), float("inf"))
        for _ in range(args.repeat):
            best["ours"] = min(best["ours"], cpu_per_call(partial(ours.detect, image)))
            best["bare"] = min(best["bare"], cpu_per_call(partial(bare.detectMarkers, image)))
            best["ours_pose"] = min(best["ours_pose"], cpu_per_call(partial(our_poses, ours, image)))
            best["bare_pose"] = min(best["bare_pose"], cpu_per_call(partial(bare_poses, bare, image)))
        figures[f"{name}_markers"] = count
        figures[f"{name}_detect_ms"] = best["ours"] * 1e3
        figures[f"{name}_bare_detect_ms"] = best["bare"] * 1e3
        figures[f"{name}_detect_ratio"] = best["ours"] / best["bare"]
        figures[f"{name}_detect_pose_ms"] = best["ours_pose"] * 1e3
        figures[f"{name}_bare_detect_pose_ms"] = best["bare_pose"] * 1e3
        figures[f"{name}_detect_pose_ratio"] = best["ours_pose"] / best["bare_pose"]
    report.write("aruco", figures)


if __name__ == "__main__":
    main()
