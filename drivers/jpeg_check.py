"""Is this JPEG whole? Marker checks on every frame, a full decode on a sample of frames.

A camera's MJPEG frame is stored unchanged, so a damaged frame must be caught before it is
logged. ``jpeg_header`` walks the marker segments (ITU-T T.81 annex B): SOI first, every header
segment inside the frame, a SOF giving the size, then the entropy-coded data up to an EOI at the
end (zero padding after EOI, which some UVC cameras send, is accepted). Inside the entropy-coded
data a 0xFF byte may only be followed by 0x00 (stuffing), RST0-7, fill 0xFF or a table/scan
marker (multi-scan images), so a flipped byte that forms any other marker is caught too.
A frame whose entropy data is damaged without forming a marker passes these checks; the sampled
``cv2.imdecode`` (reduced size, so cheap) catches those libjpeg cannot decode.
"""

from __future__ import annotations

import cv2
import numpy as np

from trundle.logs.errors import ProtocolError

SOI = b"\xff\xd8"
EOI = b"\xff\xd9"
SOS = 0xDA
# SOF0-15 except DHT (C4), JPG (C8) and DAC (CC)
SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# bytes that may follow 0xFF inside entropy-coded data
_ALLOWED_AFTER_FF = np.zeros(256, dtype=bool)
_ALLOWED_AFTER_FF[[0x00, 0xFF, *range(0xD0, 0xD8), 0xC4, 0xCC, 0xDA, 0xDB, 0xDD, 0xFE]] = True


class CorruptJpeg(ProtocolError):
    """The bytes are not one whole JPEG image; the message says what is wrong (the camera driver
    counts and drops such a frame)."""


def jpeg_end(data: bytes) -> int:
    """Length of ``data`` up to and including its EOI marker, ignoring zero padding after it.

    Raises ``CorruptJpeg`` when the frame does not end with EOI (a truncated frame).
    """
    end = len(data)
    if data[end - 2:end] != EOI:
        end = len(data.rstrip(b"\0"))
        if end < 4 or data[end - 2:end] != EOI:
            raise CorruptJpeg("no EOI marker at the end (truncated frame)")
    return end


def jpeg_header(data: bytes) -> tuple[int, int]:
    """``(width, height)`` in pixels of a whole JPEG; raises ``CorruptJpeg`` saying what is wrong."""
    if len(data) < 4 or data[:2] != SOI:
        raise CorruptJpeg("no SOI marker at the start")
    end = jpeg_end(data)
    pos, size = 2, None
    while True:
        if pos + 4 > end:
            raise CorruptJpeg("frame ends inside the header")
        if data[pos] != 0xFF:
            raise CorruptJpeg(f"no marker at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte before a marker
            pos += 1
            continue
        if marker in (0x00, 0x01, 0xD8, 0xD9) or 0xD0 <= marker <= 0xD7:
            raise CorruptJpeg(f"unexpected marker 0xFF{marker:02X} at byte {pos} in the header")
        length = (data[pos + 2] << 8) | data[pos + 3]
        if length < 2 or pos + 2 + length > end - 2:
            raise CorruptJpeg(f"segment 0xFF{marker:02X} at byte {pos} overruns the frame")
        if marker in SOF_MARKERS:
            if length < 8:
                raise CorruptJpeg("SOF segment too short")
            height = (data[pos + 5] << 8) | data[pos + 6]
            width = (data[pos + 7] << 8) | data[pos + 8]
            if width == 0 or height == 0:
                raise CorruptJpeg(f"SOF gives an empty image {width}x{height}")
            size = (width, height)
        pos += 2 + length
        if marker == SOS:
            break
    if size is None:
        raise CorruptJpeg("no SOF segment before the scan")
    scan = np.frombuffer(data, dtype=np.uint8, count=end - 2 - pos, offset=pos)
    after_ff = scan[1:][scan[:-1] == 0xFF]
    bad = ~_ALLOWED_AFTER_FF[after_ff]
    if bad.any():
        raise CorruptJpeg(f"invalid marker 0xFF{int(after_ff[bad][0]):02X} inside the image data")
    return size


def jpeg_problem(data: bytes) -> str | None:
    """What is wrong with a JPEG frame's structure, or None when it is whole."""
    try:
        jpeg_header(data)
    except CorruptJpeg as error:
        return str(error)
    return None


def decodes(data: bytes, size: tuple[int, int]) -> bool:
    """True when libjpeg decodes ``data`` (at 1/2 scale, for speed) to an image of ``size`` (w, h)."""
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_2)
    return image is not None and image.shape == ((size[1] + 1) // 2, (size[0] + 1) // 2)


class JpegChecker:
    """Marker checks on every frame and a decode on every ``decode_every``-th (0: never).

    ``check`` returns None for a good frame, else the reason; ``expected_size`` (w, h), when
    given, must match the frame's own size.
    """

    def __init__(self, decode_every: int = 30, expected_size: tuple[int, int] | None = None) -> None:
        self.decode_every = decode_every
        self.expected_size = expected_size
        self.decoded = 0
        self._count = 0

    def check(self, data: bytes) -> str | None:
        try:
            size = jpeg_header(data)
        except CorruptJpeg as error:
            return str(error)
        if self.expected_size is not None and size != tuple(self.expected_size):
            return f"frame is {size[0]}x{size[1]}, expected {self.expected_size[0]}x{self.expected_size[1]}"
        self._count += 1
        if self.decode_every > 0 and self._count % self.decode_every == 1 % self.decode_every:
            self.decoded += 1
            if not decodes(data, size):
                return "libjpeg cannot decode the frame"
        return None
