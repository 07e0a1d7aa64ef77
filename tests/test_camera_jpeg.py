"""JPEG frame checks: whole frames pass, every kind of damage a camera produces is caught."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trundle.drivers.jpeg_check import CorruptJpeg, JpegChecker, decodes, jpeg_header, jpeg_problem


def encoded(width: int = 64, height: int = 48, *params: int, seed: int = 0, gray: bool = False) -> bytes:
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (height, width) if gray else (height, width, 3), dtype=np.uint8)
    ok, buffer = cv2.imencode(".jpg", image, params)
    assert ok
    return buffer.tobytes()


def scan_start(data: bytes) -> int:
    """Offset of the first byte after the SOS segment (independent walk by segment lengths)."""
    pos = 2
    while True:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        pos += 2 + length
        if marker == 0xDA:
            return pos


GOOD = [
    encoded(),
    encoded(37, 23),  # odd size
    encoded(64, 48, cv2.IMWRITE_JPEG_QUALITY, 10),
    encoded(64, 48, cv2.IMWRITE_JPEG_PROGRESSIVE, 1),  # several scans with tables between them
    encoded(64, 48, cv2.IMWRITE_JPEG_RST_INTERVAL, 2),  # restart markers in the image data
    encoded(64, 48, gray=True),
    encoded(640, 480, cv2.IMWRITE_JPEG_OPTIMIZE, 1),
]


@pytest.mark.parametrize("data", GOOD)
def test_whole_frames_pass_with_their_size(data: bytes) -> None:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert jpeg_header(data) == (image.shape[1], image.shape[0])
    assert JpegChecker(decode_every=1).check(data) is None


def test_size_comes_from_the_sof_segment() -> None:
    assert jpeg_header(encoded(37, 23)) == (37, 23)
    assert jpeg_header(encoded(1280, 720, seed=3)) == (1280, 720)


def test_zero_padding_after_eoi_is_accepted() -> None:
    data = encoded() + bytes(300)  # some UVC cameras hand over the whole buffer
    assert jpeg_problem(data) is None
    assert JpegChecker(decode_every=1).check(data) is None


@pytest.mark.parametrize("damage, reason", [
    (lambda d: d[: len(d) // 2], "EOI"),                                 # short transfer
    (lambda d: d[: len(d) // 2] + bytes(len(d) - len(d) // 2), "EOI"),   # zero-filled tail
    (lambda d: b"\x00\x00" + d[2:], "SOI"),
    (lambda d: d[:2] + b"\x12" + d[3:], "marker"),                        # header broken
    (lambda d: d[:-2] + b"\x00\x00", "EOI"),
    (lambda d: d[:4] + b"\xff\xff" + d[6:], "overruns"),                  # APP0 length blown up
    (lambda d: b"", "SOI"),
])
def test_damaged_frames_are_caught(damage, reason: str) -> None:
    problem = jpeg_problem(damage(encoded(seed=5)))
    assert problem is not None and reason in problem


def test_invalid_marker_inside_the_image_data_is_caught() -> None:
    data = bytearray(encoded(seed=6))
    middle = (scan_start(bytes(data)) + len(data)) // 2
    data[middle:middle + 2] = b"\xff\xc0"  # a SOF marker cannot appear in entropy-coded data
    assert "inside the image data" in jpeg_problem(bytes(data))


def test_decode_check_catches_what_markers_cannot() -> None:
    # point the scan's first component at Huffman tables 3/3, which the header never defines
    data = bytearray(encoded(seed=7))
    sos = bytes(data).index(b"\xff\xda")
    data[sos + 6] = 0x33
    data = bytes(data)
    assert jpeg_problem(data) is None
    assert not decodes(data, jpeg_header(data))
    assert JpegChecker(decode_every=1).check(data) == "libjpeg cannot decode the frame"
    assert JpegChecker(decode_every=0).check(data) is None


def test_decode_is_sampled() -> None:
    checker = JpegChecker(decode_every=3)
    for _ in range(9):
        assert checker.check(GOOD[0]) is None
    assert checker.decoded == 3


def test_expected_size_mismatch_is_a_bad_frame() -> None:
    checker = JpegChecker(decode_every=0, expected_size=(640, 480))
    assert checker.check(encoded(64, 48)) == "frame is 64x48, expected 640x480"


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400))
def test_any_bytes_give_a_reason_or_a_size(data: bytes) -> None:
    try:
        width, height = jpeg_header(data)
    except CorruptJpeg as error:
        assert str(error)
    else:
        assert width > 0 and height > 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(GOOD[:6]), st.floats(0.0, 1.0, exclude_max=True))
def test_every_truncation_is_caught(data: bytes, fraction: float) -> None:
    assert jpeg_problem(data[: int(len(data) * fraction)]) is not None


FORBIDDEN_AFTER_FF = [
    b for b in range(256) if b not in {0x00, 0xFF, *range(0xD0, 0xD8), 0xC4, 0xCC, 0xDA, 0xDB, 0xDD, 0xFE}
]


@settings(max_examples=150, deadline=None)
@given(
    st.sampled_from(GOOD[:3] + GOOD[4:6]), st.floats(0.0, 1.0, exclude_max=True), st.sampled_from(FORBIDDEN_AFTER_FF)
)
def test_any_forbidden_marker_in_the_scan_is_caught(data: bytes, where: float, second: int) -> None:
    start = scan_start(data)
    pos = start + int((len(data) - 2 - start - 2) * where)
    damaged = data[:pos] + bytes([0xFF, second]) + data[pos + 2:]
    assert jpeg_problem(damaged) is not None
