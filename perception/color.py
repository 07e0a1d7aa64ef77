"""Colour segmentation: HSV, template histograms, back-projection, cleaning, regions.

Two HSV representations are used:
- textbook HSV (``rgb_to_hsv``): H in degrees [0, 360), S and V in [0, 1], computed exactly;
- OpenCV 8-bit HSV (``to_hsv8``): H = h/2 in [0, 180), S = 255 s, V = 255 v as uint8, which is
  what the fast pipeline works on. ``hsv8_bounds`` converts textbook bounds to it.
Colour images are OpenCV-style BGR uint8 unless a function says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from trundle.perception.regions import Region, find_regions

HSV8_RANGES = (180, 256, 256)   # number of values of each OpenCV 8-bit HSV channel
DEFAULT_WEIGHTS = (0.5, 0.3, 0.2)   # hue dominates: it changes least with illumination


def rgb_to_hsv(image: np.ndarray, order: str = "rgb") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Textbook HSV of a uint8 colour image: (H degrees [0, 360), S [0, 1], V [0, 1]) as float64.

    With M = max, m = min of (R, G, B): H = 60 ((G-B)/(M-m) mod 6) if M = R, 60 ((B-R)/(M-m) + 2)
    if M = G, 60 ((R-G)/(M-m) + 4) if M = B, 0 if M = m; S = (M-m)/M (0 if M = 0); V = M/255.
    Each value is one division of exact integers, so it is the correctly rounded float64 of the
    formula. ``order`` is "rgb" or "bgr" (OpenCV's channel order).
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape[-1] != 3:
        raise ValueError(f"expected uint8 (..., 3) colour values, got {image.dtype} {image.shape}")
    if order not in ("rgb", "bgr"):
        raise ValueError("order must be 'rgb' or 'bgr'")
    channels = image.astype(np.int32)
    r, g, b = (channels[..., 0], channels[..., 1], channels[..., 2])
    if order == "bgr":
        r, b = b, r
    big = np.maximum(np.maximum(r, g), b)
    delta = big - np.minimum(np.minimum(r, g), b)
    # Hue in sixths of the circle times delta, kept in [0, 6 delta) with integer arithmetic.
    sixths = np.where(big == r, g - b + 6 * delta * (g < b),
                      np.where(big == g, b - r + 2 * delta, r - g + 4 * delta))
    hue = np.divide(60.0 * sixths, delta, out=np.zeros(delta.shape), where=delta > 0)
    saturation = np.divide(delta.astype(np.float64), big, out=np.zeros(delta.shape), where=big > 0)
    return hue, saturation, big / 255.0


def to_hsv8(bgr: np.ndarray) -> np.ndarray:
    """OpenCV 8-bit HSV of a BGR uint8 image: H = h/2 in [0, 180), S = 255 s, V = 255 v."""
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)


def hsv8_bounds(lower: tuple[float, float, float], upper: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Textbook HSV bounds (degrees, [0, 1], [0, 1]) in OpenCV 8-bit units, rounded to nearest."""
    scale = np.array([0.5, 255.0, 255.0])
    lo = np.clip(np.rint(np.asarray(lower, dtype=np.float64) * scale), 0, [179, 255, 255])
    hi = np.clip(np.rint(np.asarray(upper, dtype=np.float64) * scale), 0, [179, 255, 255])
    return lo.astype(np.uint8), hi.astype(np.uint8)


def in_range(hsv8: np.ndarray, lower: tuple[float, float, float], upper: tuple[float, float, float]) -> np.ndarray:
    """The fast path: 255 where every channel lies within textbook bounds [lower, upper].

    Hue wraps: lower H > upper H (e.g. 340 to 20 degrees for red) selects across 0 degrees.
    """
    lo, hi = hsv8_bounds(lower, upper)
    if lo[0] <= hi[0]:
        return cv2.inRange(hsv8, lo, hi)
    below = cv2.inRange(hsv8, np.array([0, lo[1], lo[2]], np.uint8), hi)
    above = cv2.inRange(hsv8, lo, np.array([179, hi[1], hi[2]], np.uint8))
    return cv2.bitwise_or(below, above)


@dataclass(frozen=True, eq=False)
class HsvTemplate:
    """Per-channel histograms of a colour template in OpenCV 8-bit HSV, each scaled to max 1.

    ``hue``, ``saturation`` and ``value`` have ``bins[c]`` bins covering 180, 256, 256 values.
    """

    hue: np.ndarray
    saturation: np.ndarray
    value: np.ndarray

    @property
    def bins(self) -> tuple[int, int, int]:
        return self.hue.size, self.saturation.size, self.value.size

    def scaled(self) -> list[np.ndarray]:
        """The three histograms scaled to peak 255 as (bins, 1) float32, as calcBackProject wants."""
        return [(255.0 * h).astype(np.float32).reshape(-1, 1) for h in (self.hue, self.saturation, self.value)]


def template_histograms(bgr: np.ndarray, mask: np.ndarray | None = None,
                        bins: int | tuple[int, int, int] = 32) -> HsvTemplate:
    """Template HSV histograms of a BGR image (``mask`` != 0 selects the template pixels)."""
    counts = (bins, bins, bins) if isinstance(bins, int) else tuple(bins)
    if len(counts) != len(HSV8_RANGES) or any(not 1 <= n <= size for n, size in zip(counts, HSV8_RANGES, strict=True)):
        raise ValueError(f"bins must be 1..{HSV8_RANGES} per channel, got {counts}")
    hsv8 = to_hsv8(bgr)
    selected = hsv8.reshape(-1, 3) if mask is None else hsv8[np.asarray(mask) != 0]
    if selected.shape[0] == 0:
        raise ValueError("template has no pixels")
    hists = []
    for c, (n, size) in enumerate(zip(counts, HSV8_RANGES, strict=True)):
        hist = np.bincount(selected[:, c].astype(np.int64) * n // size, minlength=n).astype(np.float64)
        hists.append(hist / hist.max())
    return HsvTemplate(*hists)


def back_project(hsv8: np.ndarray, template: HsvTemplate,
                 weights: tuple[float, float, float] = DEFAULT_WEIGHTS) -> np.ndarray:
    """Likeness of each pixel to the template, 0..255 uint8.

    Each channel is back-projected through its own histogram (``cv2.calcBackProject``, 0..255)
    and the three are merged as the weighted sum ``sum_c weights[c] * backprojection_c /
    sum(weights)`` (``cv2.addWeighted``, rounded at each of the two additions).
    """
    total = float(sum(weights))
    if total <= 0 or min(weights) < 0:
        raise ValueError("weights must be non-negative and not all zero")
    planes = [cv2.calcBackProject([hsv8], [c], hist, [0, size], 1)
              for c, (hist, size) in enumerate(zip(template.scaled(), HSV8_RANGES, strict=True))]
    merged = cv2.addWeighted(planes[0], weights[0] / total, planes[1], weights[1] / total, 0)
    return cv2.addWeighted(merged, 1.0, planes[2], weights[2] / total, 0)


def clean_mask(mask: np.ndarray, median_size: int = 5, close_size: int = 5, open_size: int = 0) -> np.ndarray:
    """Median filter then morphological closing and opening with elliptical elements.

    Sizes are odd kernel widths in pixels; 0 skips that step. Closing fills holes and gaps,
    opening removes specks.
    """
    if median_size:
        mask = cv2.medianBlur(mask, median_size)
    for op, size in ((cv2.MORPH_CLOSE, close_size), (cv2.MORPH_OPEN, open_size)):
        if size:
            mask = cv2.morphologyEx(mask, op, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    return mask


def masked(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The image with every pixel outside ``mask`` (== 0) set to 0."""
    return cv2.bitwise_and(image, image, mask=mask)


@dataclass(frozen=True, eq=False)
class ColorSegmentation:
    """What ``segment_color`` found: likeness (None on the fast path), cleaned mask, regions."""

    likeness: np.ndarray | None
    mask: np.ndarray
    labels: np.ndarray
    regions: list[Region]


def segment_color(bgr: np.ndarray, template: HsvTemplate | None = None, *,
                  lower: tuple[float, float, float] | None = None,
                  upper: tuple[float, float, float] | None = None,
                  weights: tuple[float, float, float] = DEFAULT_WEIGHTS,
                  blur_sigma: float = 2.0, level: int = 128, median_size: int = 5,
                  close_size: int = 5, open_size: int = 0, min_area: int = 50,
                  max_area: int | None = None, max_aspect: float | None = None,
                  min_extent: float = 0.0) -> ColorSegmentation:
    """Find regions of a colour in a BGR image.

    With ``template``: back-project its HSV histograms (merged with ``weights``), Gaussian blur
    (``blur_sigma`` px, 0 skips), keep likeness > ``level`` (0..255). With ``lower``/``upper``
    textbook HSV bounds instead: the fast per-pixel range test. Then ``clean_mask`` and
    ``find_regions`` with the given area and shape limits.
    """
    hsv8 = to_hsv8(bgr)
    if template is not None:
        if lower is not None or upper is not None:
            raise ValueError("give either a template or lower/upper bounds, not both")
        likeness = back_project(hsv8, template, weights)
        if blur_sigma > 0:
            likeness = cv2.GaussianBlur(likeness, (0, 0), blur_sigma)
        _, mask = cv2.threshold(likeness, level, 255, cv2.THRESH_BINARY)
    elif lower is not None and upper is not None:
        likeness, mask = None, in_range(hsv8, lower, upper)
    else:
        raise ValueError("give a template or both lower and upper bounds")
    mask = clean_mask(mask, median_size, close_size, open_size)
    labels, regions = find_regions(mask, min_area, max_area, max_aspect, min_extent)
    return ColorSegmentation(likeness, mask, labels, regions)
