"""Colour segmentation per 640x480 frame against the bare OpenCV call chain doing the same work.

Goal (issue 6): ``segment_color`` / bare chain <= 1.2 for both the template (back-projection)
path and the fast HSV-bounds path. The frame is a textured background with 10 orange ellipses;
both sides must find the same 10 regions. Times are process CPU seconds (all threads), the
minimum over interleaved rounds, so the load of a shared machine hits both sides alike.
Run: python tools/bench/bench_color.py [--repeat N]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import cv2
import numpy as np

from trundle.perception.color import DEFAULT_WEIGHTS, HSV8_RANGES, hsv8_bounds, segment_color, template_histograms
from trundle.tools.bench import report

ORANGE = (0, 128, 255)
LOWER, UPPER = (15.0, 0.7, 0.7), (45.0, 1.0, 1.0)


def frame(seed: int = 0) -> np.ndarray:
    """640x480 BGR: blurred colour noise with 10 non-overlapping orange ellipses and pixel noise."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640, 3)).astype(np.uint8), (0, 0), 6)
    image = cv2.normalize(image, None, 40, 200, cv2.NORM_MINMAX)  # type: ignore[call-overload]  # dst None: allocated (stubs say otherwise)
    for i in range(10):
        centre = (60 + 130 * (i % 5), 120 + 240 * (i // 5))
        cv2.ellipse(image, centre, (int(rng.integers(20, 50)), int(rng.integers(12, 30))), float(rng.uniform(0, 180)),
                    0, 360, ORANGE, -1)
    return np.clip(image + rng.normal(0, 5, image.shape), 0, 255).astype(np.uint8)


def bare_template(image: np.ndarray, hists: list[np.ndarray], weights: tuple[float, float, float]) -> int:
    """The same steps as segment_color's template path, written directly against OpenCV."""
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    total = sum(weights)
    planes = [cv2.calcBackProject([hsv], [c], hists[c], [0, HSV8_RANGES[c]], 1) for c in range(3)]
    likeness = cv2.addWeighted(planes[0], weights[0] / total, planes[1], weights[1] / total, 0)
    likeness = cv2.addWeighted(likeness, 1.0, planes[2], weights[2] / total, 0)
    likeness = cv2.GaussianBlur(likeness, (0, 0), 2.0)
    _, mask = cv2.threshold(likeness, 128, 255, cv2.THRESH_BINARY)
    return _bare_regions(mask)


def bare_bounds(image: np.ndarray) -> int:
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    lo, hi = hsv8_bounds(LOWER, UPPER)
    return _bare_regions(cv2.inRange(hsv, lo, hi))


def _bare_regions(mask: np.ndarray) -> int:
    mask = cv2.medianBlur(mask, 5)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    kept = 0
    for label in range(1, count):
        x, y, w, h, area = stats[label]
        if area < 50:
            continue
        moments = cv2.moments((labels[y:y + h, x:x + w] == label).astype(np.uint8), binaryImage=True)
        cv2.HuMoments(moments)
        kept += 1
    return kept


def cpu_per_call(fn: Callable[[], object], number: int = 5) -> float:
    """Mean process CPU seconds per call over ``number`` calls."""
    start = time.process_time()
    for _ in range(number):
        fn()
    return (time.process_time() - start) / number


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=15)
    args = parser.parse_args()
    image = frame()
    patch = np.random.default_rng(1).normal(ORANGE, 5, (16, 16, 3))
    template = template_histograms(np.clip(patch, 0, 255).astype(np.uint8))
    hists = template.scaled()

    ours_regions = len(segment_color(image, template).regions)
    bounds_regions = len(segment_color(image, lower=LOWER, upper=UPPER).regions)
    counts = (ours_regions, bare_template(image, hists, DEFAULT_WEIGHTS), bounds_regions, bare_bounds(image))
    if counts != (10,) * 4:
        raise SystemExit(f"region counts differ from the 10 drawn: {counts}")

    figures: dict[str, float] = {}
    ours_t = bare_t = ours_b = bare_b = float("inf")
    for _ in range(args.repeat):          # interleaved, so load changes hit both sides alike
        ours_t = min(ours_t, cpu_per_call(lambda: segment_color(image, template)))
        bare_t = min(bare_t, cpu_per_call(lambda: bare_template(image, hists, DEFAULT_WEIGHTS)))
        ours_b = min(ours_b, cpu_per_call(lambda: segment_color(image, lower=LOWER, upper=UPPER)))
        bare_b = min(bare_b, cpu_per_call(lambda: bare_bounds(image)))
    figures["template_ours_ms"] = ours_t * 1e3
    figures["template_bare_opencv_ms"] = bare_t * 1e3
    figures["template_ratio"] = ours_t / bare_t
    figures["bounds_ours_ms"] = ours_b * 1e3
    figures["bounds_bare_opencv_ms"] = bare_b * 1e3
    figures["bounds_ratio"] = ours_b / bare_b
    figures["regions"] = 10
    figures["goal_ratio"] = 1.2
    report.write("color", figures)


if __name__ == "__main__":
    main()
