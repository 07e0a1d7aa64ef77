"""Image messages to arrays; grey and binary images, 256-bin histograms, fixed and Otsu thresholds.

Images are OpenCV-style uint8 arrays: H x W (grey) or H x W x 3 in BGR order. Binary images
are uint8 masks holding 0 and 255 so they feed straight into OpenCV morphology and labelling.
"""

from __future__ import annotations

import cv2
import numpy as np

from trundle.logs.messages import CompressedImage, Image

# sensor_msgs/Image encodings (REP 104 names) -> conversion to BGR or grey (None: use as is)
_RAW_ENCODINGS = {
    "mono8": None, "8uc1": None, "bgr8": None, "8uc3": None,
    "rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR,
    "yuv422_yuy2": cv2.COLOR_YUV2BGR_YUY2, "yuyv": cv2.COLOR_YUV2BGR_YUY2,
    "uyvy": cv2.COLOR_YUV2BGR_UYVY, "yuv422": cv2.COLOR_YUV2BGR_UYVY,
}


def decode_image(msg: CompressedImage | Image) -> np.ndarray:
    """The pixels of an image message as BGR (or grey for mono8) uint8.

    Handles CompressedImage (any format OpenCV decodes: JPEG, PNG, ...) and the 8-bit Image
    encodings mono8, bgr8, rgb8, bgra8, rgba8 and YUV 4:2:2 (yuyv / uyvy). Raises ValueError
    for a corrupt or unsupported image.
    """
    if isinstance(msg, CompressedImage):
        try:
            pixels = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        except cv2.error:            # e.g. an empty buffer
            pixels = None
        if pixels is None:
            raise ValueError(f"cannot decode a {len(msg.data)}-byte {msg.format or 'compressed'} image")
        if pixels.dtype != np.uint8:
            raise ValueError(f"unsupported {pixels.dtype} compressed image")
        return cv2.cvtColor(pixels, cv2.COLOR_BGRA2BGR) if pixels.ndim == 3 and pixels.shape[2] == 4 else pixels
    encoding = msg.encoding.lower()
    if encoding not in _RAW_ENCODINGS:
        raise ValueError(f"unsupported image encoding {msg.encoding!r}")
    channels = 2 if encoding in ("yuv422_yuy2", "yuyv", "uyvy", "yuv422") else 4 if encoding.endswith("a8") else \
        3 if encoding in ("bgr8", "rgb8", "8uc3") else 1
    if msg.height <= 0 or msg.width <= 0 or msg.step < msg.width * channels or msg.data.size < msg.height * msg.step:
        raise ValueError(f"image data ({msg.data.size} bytes) does not fit {msg.width}x{msg.height} {msg.encoding}")
    rows = msg.data[: msg.height * msg.step].reshape(msg.height, msg.step)[:, : msg.width * channels]
    pixels = rows.reshape(msg.height, msg.width, channels) if channels > 1 else rows
    conversion = _RAW_ENCODINGS[encoding]
    return np.ascontiguousarray(pixels) if conversion is None else cv2.cvtColor(pixels, conversion)


def to_gray(image: np.ndarray) -> np.ndarray:
    """Grey uint8 image from a grey, BGR or BGRA uint8 image (ITU-R BT.601 weights, as OpenCV)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"expected H x W or H x W x 1/3/4 image, got shape {image.shape}")


def histogram(gray: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Counts of each grey level 0..255 (int64, length 256); ``mask`` != 0 selects pixels."""
    gray = np.asarray(gray)
    if gray.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {gray.dtype}")
    values = gray.reshape(-1) if mask is None else gray[np.asarray(mask) != 0]
    return np.bincount(values, minlength=256).astype(np.int64)


def threshold(gray: np.ndarray, level: float, invert: bool = False) -> np.ndarray:
    """Binary mask: 255 where ``gray > level`` (``<=`` when ``invert``), else 0."""
    above = np.asarray(gray) > level
    return np.where(above != invert, np.uint8(255), np.uint8(0))


def otsu_level(hist: np.ndarray) -> int:
    """Otsu's threshold from a histogram: the level t maximising the between-class variance.

    Pixels ``<= t`` form one class and ``> t`` the other (so ``threshold(gray, t)`` splits them).
    Ties go to the lowest level. A histogram with a single occupied level gives that level.
    """
    hist = np.asarray(hist, dtype=np.float64).reshape(-1)
    total = hist.sum()
    if total <= 0:
        raise ValueError("empty histogram")
    levels = np.arange(hist.size, dtype=np.float64)
    weight0 = np.cumsum(hist)                      # pixels <= t
    weight1 = total - weight0                      # pixels > t
    sum0 = np.cumsum(hist * levels)
    mean0 = np.divide(sum0, weight0, out=np.zeros_like(sum0), where=weight0 > 0)
    mean1 = np.divide(sum0[-1] - sum0, weight1, out=np.zeros_like(sum0), where=weight1 > 0)
    between = weight0 * weight1 * (mean0 - mean1) ** 2
    best = between.max()
    if best <= 0:
        return int(np.flatnonzero(hist)[0])
    # Round-off makes equal variances differ in the last bits: treat them as ties.
    return int(np.flatnonzero(between >= best * (1 - 1e-12))[0])


def otsu_threshold(gray: np.ndarray, mask: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """Otsu's level of a grey image and the binary mask it gives (255 above the level)."""
    level = otsu_level(histogram(gray, mask))
    return level, threshold(gray, level)
