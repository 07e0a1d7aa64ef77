"""Detectors and descriptors on synthetic images with known answers."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from feature_scenes import scene

from trundle.logs.errors import UserError
from trundle.perception.features import (
    DESCRIPTORS,
    METHODS,
    available,
    describe,
    detect,
    detect_and_describe,
    edge_map,
    intensity_centroid_angle,
    sift_octave,
)
from trundle.perception.keypoints import from_cv, make_keypoints, to_cv


@pytest.mark.parametrize("method", list(METHODS))
def test_every_detector_gives_position_size_and_orientation(method: str) -> None:
    if not available(method):
        pytest.skip(f"{method} is not in this OpenCV build ({cv2.__version__})")
    image = scene()
    kp = detect(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), method)
    assert len(kp) > 10
    assert np.isfinite(kp.angle).all() and ((kp.angle >= 0) & (kp.angle < 2 * math.pi)).all()
    assert (kp.size > 0).all()
    assert ((kp.xy >= -0.5) & (kp.xy <= [320 - 0.5, 240 - 0.5])).all()
    few = detect(image, method, max_keypoints=10)
    assert len(few) == 10 and few.response.min() >= np.sort(kp.response)[-10]


def test_unknown_names_and_missing_capabilities() -> None:
    image = scene()
    with pytest.raises(UserError):
        detect(image, "harris-laplace")
    with pytest.raises(UserError):
        describe(image, detect(image, "fast"), "freak")
    with pytest.raises(UserError):
        describe(image, detect(image, "fast"), "akaze")
    assert not available("harris-laplace")


def test_intensity_centroid_points_to_the_bright_side() -> None:
    image = np.zeros((101, 101), np.uint8)
    image[:, 51:] = 200                                    # bright to the right of the centre column
    kp = make_keypoints([[50.0, 50.0]], 21.0)
    assert intensity_centroid_angle(image, kp)[0] == pytest.approx(0.0, abs=1e-9)
    assert intensity_centroid_angle(image.T.copy(), kp)[0] == pytest.approx(math.pi / 2, abs=1e-9)   # below


def test_fast_and_harris_find_the_corners_of_a_square() -> None:
    image = np.zeros((120, 120), np.uint8)
    image[40:80, 30:90] = 255
    image = cv2.GaussianBlur(image, (0, 0), 1.0)          # a perfect binary corner ties FAST's scores
    corners = np.array([[30, 40], [89, 40], [89, 79], [30, 79]], dtype=float)
    for method, params in (("fast", {"threshold": 20}), ("agast", {"threshold": 20}), ("harris", {"min_distance": 10}),
                           ("shi-tomasi", {"min_distance": 10})):
        kp = detect(image, method, **params)
        nearest = np.sqrt(((kp.xy[:, None] - corners[None]) ** 2).sum(axis=2)).min(axis=0)
        assert (nearest < 2.5).all(), (method, nearest)


def test_mser_region_is_the_drawn_ellipse() -> None:
    image = np.full((200, 240), 230, np.uint8)
    cv2.ellipse(image, (120, 100), (50, 20), 30, 0, 360, 20, -1)   # semi-axes 50, 20 at 30 degrees
    kp = detect(image, "mser")
    best = np.argmin(np.sqrt(((kp.xy - [120, 100]) ** 2).sum(axis=1)) + np.abs(kp.size - 2 * math.sqrt(1000)))
    assert np.hypot(*(kp.xy[best] - [120, 100])) < 0.5
    assert kp.size[best] == pytest.approx(2 * math.sqrt(50 * 20), rel=0.05)
    assert math.cos(2 * (kp.angle[best] - math.radians(30))) > math.cos(2 * math.radians(2))


@pytest.mark.parametrize("method", ["log", "dog"])
def test_blob_scale_follows_the_blob(method: str) -> None:
    y, x = np.mgrid[0:160, 0:160]
    for sigma in (3.0, 6.0):
        image = (40 + 180 * np.exp(-((x - 80) ** 2 + (y - 80) ** 2) / (2 * sigma ** 2))).astype(np.uint8)
        kp = detect(image, method, max_keypoints=1)
        assert np.hypot(*(kp.xy[0] - 80)) <= 1.0
        # scale-normalised LoG peaks at the blob's sigma: size = 2 sqrt(2) sigma, one ladder step
        assert kp.size[0] / (2 * math.sqrt(2) * sigma) == pytest.approx(1.0, rel=0.27)


def test_edge_maps_on_a_vertical_step() -> None:
    image = np.zeros((20, 20), np.uint8)
    image[:, 10:] = 100
    x, y, magnitude, direction = edge_map(image, "roberts")
    assert set(x.tolist()) == {9.5} and len(x) == 19
    assert magnitude == pytest.approx(np.full(19, 100 * math.sqrt(2)))
    assert direction == pytest.approx(np.zeros(19))          # gradient points to +x
    x, _, magnitude, direction = edge_map(image, "sobel")
    assert set(x.tolist()) <= {9.0, 10.0} and magnitude.max() == pytest.approx(400.0)
    assert np.abs(np.angle(np.exp(1j * direction))).max() < 1e-6
    x, _, _, _ = edge_map(image, "canny")
    assert len(x) >= 18 and set(x.tolist()) <= {9.0, 10.0}
    with pytest.raises(ValueError):
        edge_map(image, "prewitt")


@pytest.mark.parametrize("descriptor", sorted(DESCRIPTORS))
def test_descriptors_row_for_row(descriptor: str) -> None:
    if descriptor != "surf" and not available(descriptor):
        pytest.skip(f"{descriptor} is not in this OpenCV build")
    image = scene(2)
    feats = detect_and_describe(image, "fast" if descriptor != "akaze" else "akaze", descriptor, max_keypoints=200)
    assert len(feats.descriptors) == len(feats.keypoints) > 50
    assert feats.metric == DESCRIPTORS[descriptor]
    assert (feats.descriptors.dtype == np.float32) == (feats.metric == "l2")


def test_keypoints_round_trip_through_opencv() -> None:
    kp = make_keypoints([[1.5, 2.25], [3.0, 4.0]], [7.0, 9.5], [0.5, math.nan], [0.25, 1.0], [0, 2])
    back = from_cv(to_cv(kp))
    assert back.xy.tolist() == kp.xy.tolist() and back.size.tolist() == kp.size.tolist()
    assert back.angle[0] == pytest.approx(0.5, abs=1e-6) and math.isnan(back.angle[1])
    assert back.octave.tolist() == [0, 2] and len(from_cv([])) == 0


def test_sift_octave_codes_foreign_keypoints_like_sift_its_own() -> None:
    # SIFT's size is 2 sigma with sigma = 1.6 * 2^(octave + layer / 3); packed octave | layer << 8
    sizes = 3.2 * 2.0 ** np.array([0.0, 1 / 3, 1.0, 2 + 2 / 3, -1.0])
    assert sift_octave(sizes).tolist() == [0, 1 << 8, 1, 2 | (2 << 8), 255]
    image = scene(3)
    kp = detect(image, "mser")
    described, desc = describe(image, kp, "sift")
    assert len(described) == len(kp) and desc.shape == (len(kp), 128)
    assert described.octave.tolist() == kp.octave.tolist()
