"""Textbook RGB -> HSV: exact on all 2^24 colours, and OpenCV's HSV within its quantisation."""

from __future__ import annotations

import colorsys

import cv2
import numpy as np
import pytest

from trundle.perception.color import hsv8_bounds, rgb_to_hsv

REDS_PER_CHUNK = 16   # 16 x 65536 colours (~1M) per chunk keeps memory to a few tens of MB


def _chunk(first_red: int) -> np.ndarray:
    """All colours whose red lies in [first_red, first_red + REDS_PER_CHUNK), as (N, 3) RGB uint8."""
    codes = np.arange(first_red << 16, (first_red + REDS_PER_CHUNK) << 16, dtype="<u4")   # 0xRRGGBB
    return np.ascontiguousarray(codes.view(np.uint8).reshape(-1, 4)[:, 2::-1])


def _hexcone_hue(rgb: np.ndarray) -> np.ndarray:
    """Hue by hexcone sector (which channel is largest, middle, smallest), an independent route.

    In sector k the hue is 60 (k + f) with f the middle channel's share; written as an integer
    numerator over the integer chroma so that one division gives the correctly rounded degree.
    """
    r, g, b = (rgb[:, i].astype(np.int32) for i in range(3))
    chroma = rgb.max(axis=1).astype(np.int32) - rgb.min(axis=1)
    sectors = [
        ((r >= g) & (g >= b), g - b),                    # red to yellow
        ((g >= r) & (r >= b), 2 * chroma - (r - b)),     # yellow to green
        ((g >= b) & (b >= r), 2 * chroma + (b - r)),     # green to cyan
        ((b >= g) & (g >= r), 4 * chroma - (g - r)),     # cyan to blue
        ((b >= r) & (r >= g), 4 * chroma + (r - g)),     # blue to magenta
        ((r >= b) & (b >= g), 6 * chroma - (b - g)),     # magenta to red
    ]
    numerator = np.select([c for c, _ in sectors], [n for _, n in sectors])
    return np.where(chroma > 0, 60 * numerator / np.maximum(chroma, 1), 0.0)


def test_exact_on_all_colours() -> None:
    for first_red in range(0, 256, REDS_PER_CHUNK):
        rgb = _chunk(first_red)
        hue, saturation, value = rgb_to_hsv(rgb)
        big = rgb.max(axis=1).astype(np.int32)
        chroma = big - rgb.min(axis=1)
        assert np.array_equal(hue, _hexcone_hue(rgb))
        assert np.array_equal(saturation, np.where(big > 0, chroma / np.maximum(big, 1), 0.0))
        assert np.array_equal(value, big / 255)
        assert hue.min() >= 0 and hue.max() < 360


def test_bgr_order_swaps_red_and_blue() -> None:
    rgb = _chunk(128)[::977]
    for got, want in zip(rgb_to_hsv(rgb[:, ::-1], order="bgr"), rgb_to_hsv(rgb), strict=True):
        assert np.array_equal(got, want)


def test_hand_computed_colours() -> None:
    rgb = np.array([[255, 0, 0], [255, 255, 0], [0, 255, 0], [0, 255, 255], [0, 0, 255], [255, 0, 255],
                    [0, 0, 0], [255, 255, 255], [128, 128, 128], [255, 0, 1], [100, 50, 0]], np.uint8)
    hue, saturation, value = rgb_to_hsv(rgb)
    # [255, 0, 1]: M = R, (G-B)/(M-m) = -1/255, mod 6 -> 6 - 1/255, times 60 -> 360 - 60/255.
    assert hue.tolist() == [0, 60, 120, 180, 240, 300, 0, 0, 0, 360 - 60 / 255, 30]
    assert saturation.tolist() == [1, 1, 1, 1, 1, 1, 0, 0, 0, 1, 1]
    assert value.tolist() == [1, 1, 1, 1, 1, 1, 0, 1, 128 / 255, 1, 100 / 255]


def test_agrees_with_colorsys_on_a_sample() -> None:
    rng = np.random.default_rng(7)
    rgb = rng.integers(0, 256, (20000, 3)).astype(np.uint8)
    hue, saturation, value = rgb_to_hsv(rgb)
    expected = np.array([colorsys.rgb_to_hsv(*(c / 255 for c in colour)) for colour in rgb.tolist()])
    hue_error = np.abs(hue - 360 * expected[:, 0])
    assert np.minimum(hue_error, 360 - hue_error).max() < 1e-9
    assert np.abs(saturation - expected[:, 1]).max() < 1e-12
    assert np.abs(value - expected[:, 2]).max() < 1e-12


def test_opencv_8bit_within_quantisation_on_all_colours() -> None:
    """OpenCV stores H/2, 255 S, 255 V as uint8: one quantum is 2 deg in H and 1/255 in S and V.

    Rounding alone errs by half a quantum; OpenCV's fixed-point division table adds up to ~0.15
    of a quantum more (measured). V is the exact maximum.
    """
    for first_red in range(0, 256, REDS_PER_CHUNK):
        rgb = _chunk(first_red)
        hue, saturation, value = rgb_to_hsv(rgb)
        hsv8 = cv2.cvtColor(rgb[None], cv2.COLOR_RGB2HSV)[0].astype(np.float64)
        hue_error = np.abs(hsv8[:, 0] - hue / 2)
        hue_error = np.minimum(hue_error, 180 - hue_error)
        assert hue_error.max() <= 0.7
        assert np.abs(hsv8[:, 1] - 255 * saturation).max() <= 0.6
        assert np.array_equal(hsv8[:, 2], 255 * value)
        # and the float version of OpenCV's conversion is this formula in float32
        hsv32 = cv2.cvtColor(rgb[None].astype(np.float32) / 255, cv2.COLOR_RGB2HSV)[0]
        hue_error = np.abs(hsv32[:, 0] - hue)
        assert np.minimum(hue_error, 360 - hue_error).max() < 5e-3   # float32, chroma as small as 1/255
        assert np.abs(hsv32[:, 1] - saturation).max() < 1e-4   # OpenCV divides by V + FLT_EPSILON


@pytest.mark.parametrize("lower, upper, lo8, hi8", [
    ((0, 0, 0), (360, 1, 1), [0, 0, 0], [179, 255, 255]),
    ((20, 0.5, 0.2), (40.4, 0.75, 1.0), [10, 128, 51], [20, 191, 255]),
])
def test_hsv8_bounds(lower, upper, lo8, hi8) -> None:
    lo, hi = hsv8_bounds(lower, upper)
    assert lo.tolist() == lo8 and hi.tolist() == hi8
