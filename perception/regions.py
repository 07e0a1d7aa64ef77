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

import cv2
import numpy as np
from scipy.special import comb

ORDER = 3


def raw_moments(image: np.ndarray, order: int = ORDER) -> np.ndarray:
    """Raw moments m[p, q] = sum_x sum_y x^p y^q I(y, x) for p, q <= ``order`` (float64).

    ``image`` is a 2-D array of weights (a mask counts as 0/1 if it is boolean; pass
    ``mask > 0`` for a 0/255 mask). Computed as two matrix products, exact for small arrays.
    """
    weights = np.asarray(image, dtype=np.float64)
    if weights.ndim != 2:
        raise ValueError(f"expected a 2-D array, got shape {weights.shape}")
    powers = np.arange(order + 1)
    xs = np.arange(weights.shape[1], dtype=np.float64)[:, None] ** powers   # (W, order+1)
    ys = np.arange(weights.shape[0], dtype=np.float64)[:, None] ** powers   # (H, order+1)
    return xs.T @ (weights.T @ ys)


def centroid(m: np.ndarray) -> tuple[float, float]:
    """(x0, y0) = (m10/m00, m01/m00) from raw moments; raises on an empty region."""
    if m[0, 0] <= 0:
        raise ValueError("region has zero area")
    return float(m[1, 0] / m[0, 0]), float(m[0, 1] / m[0, 0])


def shift_moments(m: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Moments of the same weights after moving the origin by (-dx, -dy): x -> x + dx, y -> y + dy.

    By the binomial theorem m'[p, q] = sum_i sum_j C(p, i) dx^(p-i) C(q, j) dy^(q-j) m[i, j].
    """
    k = np.arange(m.shape[0])
    binomial = np.tril(comb(k[:, None], k[None, :]))
    exponent = np.clip(k[:, None] - k[None, :], 0, None)
    return (binomial * dx ** exponent) @ m @ (binomial * dy ** exponent).T


def central_moments(m: np.ndarray) -> np.ndarray:
    """Central moments mu[p, q] = sum (x - x0)^p (y - y0)^q I from raw moments."""
    x0, y0 = centroid(m)
    return shift_moments(m, -x0, -y0)


def ellipse(mu: np.ndarray) -> tuple[float, float, float]:
    """Equivalent ellipse (a, b, theta) of central moments: semi-axes in px, theta in radians.

    theta is in (-pi/2, pi/2]; it is meaningless when a == b (a disc).
    """
    m00, mu20, mu02, mu11 = mu[0, 0], mu[2, 0], mu[0, 2], mu[1, 1]
    half_sum = 0.5 * (mu20 + mu02)
    radius = math.hypot(0.5 * (mu20 - mu02), mu11)
    lambda_a, lambda_b = half_sum + radius, max(half_sum - radius, 0.0)
    a = 2.0 * math.sqrt(lambda_a / m00)
    b = 2.0 * math.sqrt(lambda_b / m00)
    return a, b, 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)


def hu_moments(mu: np.ndarray) -> np.ndarray:
    """Hu's seven invariants (translation, scale and rotation; h7 flips sign under reflection)."""
    m00 = mu[0, 0]

    def eta(p: int, q: int) -> float:
        return mu[p, q] / m00 ** (1 + (p + q) / 2)

    n20, n02, n11 = eta(2, 0), eta(0, 2), eta(1, 1)
    n30, n03, n21, n12 = eta(3, 0), eta(0, 3), eta(2, 1), eta(1, 2)
    s1, s2 = n30 + n12, n21 + n03
    d1, d2 = n30 - 3 * n12, 3 * n21 - n03
    return np.array([
        n20 + n02,
        (n20 - n02) ** 2 + 4 * n11 ** 2,
        d1 ** 2 + d2 ** 2,
        s1 ** 2 + s2 ** 2,
        d1 * s1 * (s1 ** 2 - 3 * s2 ** 2) + d2 * s2 * (3 * s1 ** 2 - s2 ** 2),
        (n20 - n02) * (s1 ** 2 - s2 ** 2) + 4 * n11 * s1 * s2,
        d2 * s1 * (s1 ** 2 - 3 * s2 ** 2) - d1 * s2 * (3 * s1 ** 2 - s2 ** 2),
    ])


@dataclass(frozen=True)
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


def region_of(mask: np.ndarray, label: int = 1, offset: tuple[int, int] = (0, 0)) -> Region:
    """Moments, ellipse and Hu invariants of the non-zero pixels of ``mask``.

    ``offset`` (x, y) is where ``mask``'s pixel (0, 0) lies in the full image; moments are
    computed locally (less cancellation) and shifted to image coordinates.
    """
    inside = np.asarray(mask) != 0
    local = raw_moments(inside)
    mu = central_moments(local)
    x_local, y_local = centroid(local)
    ox, oy = offset
    # Raw moments about the image origin = central moments shifted by the full centroid.
    cx, cy = x_local + ox, y_local + oy
    moments = shift_moments(mu, cx, cy)
    rows, cols = np.nonzero(inside.any(axis=1))[0], np.nonzero(inside.any(axis=0))[0]
    bbox = (int(cols[0]) + ox, int(rows[0]) + oy, int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1))
    a, b, theta = ellipse(mu)
    return Region(label, int(round(local[0, 0])), bbox, (cx, cy), moments, mu, a, b, theta, hu_moments(mu))


def find_regions(mask: np.ndarray, min_area: int = 1, max_area: int | None = None,
                 max_aspect: float | None = None, min_extent: float = 0.0,
                 connectivity: int = 8) -> tuple[np.ndarray, list[Region]]:
    """Label the connected non-zero regions of ``mask`` and keep those within the limits.

    min_area, max_area: pixel counts (inclusive). max_aspect: largest allowed a/b of the
    equivalent ellipse (None: any). min_extent: smallest fraction of the bounding box filled.
    connectivity: 4 or 8. Returns the label image (int32, 0 = background) and the kept
    regions ordered by decreasing area.
    """
    if connectivity not in (4, 8):
        raise ValueError("connectivity must be 4 or 8")
    binary = (np.asarray(mask) != 0).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=connectivity)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = areas >= min_area
    if max_area is not None:
        keep &= areas <= max_area
    regions = []
    for label in np.flatnonzero(keep) + 1:
        x, y, w, h = stats[label, :4]
        if stats[label, cv2.CC_STAT_AREA] < min_extent * w * h:
            continue
        region = region_of(labels[y:y + h, x:x + w] == label, int(label), (int(x), int(y)))
        if max_aspect is not None and region.a > max_aspect * region.b:
            continue
        regions.append(region)
    regions.sort(key=lambda r: -r.area)
    return labels, regions
