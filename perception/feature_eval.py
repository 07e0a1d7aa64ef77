"""Feature quality against a ground-truth homography (Oxford/HPatches protocol, point form).

A keypoint of image 1 and one of image 2 correspond when the homography maps the first to
within `threshold` pixels of the second. Only keypoints in the part of the scene both images
see count (image-1 points mapped inside image 2, image-2 points mapped back inside image 1).

- repeatability: one-to-one correspondences (mutual nearest neighbours within the threshold)
  / min(keypoints of image 1, keypoints of image 2) in the shared part (Mikolajczyk et al.,
  IJCV 2005, with a point-distance criterion instead of region overlap);
- matching score: correct matches / the same minimum (Mikolajczyk and Schmid, PAMI 2005);
- precision: correct matches / matches;
- corner error: distance between image 1's corners mapped by an estimated homography and by
  the true one (mean: HPatches' MACE; max: the acceptance "within 3 px").
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from trundle.perception.keypoints import Keypoints
from trundle.perception.ransac import project


def _inside(points: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    h, w = shape[:2]
    return (points[:, 0] >= -0.5) & (points[:, 0] <= w - 0.5) & (points[:, 1] >= -0.5) & (points[:, 1] <= h - 0.5)


def shared(kp1: Keypoints, kp2: Keypoints, h: np.ndarray, shape1: tuple[int, ...],
           shape2: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the keypoints of image 1 and of image 2 that lie in the part both images see."""
    return _inside(project(h, kp1.xy), shape2), _inside(project(np.linalg.inv(h), kp2.xy), shape1)


def transfer_error(kp1: Keypoints, kp2: Keypoints, pairs: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Distance in image 2 between H x1 and x2 for each pair (Q, 2) of keypoint indices."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return np.sqrt(((project(h, kp1.xy[pairs[:, 0]]) - kp2.xy[pairs[:, 1]]) ** 2).sum(axis=1))


def repeatability(kp1: Keypoints, kp2: Keypoints, h: np.ndarray, shape1: tuple[int, ...],
                  shape2: tuple[int, ...], threshold: float = 3.0) -> tuple[float, int]:
    """(repeatability, number of one-to-one correspondences) of two keypoint sets."""
    in1, in2 = shared(kp1, kp2, h, shape1, shape2)
    denominator = min(int(in1.sum()), int(in2.sum()))
    if denominator == 0:
        return 0.0, 0
    p1 = project(h, kp1.xy[in1])
    p2 = kp2.xy[in2]
    d12, j = cKDTree(p2).query(p1)
    _, i = cKDTree(p1).query(p2)
    i = np.asarray(i)  # (N,) for the (N, 2) query
    mutual = (i[j] == np.arange(len(p1))) & (d12 < threshold)
    count = int(mutual.sum())
    return count / denominator, count


def matching_score(kp1: Keypoints, kp2: Keypoints, pairs: np.ndarray, h: np.ndarray, shape1: tuple[int, ...],
                   shape2: tuple[int, ...], threshold: float = 3.0) -> tuple[float, float, int]:
    """(matching score, precision, correct matches) of matches `pairs` (Q, 2)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    in1, in2 = shared(kp1, kp2, h, shape1, shape2)
    denominator = min(int(in1.sum()), int(in2.sum()))
    correct = int((transfer_error(kp1, kp2, pairs, h) < threshold).sum())
    score = correct / denominator if denominator else 0.0
    precision = correct / len(pairs) if len(pairs) else 0.0
    return score, precision, correct


def image_corners(shape: tuple[int, ...]) -> np.ndarray:
    """The four corner pixels' centres (x, y) of an image of `shape`: TL, TR, BR, BL."""
    h, w = shape[:2]
    return np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])


def corner_error(estimate: np.ndarray | None, truth: np.ndarray, shape: tuple[int, ...]) -> tuple[float, float]:
    """(mean, max) distance in image 2 between image 1's corners mapped by `estimate` and by
    `truth`; (inf, inf) when there is no estimate."""
    if estimate is None:
        return float("inf"), float("inf")
    corners = image_corners(shape)
    d = np.sqrt(((project(estimate, corners) - project(truth, corners)) ** 2).sum(axis=1))
    return float(d.mean()), float(d.max())
