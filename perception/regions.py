"""Connected regions of a binary mask and their moments, ellipses and Hu invariants.

Coordinates are image pixels: x to the right (column), y down (row), the centre of pixel
(row j, column i) at (i, j). Raw moments m_pq = sum x^p y^q I(x, y); the centroid is
(m10/m00, m01/m00); central moments mu_pq are taken about it. The equivalent ellipse has
semi-axes a = 2 sqrt(lambda_a/m00) >= b = 2 sqrt(lambda_b/m00) from the eigenvalues of
[[mu20, mu11], [mu11, mu02]] and orientation theta = 0.5 atan2(2 mu11, mu20 - mu02) in radians
from the x axis towards y (clockwise on screen, because y points down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

ORDER = 3


def raw_moments(image: np.ndarray, order: int = ORDER, origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Raw moments m[p, q] = sum_x sum_y x^p y^q I(y, x) for p, q <= ``order`` (float64).

    ``image`` is a 2-D array of weights (a boolean mask counts 0/1; pass ``mask > 0`` for a
    0/255 mask). ``origin`` (x, y) is the image coordinate of ``image``'s pixel (0, 0), for a
    crop of a larger image. Computed as two matrix products, exact for small arrays.
    """
    weights = np.asarray(image, dtype=np.float64)
    if weights.ndim != 2:
        raise ValueError(f"expected a 2-D array, got shape {weights.shape}")
    height, width = weights.shape
    xs = np.vander(np.arange(width, dtype=np.float64) + origin[0], order + 1, increasing=True)   # (W, order+1)
    ys = np.vander(np.arange(height, dtype=np.float64) + origin[1], order + 1, increasing=True)  # (H, order+1)
    return xs.T @ (weights.T @ ys)


def centroid(m: np.ndarray) -> tuple[float, float]:
    """(x0, y0) = (m10/m00, m01/m00) from raw moments; raises on an empty region."""
    if m[0, 0] <= 0:
        raise ValueError("region has zero area")
    return float(m[1, 0] / m[0, 0]), float(m[0, 1] / m[0, 0])


@lru_cache(maxsize=8)
def _binomial(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Lower-triangular C(p, i) and the exponents max(p - i, 0) for p, i < n."""
    binomial = np.array([[math.comb(p, i) for i in range(n)] for p in range(n)], dtype=np.float64)
    k = np.arange(n)
    return binomial, np.clip(k[:, None] - k[None, :], 0, None)


def shift_moments(m: np.ndarray, dx: float | np.ndarray, dy: float | np.ndarray) -> np.ndarray:
    """Moments of the same weights after moving the origin by (-dx, -dy): x -> x + dx, y -> y + dy.

    By the binomial theorem m'[p, q] = sum_i sum_j C(p, i) dx^(p-i) C(q, j) dy^(q-j) m[i, j].
    ``m`` may be a stack (..., n, n) with ``dx``, ``dy`` of shape (...).
    """
    binomial, exponent = _binomial(m.shape[-1])
    sx = binomial * np.power(np.asarray(dx, dtype=np.float64)[..., None, None], exponent)
    sy = binomial * np.power(np.asarray(dy, dtype=np.float64)[..., None, None], exponent)
    return sx @ m @ np.swapaxes(sy, -1, -2)


def central_moments(m: np.ndarray) -> np.ndarray:
    """Central moments mu[p, q] = sum (x - x0)^p (y - y0)^q I from raw moments (or a stack of them)."""
    if np.any(m[..., 0, 0] <= 0):
        raise ValueError("region has zero area")
    return shift_moments(m, -m[..., 1, 0] / m[..., 0, 0], -m[..., 0, 1] / m[..., 0, 0])


def ellipse(mu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equivalent ellipse (a, b, theta) of central moments: semi-axes in px, theta in radians.

    theta is in (-pi/2, pi/2]; it is meaningless when a == b (a disc). For a stack of moments
    (..., n, n) each is an array of shape (...).
    """
    m00, mu20, mu02, mu11 = mu[..., 0, 0], mu[..., 2, 0], mu[..., 0, 2], mu[..., 1, 1]
    half_sum = 0.5 * (mu20 + mu02)
    radius = np.hypot(0.5 * (mu20 - mu02), mu11)
    a = 2.0 * np.sqrt((half_sum + radius) / m00)
    b = 2.0 * np.sqrt(np.maximum(half_sum - radius, 0.0) / m00)
    return a, b, 0.5 * np.arctan2(2.0 * mu11, mu20 - mu02)


def hu_moments(mu: np.ndarray) -> np.ndarray:
    """Hu's seven invariants (translation, scale and rotation; h7 flips sign under reflection).

    Shape (7,) for one (n, n) set of central moments, (..., 7) for a stack.
    """
    m00 = mu[..., 0, 0]
    second, third = m00 ** 2, m00 ** 2.5        # normalised central moments eta_pq = mu_pq / m00^(1 + (p+q)/2)
    n20, n02, n11 = mu[..., 2, 0] / second, mu[..., 0, 2] / second, mu[..., 1, 1] / second
    n30, n03, n21, n12 = mu[..., 3, 0] / third, mu[..., 0, 3] / third, mu[..., 2, 1] / third, mu[..., 1, 2] / third
    s1, s2 = n30 + n12, n21 + n03
    d1, d2 = n30 - 3 * n12, 3 * n21 - n03
    return np.stack([
        n20 + n02,
        (n20 - n02) ** 2 + 4 * n11 ** 2,
        d1 ** 2 + d2 ** 2,
        s1 ** 2 + s2 ** 2,
        d1 * s1 * (s1 ** 2 - 3 * s2 ** 2) + d2 * s2 * (3 * s1 ** 2 - s2 ** 2),
        (n20 - n02) * (s1 ** 2 - s2 ** 2) + 4 * n11 * s1 * s2,
        d2 * s1 * (s1 ** 2 - 3 * s2 ** 2) - d1 * s2 * (3 * s1 ** 2 - s2 ** 2),
    ], axis=-1)


@dataclass(frozen=True, eq=False)
class Region:
    """One connected region: label in the label image, moments and the equivalent ellipse.

    ``bbox`` is (x, y, width, height) in px; ``moments`` are the raw moments m[p, q] in image
    coordinates and ``central`` the central moments, both up to order 3.
    """

    label: int
    area: int
    bbox: tuple[int, int, int, int]
    centroid: tuple[float, float]
    moments: np.ndarray
    central: np.ndarray
    a: float
    b: float
    theta: float
    hu: np.ndarray

    @property
    def extent(self) -> float:
        """Fraction of the bounding box the region fills."""
        return self.area / float(self.bbox[2] * self.bbox[3])


def _regions(masks: list[np.ndarray], labels: list[int], boxes: list[tuple[int, int, int, int]]) -> list[Region]:
    """Regions of cropped boolean masks whose boxes (x, y, w, h) place them in the image."""
    if not masks:
        return []
    raw = np.stack([raw_moments(mask, ORDER, (x, y)) for mask, (x, y, _, _) in zip(masks, boxes, strict=True)])
    mu = central_moments(raw)
    a, b, theta = ellipse(mu)
    hu = hu_moments(mu)
    cx, cy = raw[:, 1, 0] / raw[:, 0, 0], raw[:, 0, 1] / raw[:, 0, 0]
    return [Region(label, int(round(raw[i, 0, 0])), box, (float(cx[i]), float(cy[i])), raw[i], mu[i],
                   float(a[i]), float(b[i]), float(theta[i]), hu[i])
            for i, (label, box) in enumerate(zip(labels, boxes, strict=True))]


def region_of(mask: np.ndarray, label: int = 1) -> Region:
    """Moments, ellipse and Hu invariants of the non-zero pixels of a whole-image ``mask``."""
    inside = np.asarray(mask) != 0
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if rows.size == 0:
        raise ValueError("region has zero area")
    x, y = int(cols[0]), int(rows[0])
    w, h = int(cols[-1]) - x + 1, int(rows[-1]) - y + 1
    return _regions([inside[y:y + h, x:x + w]], [label], [(x, y, w, h)])[0]


def find_regions(mask: np.ndarray, min_area: int = 1, max_area: int | None = None,
                 max_aspect: float | None = None, min_extent: float = 0.0,
                 connectivity: int = 8) -> tuple[np.ndarray, list[Region]]:
    """Label the connected non-zero regions of ``mask`` and keep those within the limits.

    min_area, max_area: pixel counts (inclusive). max_aspect: largest allowed a/b of the
    equivalent ellipse (None: any). min_extent: smallest fraction of the bounding box filled.
    connectivity: 4 or 8. Returns the label image (int32, 0 = background) and the kept
    regions ordered by decreasing area. Moments are computed per region over its bounding
    box; the ellipse and invariant arithmetic runs once over all regions.
    """
    if connectivity not in (4, 8):
        raise ValueError("connectivity must be 4 or 8")
    mask = np.asarray(mask)
    binary = mask if mask.dtype == np.uint8 else (mask != 0).astype(np.uint8)   # OpenCV: non-zero is foreground
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=connectivity)
    areas = stats[:, cv2.CC_STAT_AREA]
    keep = (areas >= min_area) & (areas >= min_extent * stats[:, cv2.CC_STAT_WIDTH] * stats[:, cv2.CC_STAT_HEIGHT])
    if max_area is not None:
        keep &= areas <= max_area
    keep[0] = False                                               # background
    kept = np.flatnonzero(keep)
    boxes = [(int(x), int(y), int(w), int(h)) for x, y, w, h in (stats[label, :4] for label in kept)]
    crops = [labels[y:y + h, x:x + w] == label for label, (x, y, w, h) in zip(kept, boxes, strict=True)]
    regions = _regions(crops, [int(label) for label in kept], boxes)
    if max_aspect is not None:
        regions = [r for r in regions if r.a <= max_aspect * r.b]
    regions.sort(key=lambda r: -r.area)
    return labels, regions
