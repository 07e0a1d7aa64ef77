"""Repeatability, matching score and corner error on hand-computed configurations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.perception.feature_eval import corner_error, image_corners, matching_score, repeatability, shared
from trundle.perception.keypoints import make_keypoints

SHAPE = (100, 200)          # rows, cols
SHIFT = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])   # x2 = x1 + 10


def test_shared_part_under_a_translation() -> None:
    kp1 = make_keypoints([[5.0, 5.0], [185.0, 50.0], [195.0, 50.0]], 1.0)
    kp2 = make_keypoints([[5.0, 5.0], [50.0, 50.0]], 1.0)
    in1, in2 = shared(kp1, kp2, SHIFT, SHAPE, SHAPE)
    # 195 + 10 leaves image 2 (last centre 199); 5 - 10 leaves image 1 going back
    assert in1.tolist() == [True, True, False]
    assert in2.tolist() == [False, True]


def test_repeatability_counts_one_to_one_within_the_threshold() -> None:
    xy = np.array([[20.0, 20.0], [60.0, 30.0], [100.0, 70.0], [150.0, 40.0]])
    kp1 = make_keypoints(xy, 1.0)
    exact = make_keypoints(xy + [10.0, 0.0], 1.0)
    assert repeatability(kp1, exact, SHIFT, SHAPE, SHAPE) == (1.0, 4)
    nudged = make_keypoints(xy + [10.0, 2.0], 1.0)
    assert repeatability(kp1, nudged, SHIFT, SHAPE, SHAPE, threshold=3.0) == (1.0, 4)
    assert repeatability(kp1, nudged, SHIFT, SHAPE, SHAPE, threshold=1.5) == (0.0, 0)
    # two image-2 points near one image-1 point: one correspondence, not two
    crowded = make_keypoints([[30.0, 20.0], [31.0, 20.0]], 1.0)
    assert repeatability(kp1, crowded, SHIFT, SHAPE, SHAPE) == (0.5, 1)


def test_matching_score_and_precision() -> None:
    xy = np.array([[20.0, 20.0], [60.0, 30.0], [100.0, 70.0], [150.0, 40.0]])
    kp1 = make_keypoints(xy, 1.0)
    kp2 = make_keypoints(xy + [10.0, 0.0], 1.0)
    pairs = np.array([[0, 0], [1, 1], [2, 3]])        # the third is wrong
    score, precision, correct = matching_score(kp1, kp2, pairs, SHIFT, SHAPE, SHAPE)
    assert (score, correct) == (0.5, 2) and precision == pytest.approx(2 / 3)
    assert matching_score(kp1, kp2, np.empty((0, 2)), SHIFT, SHAPE, SHAPE) == (0.0, 0.0, 0)


def test_corner_error() -> None:
    assert image_corners(SHAPE).tolist() == [[0, 0], [199, 0], [199, 99], [0, 99]]
    off = SHIFT.copy()
    off[0, 2] += 3.0
    off[1, 2] += 4.0
    assert corner_error(off, SHIFT, SHAPE) == pytest.approx((5.0, 5.0))
    scaled = np.diag([1.01, 1.0, 1.0])                 # x grows by 1 %: 0 px at x=0, 1.99 px at x=199
    mean, worst = corner_error(scaled, np.eye(3), SHAPE)
    assert worst == pytest.approx(1.99) and mean == pytest.approx(1.99 / 2)
    assert corner_error(None, SHIFT, SHAPE) == (math.inf, math.inf)
