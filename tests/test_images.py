"""Grey/binary conversion, histograms, fixed and Otsu thresholds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tests.conftest import shared_file
from trundle.logs.messages import CompressedImage, Image
from trundle.perception.images import decode_image, histogram, otsu_level, otsu_threshold, threshold, to_gray


def _bgr(height: int = 6, width: int = 8) -> np.ndarray:
    return np.arange(height * width * 3, dtype=np.uint8).reshape(height, width, 3)


def test_decode_compressed_png_and_jpeg() -> None:
    bgr = _bgr()
    png = cv2.imencode(".png", bgr)[1].tobytes()
    assert np.array_equal(decode_image(CompressedImage(0, "cam", "png", png)), bgr)
    grey = cv2.imencode(".png", bgr[:, :, 0])[1].tobytes()
    assert np.array_equal(decode_image(CompressedImage(0, "cam", "png", grey)), bgr[:, :, 0])
    flat = np.full((16, 16, 3), (10, 120, 230), np.uint8)
    jpeg = cv2.imencode(".jpg", flat, (cv2.IMWRITE_JPEG_QUALITY, 95))[1].tobytes()
    assert np.abs(decode_image(CompressedImage(0, "cam", "jpeg", jpeg)).astype(int) - flat).max() <= 3


@pytest.mark.parametrize("encoding, convert", [("bgr8", None), ("rgb8", cv2.COLOR_BGR2RGB),
                                               ("bgra8", cv2.COLOR_BGR2BGRA), ("rgba8", cv2.COLOR_BGR2RGBA)])
def test_decode_raw_colour_encodings(encoding: str, convert: int | None) -> None:
    bgr = _bgr()
    pixels = bgr if convert is None else cv2.cvtColor(bgr, convert)
    assert np.array_equal(decode_image(Image.from_array(0, "cam", pixels, encoding)), bgr)


def test_decode_mono_with_row_padding() -> None:
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    padded = np.zeros((3, 6), np.uint8)
    padded[:, :4] = grey
    msg = Image(0, "cam", 3, 4, "mono8", 6, padded.reshape(-1))
    assert np.array_equal(decode_image(msg), grey)


def test_decode_yuyv() -> None:
    # Y0 U Y1 V per two pixels; U = V = 128 is colourless, so every channel equals Y (BT.601)
    row = np.array([16, 128, 235, 128] * 2, np.uint8)
    msg = Image(0, "cam", 2, 4, "yuv422_yuy2", 8, np.tile(row, 2))
    pixels = decode_image(msg)
    assert pixels.shape == (2, 4, 3)
    assert pixels[0, :, 0].tolist() == [0, 255, 0, 255]
    assert np.array_equal(pixels, cv2.cvtColor(np.tile(row, 2).reshape(2, 4, 2), cv2.COLOR_YUV2BGR_YUY2))


def test_decode_rejects_bad_images() -> None:
    with pytest.raises(ValueError, match="cannot decode"):
        decode_image(CompressedImage(0, "cam", "jpeg", b"\xff\xd8 not a jpeg"))
    with pytest.raises(ValueError, match="unsupported"):
        decode_image(Image(0, "cam", 2, 2, "32FC1", 8, np.zeros(16, np.uint8)))
    with pytest.raises(ValueError, match="does not fit"):
        decode_image(Image(0, "cam", 4, 4, "bgr8", 12, np.zeros(20, np.uint8)))


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_decode_of_garbage_raises_only_valueerror(data: bytes) -> None:
    for msg in (CompressedImage(0, "cam", "jpeg", data), CompressedImage(0, "cam", "png", b"\x89PNG\r\n\x1a\n" + data),
                Image(0, "cam", 3, 5, "rgb8", 15, np.frombuffer(data, np.uint8))):
        try:
            pixels = decode_image(msg)
        except ValueError:
            continue
        assert pixels.dtype == np.uint8


def test_gray_of_bgr_uses_bt601_weights() -> None:
    # Pure blue, green, red: 0.114, 0.587, 0.299 of 255, rounded.
    bgr = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]]], np.uint8)
    assert to_gray(bgr).tolist() == [[29, 150, 76, round(0.114 * 10 + 0.587 * 20 + 0.299 * 30)]]


def test_gray_passes_grey_through_and_rejects_other_shapes() -> None:
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert to_gray(grey) is grey
    assert np.array_equal(to_gray(grey[:, :, None]), grey)
    with pytest.raises(ValueError):
        to_gray(np.zeros((3, 4, 2), np.uint8))
    with pytest.raises(ValueError):
        to_gray(np.zeros((3, 4), np.float32))


def test_histogram_counts_and_mask() -> None:
    grey = np.array([[0, 0, 7], [255, 7, 7]], np.uint8)
    hist = histogram(grey)
    assert hist.shape == (256,) and hist.sum() == 6
    assert (hist[0], hist[7], hist[255]) == (2, 3, 1)
    mask = np.array([[1, 0, 0], [1, 1, 0]], np.uint8)
    assert histogram(grey, mask)[[0, 7, 255]].tolist() == [1, 1, 1]


@given(arrays(np.uint8, st.tuples(st.integers(1, 40), st.integers(1, 40))))
@settings(max_examples=100, deadline=None)
def test_histogram_matches_calchist(grey: np.ndarray) -> None:
    expected = cv2.calcHist([grey], [0], None, [256], [0, 256]).ravel()
    assert np.array_equal(histogram(grey), expected)


def test_fixed_threshold() -> None:
    grey = np.array([[0, 99, 100, 101, 255]], np.uint8)
    assert threshold(grey, 100).tolist() == [[0, 0, 0, 255, 255]]
    assert threshold(grey, 100, invert=True).tolist() == [[255, 255, 255, 0, 0]]
    assert np.array_equal(threshold(grey, 100), cv2.threshold(grey, 100, 255, cv2.THRESH_BINARY)[1])


def test_otsu_hand_computed() -> None:
    # Levels 0 (1 px), 1 (1 px), 2 (2 px): between-class variance w0 w1 (m0 - m1)^2 is
    # 1*3*(0 - 5/3)^2 = 25/3 at t=0 and 2*2*(0.5 - 2)^2 = 9 at t=1, so t = 1.
    hist = np.zeros(256)
    hist[[0, 1, 2]] = [1, 1, 2]
    assert otsu_level(hist) == 1
    # Two spikes: every t in [10, 199] separates them equally; the lowest wins (as OpenCV).
    hist = np.zeros(256)
    hist[[10, 200]] = [3, 5]
    assert otsu_level(hist) == 10
    hist = np.zeros(256)
    hist[42] = 9
    assert otsu_level(hist) == 42
    with pytest.raises(ValueError):
        otsu_level(np.zeros(256))


@pytest.mark.parametrize("name", ["aruco/singlemarkersoriginal.jpg", "aruco/choriginal.jpg",
                                  "oxford/graf/img1.png", "hpatches/v_churchill/1.png"])
def test_otsu_matches_opencv_on_photos(name: str) -> None:
    grey = cv2.cvtColor(cv2.imread(str(shared_file(name))), cv2.COLOR_BGR2GRAY)
    level, mask = otsu_threshold(grey)
    cv_level, cv_mask = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    assert level == cv_level
    assert np.array_equal(mask, cv_mask)


@given(st.integers(0, 2**32 - 1), st.integers(1, 254), st.floats(1, 40), st.floats(0.05, 0.95))
@settings(max_examples=100, deadline=None)
def test_otsu_matches_opencv_on_bimodal(seed: int, gap: int, sigma: float, fraction: float) -> None:
    rng = np.random.default_rng(seed)
    low = rng.normal(100 - gap / 2, sigma, 2000)
    high = rng.normal(100 + gap / 2, sigma, 2000)
    values = np.where(rng.random(2000) < fraction, low, high)
    grey = np.clip(np.rint(values), 0, 255).astype(np.uint8).reshape(40, 50)
    cv_level, _ = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    assert otsu_threshold(grey)[0] == cv_level
