"""Regions and moments: hand-computed moments, OpenCV's moments, drawn ellipses recovered."""

from __future__ import annotations

import math
from fractions import Fraction

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.perception.regions import (
    central_moments,
    centroid,
    ellipse,
    find_regions,
    hu_moments,
    raw_moments,
    region_of,
)

TINY = np.array([[1, 0, 2],
                 [0, 3, 0]])   # weights at (x, y) = (0, 0), (2, 0), (1, 1)


def _definition(weights: np.ndarray, p: int, q: int, about: tuple[Fraction, Fraction]) -> Fraction:
    """sum (x - cx)^p (y - cy)^q w(x, y) in exact rational arithmetic, straight from the definition."""
    cx, cy = about
    return sum((Fraction(x) - cx) ** p * (Fraction(y) - cy) ** q * int(w)
               for (y, x), w in np.ndenumerate(weights) if w)


def test_raw_moments_hand_computed() -> None:
    m = raw_moments(TINY)
    # m00 = 1 + 2 + 3; m10 = 0*1 + 2*2 + 1*3; m01 = 1*3; m20 = 4*2 + 1*3; m11 = 1*1*3; m30 = 8*2 + 3
    assert (m[0, 0], m[1, 0], m[0, 1], m[2, 0], m[1, 1], m[0, 2], m[3, 0]) == (6, 7, 3, 11, 3, 3, 19)
    assert centroid(m) == (7 / 6, 0.5)


def test_central_moments_hand_computed() -> None:
    mu = central_moments(raw_moments(TINY))
    # mu20 = m20 - m10^2/m00 = 11 - 49/6; mu11 = 3 - 7*3/6; mu02 = 3 - 9/6;
    # mu30 = (-7/6)^3 * 1 + (5/6)^3 * 2 + (-1/6)^3 * 3 = -96/216
    assert mu[2, 0] == pytest.approx(17 / 6, abs=1e-12)
    assert mu[1, 1] == pytest.approx(-0.5, abs=1e-12)
    assert mu[0, 2] == pytest.approx(1.5, abs=1e-12)
    assert mu[3, 0] == pytest.approx(-4 / 9, abs=1e-12)
    assert mu[1, 0] == pytest.approx(0, abs=1e-12) and mu[0, 1] == pytest.approx(0, abs=1e-12)
    about = (Fraction(7, 6), Fraction(1, 2))
    for p in range(4):
        for q in range(4):
            assert mu[p, q] == pytest.approx(float(_definition(TINY, p, q, about)), abs=1e-12)


def test_moments_agree_with_opencv_on_random_blobs() -> None:
    rng = np.random.default_rng(5)
    mask = (cv2.GaussianBlur(rng.random((90, 120)), (0, 0), 4) > 0.5).astype(np.uint8)
    _, regions = find_regions(mask)
    assert len(regions) >= 3
    for region in regions:
        cv = cv2.moments((region_mask := _label_mask(mask, region)), binaryImage=True)
        for name in ("m00", "m10", "m01", "m20", "m11", "m02", "m30", "m21", "m12", "m03"):
            p, q = int(name[1]), int(name[2])
            assert region.moments[p, q] == pytest.approx(cv[name], rel=1e-9)
        for name in ("mu20", "mu11", "mu02", "mu30", "mu21", "mu12", "mu03"):
            p, q = int(name[2]), int(name[3])
            assert region.central[p, q] == pytest.approx(cv[name], rel=1e-7, abs=1e-6 * cv["m00"])
        assert np.allclose(region.hu, cv2.HuMoments(cv).ravel(), rtol=1e-6, atol=1e-15)
        x, y, w, h = cv2.boundingRect(region_mask)
        assert region.bbox == (x, y, w, h)


def _label_mask(mask: np.ndarray, region) -> np.ndarray:
    _, labels = cv2.connectedComponents(mask, connectivity=8)
    return (labels == region.label).astype(np.uint8)


def _drawn_ellipse(cx: float, cy: float, a: float, b: float, angle_deg: float) -> np.ndarray:
    """A filled ellipse drawn by OpenCV with sub-pixel centre and axes (4 fractional bits)."""
    image = np.zeros((320, 360), np.uint8)
    scale = 16
    cv2.ellipse(image, (round(cx * scale), round(cy * scale)), (round(a * scale), round(b * scale)),
                angle_deg, 0, 360, 255, -1, cv2.LINE_8, 4)
    return image


def _sampled_ellipse(cx: float, cy: float, a: float, b: float, angle_deg: float) -> np.ndarray:
    """The pixels whose centres lie inside the ellipse (exact sampling, any sub-pixel centre)."""
    y, x = np.mgrid[0:320, 0:360]
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    u, v = (x - cx) * c + (y - cy) * s, -(x - cx) * s + (y - cy) * c
    return ((u / a) ** 2 + (v / b) ** 2 <= 1).astype(np.uint8)


@pytest.mark.parametrize("cx, cy, a, b, angle", [
    (180, 160, 120, 40, 30), (150, 140, 60, 25, -55), (170.5, 150.5, 90, 30, 0),
    (180, 160, 100, 20, 90), (160, 170, 80, 50, 135), (175.5, 155, 110, 45, 12.5)])
def test_drawn_ellipse_recovered(cx: float, cy: float, a: float, b: float, angle: float) -> None:
    """cv2.ellipse draws a 5-degree polygon, so its centre is only exact on the half-pixel grid."""
    _check_ellipse(_drawn_ellipse(cx, cy, a, b, angle), cx, cy, a, b, angle, centre_px=0.1)


@given(st.floats(140, 220), st.floats(130, 190), st.floats(60, 120), st.floats(0.25, 0.6),
       st.floats(-180, 180))
@settings(max_examples=60, deadline=None)
def test_sampled_ellipse_recovered_anywhere(cx: float, cy: float, a: float, ratio: float, angle: float) -> None:
    """Arbitrary sub-pixel ellipses: the pixel lattice alone moves the centroid by up to ~0.12 px."""
    b = max(a * ratio, 30.0)
    _check_ellipse(_sampled_ellipse(cx, cy, a, b, angle), cx, cy, a, b, angle, centre_px=0.15)


def _check_ellipse(mask: np.ndarray, cx: float, cy: float, a: float, b: float, angle: float,
                   centre_px: float) -> None:
    _, regions = find_regions(mask)
    assert len(regions) == 1
    region = regions[0]
    x0, y0 = region.centroid
    assert math.hypot(x0 - cx, y0 - cy) < centre_px
    assert abs(region.a - a) < 1 and abs(region.b - b) < 1
    # theta is an axis direction: compare modulo 180 degrees
    error = (math.degrees(region.theta) - angle + 90) % 180 - 90
    assert abs(error) < 0.5


def test_near_circle_axes_recovered() -> None:
    region = find_regions(_drawn_ellipse(180, 160, 80, 79, 10))[1][0]
    assert abs(region.a - 80) < 1 and abs(region.b - 79) < 1   # orientation is ill-conditioned here


def test_ellipse_of_hand_computed_moments() -> None:
    # mu20 = 4 m00, mu02 = m00, mu11 = 0: lambdas 4 and 1 per pixel, so a = 2*2, b = 2*1, theta 0.
    mu = np.zeros((4, 4))
    mu[0, 0], mu[2, 0], mu[0, 2] = 10, 40, 10
    assert ellipse(mu) == (4.0, 2.0, 0.0)
    mu[2, 0], mu[0, 2] = 10, 40
    a, b, theta = ellipse(mu)
    assert (a, b) == (4.0, 2.0) and theta == pytest.approx(math.pi / 2)


def test_hu_invariants_under_rotation_scale_and_reflection() -> None:
    shape = np.zeros((200, 200), np.uint8)
    cv2.fillPoly(shape, [np.array([[40, 30], [150, 60], [120, 90], [70, 170]])], 255)
    hu = region_of(shape).hu
    rotated = region_of(np.rot90(shape)).hu
    flipped = region_of(shape[:, ::-1]).hu
    bigger = region_of(cv2.resize(shape, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)).hu
    assert np.allclose(rotated, hu, rtol=1e-9, atol=0)
    assert np.allclose(flipped[:6], hu[:6], rtol=1e-9) and flipped[6] == pytest.approx(-hu[6], rel=1e-9)
    assert np.allclose(bigger[:2], hu[:2], rtol=2e-2)


def test_find_regions_limits_and_connectivity() -> None:
    mask = np.zeros((40, 60), np.uint8)
    mask[2:12, 2:12] = 255          # 100 px square
    mask[20:22, 5:45] = 255         # 80 px bar, a/b ~ 20
    mask[30, 50] = mask[31, 51] = 255  # two diagonal pixels
    mask[30:35, 2:7] = 255
    mask[32, 4] = 0                 # 24 px with a hole
    labels, regions = find_regions(mask)
    assert [r.area for r in regions] == [100, 80, 24, 2]
    assert labels.dtype == np.int32 and (labels > 0).sum() == 206
    assert [r.area for r in find_regions(mask, connectivity=4)[1]] == [100, 80, 24, 1, 1]
    assert [r.area for r in find_regions(mask, min_area=24, max_area=80)[1]] == [80, 24]
    # the diagonal pair is a segment (b = 0): infinitely elongated
    assert [r.area for r in find_regions(mask, max_aspect=3)[1]] == [100, 24]
    assert [r.area for r in find_regions(mask, min_extent=0.99)[1]] == [100, 80]
    assert regions[0].bbox == (2, 2, 10, 10) and regions[0].extent == 1.0
    assert regions[0].centroid == (6.5, 6.5)
    with pytest.raises(ValueError):
        find_regions(mask, connectivity=6)
    assert find_regions(np.zeros((5, 5), np.uint8))[1] == []


def test_moment_functions_work_on_stacks() -> None:
    """central_moments, ellipse and hu_moments take (N, n, n) stacks (any order >= 2 for the ellipse)."""
    masks = [_sampled_ellipse(180, 160, 90, 30, 20), _sampled_ellipse(150.5, 170.25, 60, 45, -70)]
    singles = [region_of(mask) for mask in masks]
    stack = np.stack([r.moments for r in singles])
    mu = central_moments(stack)
    assert np.allclose(mu, np.stack([r.central for r in singles]), rtol=1e-9, atol=1e-6)
    a, b, theta = ellipse(mu[:, :3, :3])                       # second order suffices
    assert np.allclose(a, [r.a for r in singles]) and np.allclose(theta, [r.theta for r in singles])
    assert np.allclose(hu_moments(mu), np.stack([r.hu for r in singles]), rtol=1e-9, atol=0)
    with pytest.raises(ValueError):
        central_moments(np.zeros((2, 4, 4)))
