"""Two images -> features, filtered matches and a RANSAC model (homography or fundamental).

The chain behind `trundle match`, the feature benchmark and the acceptance tests: detect and
describe both images, match descriptors (`trundle.perception.matching`), fit the model robustly
(`trundle.perception.ransac`), keeping the count left after every stage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from trundle.perception.features import Features, detect_and_describe
from trundle.perception.matching import MatchResult, match
from trundle.perception.ransac import RansacResult, find_fundamental, find_homography


@dataclass(frozen=True)
class PairMatch:
    """Features of both images, the descriptor matches, and the RANSAC fit over them."""

    features: tuple[Features, Features]
    matches: MatchResult
    model: str
    fit: RansacResult

    @property
    def inlier_pairs(self) -> np.ndarray:
        """(K, 2) keypoint indices of the matches RANSAC kept."""
        return self.matches.pairs[self.fit.inliers]

    def summary(self) -> dict:
        """JSON-ready counts and model (the `trundle match --json` object, without file names)."""
        out = {"keypoints": [len(f.keypoints) for f in self.features], "metric": self.features[0].metric,
               "matches": dict(self.matches.counts), "model": self.model,
               "inliers": int(self.fit.inliers.sum()), "ransac_trials": self.fit.trials,
               self.model: None if self.fit.model is None else np.asarray(self.fit.model).tolist()}
        return out


def match_features(
    f1: Features,
    f2: Features,
    model: str = "homography",
    cross_check: bool = True,
    max_ratio: float = 0.8,
    min_difference: float = 0.0,
    max_distance: float = math.inf,
    flann: bool = False,
    threshold: float = 3.0,
    rng: np.random.Generator | int | None = None,
) -> PairMatch:
    """Match two feature sets and fit `model` ("homography": x2 ~ H x1, inlier band `threshold`
    px of transfer error; "fundamental": x2^T F x1 = 0, band `threshold` px Sampson distance)."""
    if f1.metric != f2.metric:
        raise ValueError(f"descriptor metrics differ: {f1.metric} and {f2.metric}")
    found = match(f1.descriptors, f2.descriptors, f1.metric, cross_check, max_distance, max_ratio, min_difference,
                  flann)
    x1 = f1.keypoints.xy[found.pairs[:, 0]]
    x2 = f2.keypoints.xy[found.pairs[:, 1]]
    if model == "homography":
        fit = find_homography(x1, x2, threshold, rng=rng)
    elif model == "fundamental":
        fit = find_fundamental(x1, x2, threshold, rng=rng)
    else:
        raise ValueError(f"unknown model {model!r} (homography, fundamental)")
    return PairMatch((f1, f2), found, model, fit)


def match_images(image1: np.ndarray, image2: np.ndarray, method: str = "sift", descriptor: str | None = None,
                 max_keypoints: int | None = None, detector_params: dict | None = None, **options: Any) -> PairMatch:
    """Detect, describe, match and fit between two images (grey or BGR uint8).

    `method`/`descriptor`/`max_keypoints`/`detector_params` as `features.detect_and_describe`;
    `options` as `match_features`.
    """
    params = dict(detector_params or {})
    f1 = detect_and_describe(image1, method, descriptor, max_keypoints, **params)
    f2 = detect_and_describe(image2, method, descriptor, max_keypoints, **params)
    return match_features(f1, f2, **options)
