"""Template histograms, back-projection, the fast HSV range path and the segmentation pipeline."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trundle.perception.color import (
    back_project,
    clean_mask,
    in_range,
    masked,
    segment_color,
    template_histograms,
    to_hsv8,
)

ORANGE = (0, 128, 255)     # BGR: H 30 deg -> 15, S 1 -> 255, V 1 -> 255 in OpenCV 8-bit units
TEAL = (128, 128, 0)       # BGR: H 180 deg -> 90, S 255, V 128


def _image(background=(40, 40, 40)) -> np.ndarray:
    return np.full((120, 160, 3), background, np.uint8)


def test_template_histograms_hand_computed() -> None:
    tpl = np.zeros((4, 4, 3), np.uint8)
    tpl[:] = ORANGE
    tpl[0, :2] = TEAL          # 2 of 16 pixels
    t = template_histograms(tpl, bins=(18, 8, 4))
    assert t.bins == (18, 8, 4)
    # hue bins 10 values wide: 15 -> bin 1, 90 -> bin 9; counts 14 and 2, scaled to max 1
    expected_hue = np.zeros(18)
    expected_hue[[1, 9]] = [1.0, 2 / 14]
    assert np.array_equal(t.hue, expected_hue)
    assert t.saturation.tolist() == [0] * 7 + [1]
    # value: 255 -> bin 3 (14 px), 128 -> bin 2 (2 px)
    assert t.value.tolist() == [0, 0, 2 / 14, 1]
    masked_t = template_histograms(tpl, mask=np.pad(np.ones((1, 2), np.uint8), ((0, 3), (0, 2))), bins=18)
    assert masked_t.hue[9] == 1 and masked_t.hue.sum() == 1
    with pytest.raises(ValueError):
        template_histograms(tpl, bins=0)
    with pytest.raises(ValueError, match="per channel"):  # two bin counts for three channels
        template_histograms(tpl, bins=(18, 8))
    with pytest.raises(ValueError):
        template_histograms(tpl, mask=np.zeros((4, 4), np.uint8))


def test_back_projection_is_the_weighted_sum_of_channel_histograms() -> None:
    template = template_histograms(np.full((3, 3, 3), ORANGE, np.uint8), bins=32)
    img = _image()
    img[0, 0] = ORANGE                     # all three channels match: 255
    img[0, 1] = (0, 64, 128)               # same hue and saturation, V 128: weights 0.5 + 0.3
    img[0, 2] = (128, 128, 255)            # same V, hue 0, S 127/255: only value matches
    likeness = back_project(to_hsv8(img), template, weights=(0.5, 0.3, 0.2))
    assert likeness[0, :3].tolist() == [255, round(255 * 0.8), round(255 * 0.2)]
    assert likeness[1, 1] == 0             # grey background matches nothing
    with pytest.raises(ValueError):
        back_project(to_hsv8(img), template, weights=(0, 0, 0))


def test_back_projection_agrees_with_opencv_calcbackproject() -> None:
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (96, 128, 3)).astype(np.uint8), (0, 0), 2)
    tpl = img[20:50, 30:70]
    template = template_histograms(tpl, bins=(30, 32, 16))
    hsv8 = to_hsv8(img)
    weights = (0.6, 0.25, 0.15)
    expected = np.zeros(img.shape[:2])
    tpl_hsv = to_hsv8(tpl)
    for c, (bins, size, weight) in enumerate(zip((30, 32, 16), (180, 256, 256), weights, strict=True)):
        hist = cv2.calcHist([tpl_hsv], [c], None, [bins], [0, size])
        cv2.normalize(hist, hist, 255, 0, cv2.NORM_INF)     # scale so the peak is 255
        expected += weight * cv2.calcBackProject([hsv8], [c], hist, [0, size], 1).astype(np.float64)
    # rounded to uint8 after each channel and each of the two weighted additions: <= 1.5 levels
    assert np.abs(back_project(hsv8, template, weights).astype(np.float64) - expected).max() <= 1.5


def test_in_range_with_hue_wrapping_round_red() -> None:
    img = _image()
    img[0, 0] = (20, 0, 255)     # hue 355 deg
    img[0, 1] = (0, 20, 255)     # hue 5 deg
    img[0, 2] = (0, 255, 0)      # green
    img[0, 3] = (200, 200, 255)  # pale red: S 0.22
    mask = in_range(to_hsv8(img), (340, 0.5, 0.3), (20, 1, 1))
    assert mask[0, :4].tolist() == [255, 255, 0, 0]
    assert mask.sum() == 2 * 255
    green = in_range(to_hsv8(img), (100, 0.5, 0.5), (140, 1, 1))
    assert np.flatnonzero(green).tolist() == [2]


def test_clean_mask_removes_specks_and_fills_holes() -> None:
    mask = np.zeros((60, 60), np.uint8)
    mask[10:40, 10:40] = 255
    mask[25, 25] = 0          # hole
    mask[50, 50] = 255        # speck
    cleaned = clean_mask(mask, median_size=3, close_size=5)
    assert cleaned[25, 25] == 255 and cleaned[50, 50] == 0
    assert np.array_equal(clean_mask(mask, 0, 0, 0), mask)


def test_masked_image_keeps_only_the_mask() -> None:
    img = np.full((4, 5, 3), 200, np.uint8)
    mask = np.zeros((4, 5), np.uint8)
    mask[1:3, 2] = 255
    out = masked(img, mask)
    assert out[1, 2].tolist() == [200, 200, 200] and out.sum() == 2 * 3 * 200


def _scene() -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Orange ellipses on a noisy teal-ish background, with their centres."""
    rng = np.random.default_rng(11)
    img = np.clip(rng.normal((120, 110, 30), 12, (240, 320, 3)), 0, 255).astype(np.uint8)
    centres = [(60.0, 50.0), (200.0, 70.0), (120.0, 170.0), (260.0, 190.0)]
    for (x, y), (ax, ay, angle) in zip(centres, [(25, 12, 10), (18, 18, 0), (40, 15, -35), (12, 30, 60)], strict=True):
        cv2.ellipse(img, (int(x), int(y)), (ax, ay), angle, 0, 360, ORANGE, -1)
    img[5:9, 5:9] = ORANGE     # 16 px: below min_area
    noise = rng.normal(0, 6, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8), centres


@pytest.mark.parametrize("how", ["template", "bounds"])
def test_segment_color_finds_the_coloured_blobs(how: str) -> None:
    img, centres = _scene()
    if how == "template":
        template = template_histograms(img[45:55, 50:70])
        result = segment_color(img, template, min_area=100)
        assert result.likeness is not None and result.likeness.dtype == np.uint8
    else:
        result = segment_color(img, lower=(15, 0.7, 0.7), upper=(45, 1, 1), min_area=100)
        assert result.likeness is None
    found = sorted(r.centroid for r in result.regions)
    assert len(found) == len(centres)
    for (x, y), (fx, fy) in zip(sorted(centres), found, strict=True):
        assert abs(fx - x) < 0.5 and abs(fy - y) < 0.5
    assert result.labels.shape == img.shape[:2] and result.mask.dtype == np.uint8


def test_segment_color_shape_limits() -> None:
    img, _ = _scene()
    regions = segment_color(img, lower=(15, 0.7, 0.7), upper=(45, 1, 1), min_area=100, max_aspect=1.5).regions
    assert len(regions) == 1 and abs(regions[0].a - 18) < 1     # only the circle is round enough
    assert not segment_color(img, lower=(15, 0.7, 0.7), upper=(45, 1, 1), min_area=100, max_area=500).regions


def test_segment_color_needs_one_kind_of_model() -> None:
    img, _ = _scene()
    with pytest.raises(ValueError):
        segment_color(img)
    with pytest.raises(ValueError):
        segment_color(img, template_histograms(img), lower=(0, 0, 0), upper=(1, 1, 1))
