"""Local features: one `detect` for every detector of the chapter, descriptors, and both at once.

Detectors (`METHODS`): corners FAST, AGAST, Harris, Shi-Tomasi; blobs LoG, DoG, SIFT, SURF;
regions MSER; binary-descriptor pipelines ORB, AKAZE, BRISK; edges Canny, Sobel, Roberts
(edge pixels as keypoints, oriented along the gradient). OpenCV does the detecting where it
has the detector; SURF is ours (`trundle.perception.surf`); LoG/DoG blobs and Roberts edges are
numpy over OpenCV filters. Every keypoint has a position, a size and an orientation: where a
detector gives none, the intensity centroid of a disc around it (Rosin, as ORB) supplies it
(the gradient direction for edges, the major axis for MSER ellipses).

Descriptors (`DESCRIPTORS`): SIFT and SURF (float, L2), ORB, AKAZE and BRISK (binary,
Hamming). SIFT, SURF, ORB and BRISK describe any keypoints; AKAZE only its own.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import cv2
import numpy as np

from trundle.logs.errors import UserError
from trundle.perception import surf as surf_module
from trundle.perception.images import otsu_level, to_gray
from trundle.perception.keypoints import Keypoints, from_cv, make_keypoints, strongest, to_cv
from trundle.perception.regions import central_moments, ellipse

DESCRIPTORS = {"sift": "l2", "surf": "l2", "orb": "hamming", "akaze": "hamming", "brisk": "hamming"}
EDGES = ("canny", "sobel", "roberts")


@dataclass(frozen=True)
class Features:
    """Keypoints with their descriptors (row for row) and the metric to compare them with."""

    keypoints: Keypoints
    descriptors: np.ndarray
    metric: str


def opencv_factory(name: str) -> Callable | None:
    """An OpenCV constructor from cv2 or cv2.xfeatures2d (None when this build lacks it)."""
    return getattr(cv2, name, None) or getattr(getattr(cv2, "xfeatures2d", None), name, None)


_OPENCV = {"sift": "SIFT_create", "orb": "ORB_create", "akaze": "AKAZE_create", "brisk": "BRISK_create",
           "fast": "FastFeatureDetector_create", "agast": "AgastFeatureDetector_create",
           "mser": "MSER_create", "harris": "GFTTDetector_create", "shi-tomasi": "GFTTDetector_create"}


def available(method: str) -> bool:
    """Whether `method` can run with the installed OpenCV."""
    if method not in METHODS:
        return False
    return method not in _OPENCV or opencv_factory(_OPENCV[method]) is not None


def _create(method: str, params: dict[str, Any]) -> Any:  # the OpenCV Feature2D subclass of the method
    factory = opencv_factory(_OPENCV[method])
    if factory is None:
        raise UserError(f"{method} is not in this OpenCV build (cv2 {cv2.__version__})")
    try:
        return factory(**params)
    except (TypeError, cv2.error) as error:
        raise UserError(f"bad {method} parameters {params}: {error}") from None


# --- orientation where the detector gives none ---------------------------------------------------


@functools.cache
def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    y, x = np.meshgrid(r, r, indexing="ij")
    inside = x * x + y * y <= radius * radius
    return np.column_stack([x[inside], y[inside]])


def intensity_centroid_angle(gray: np.ndarray, keypoints: Keypoints, min_radius: int = 7,
                             max_radius: int = 31) -> np.ndarray:
    """Orientation atan2(m01, m10) of the intensity moments on a disc of radius size/2 (clipped
    to [min_radius, max_radius] px) around each keypoint (Rosin 1999; ORB's orientation)."""
    radius = np.clip(np.round(keypoints.size / 2), min_radius, max_radius).astype(np.int64)
    padded = cv2.copyMakeBorder(gray, max_radius, max_radius, max_radius, max_radius, cv2.BORDER_REFLECT_101)
    centre = np.round(keypoints.xy).astype(np.int64) + max_radius
    angle = np.empty(len(keypoints))
    for r in np.unique(radius):
        idx = np.flatnonzero(radius == r)
        disc = _disc(int(r))
        values = padded[centre[idx, 1, None] + disc[:, 1], centre[idx, 0, None] + disc[:, 0]].astype(np.float64)
        angle[idx] = np.arctan2(values @ disc[:, 1], values @ disc[:, 0])
    return np.mod(angle, 2 * math.pi)


def _oriented(gray: np.ndarray, kp: Keypoints) -> Keypoints:
    return make_keypoints(kp.xy, kp.size, intensity_centroid_angle(gray, kp), kp.response, kp.octave)


# --- detectors -----------------------------------------------------------------------------------


def _opencv_detector(method: str) -> Callable[..., Keypoints]:
    def run(gray: np.ndarray, mask: np.ndarray | None, **params: Any) -> Keypoints:
        detector = _create(method, params)
        kp = from_cv(detector.detect(gray, mask))
        return kp if not np.isnan(kp.angle).any() else _oriented(gray, kp)
    return run


def _gftt(harris: bool) -> Callable[..., Keypoints]:
    def run(gray: np.ndarray, mask: np.ndarray | None, max_corners: int = 2000, quality_level: float = 0.01,
            min_distance: float = 5.0, block_size: int = 3, k: float = 0.04) -> Keypoints:
        detector = _create("harris", dict(maxCorners=max_corners, qualityLevel=quality_level, minDistance=min_distance,
                                          blockSize=block_size, useHarrisDetector=harris, k=k))
        return _oriented(gray, from_cv(detector.detect(gray, mask)))
    return run


def _mser(gray: np.ndarray, mask: np.ndarray | None, **params: Any) -> Keypoints:
    """MSER regions (both polarities) as keypoints: centroid, equal-area diameter, ellipse axis."""
    regions, _ = _create("mser", params).detectRegions(gray)
    if not regions:
        return make_keypoints(np.empty((0, 2)), 0.0)
    lengths = np.array([len(r) for r in regions])
    points = np.concatenate(regions).astype(np.float64)
    label = np.repeat(np.arange(len(regions)), lengths)
    m = np.empty((len(regions), 3, 3))
    for p in range(3):
        for q in range(3):
            m[:, p, q] = np.bincount(label, points[:, 0] ** p * points[:, 1] ** q, len(regions))
    a, b, theta = ellipse(central_moments(m))
    centre = np.column_stack([m[:, 1, 0], m[:, 0, 1]]) / m[:, 0, :1]
    kp = make_keypoints(centre, 2.0 * np.sqrt(a * b), theta, m[:, 0, 0])
    return _inside_mask(kp, mask)


def _inside_mask(kp: Keypoints, mask: np.ndarray | None) -> Keypoints:
    if mask is None or len(kp) == 0:
        return kp
    h, w = mask.shape[:2]
    col = np.clip(np.round(kp.xy).astype(np.int64), 0, [w - 1, h - 1])
    return kp[np.asarray(mask)[col[:, 1], col[:, 0]] != 0]


def _blobs(kind: str) -> Callable[..., Keypoints]:
    """Scale-normalised LoG or DoG extrema over a geometric ladder of sigmas (both polarities)."""

    def run(gray: np.ndarray, mask: np.ndarray | None, min_sigma: float = 1.6, max_sigma: float = 16.0,
            scales_per_octave: int = 3, threshold: float = 0.02) -> Keypoints:
        image = gray.astype(np.float32) / 255.0
        k = 2.0 ** (1.0 / scales_per_octave)
        count = int(math.floor(math.log(max_sigma / min_sigma, k))) + 1
        sigmas = min_sigma * k ** np.arange(count + (1 if kind == "dog" else 0))
        blurred = [cv2.GaussianBlur(image, (0, 0), float(s)) for s in sigmas]
        if kind == "log":
            layers = [float(s * s) * np.abs(cv2.Laplacian(b, cv2.CV_32F)) for s, b in zip(sigmas, blurred, strict=True)]
        else:   # (G(k s) - G(s)) ~ (k - 1) s^2 LoG: divide by (k - 1) for LoG's scale
            layers = [np.abs(b1 - b0) / np.float32(k - 1) for b0, b1 in pairwise(blurred)]
            sigmas = sigmas[:-1]
        stack = np.stack(layers)
        spread = np.stack([cv2.dilate(layer, np.ones((3, 3), np.uint8)) for layer in layers])
        padded = np.concatenate([spread[:1] * 0, spread, spread[:1] * 0])
        neighbourhood = np.maximum(np.maximum(padded[:-2], padded[1:-1]), padded[2:])
        peaks = (stack == neighbourhood) & (stack > threshold)
        peaks[:, [0, -1]] = False
        peaks[:, :, [0, -1]] = False
        z, y, x = np.nonzero(peaks)
        kp = make_keypoints(np.column_stack([x, y]), 2.0 * math.sqrt(2.0) * sigmas[z], math.nan, stack[z, y, x], z)
        kp = _inside_mask(kp, mask)
        return _oriented(gray, kp[np.argsort(-kp.response, kind="stable")])

    return run


def edge_map(image: np.ndarray, method: str = "canny", threshold: float | None = None,
             low: float = 50.0, high: float = 150.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edge pixels and their gradient: (x, y, magnitude, direction in radians), all (N,).

    canny: OpenCV's Canny with hysteresis thresholds `low`, `high` (gradient from 3x3 Sobel);
    sobel: 3x3 Sobel magnitude above `threshold`; roberts: Roberts cross magnitude
    sqrt((I[y+1,x+1] - I[y,x])^2 + (I[y+1,x] - I[y,x+1])^2) above `threshold`, located at the
    2x2 block's centre. `threshold` None: Otsu's level of the magnitude histogram.
    """
    gray = to_gray(image)
    gx: np.ndarray
    gy: np.ndarray
    if method == "roberts":
        g = gray.astype(np.float32)
        d1 = g[1:, 1:] - g[:-1, :-1]
        d2 = g[1:, :-1] - g[:-1, 1:]
        magnitude = np.hypot(d1, d2)
        gx, gy = 0.5 * (d1 - d2), 0.5 * (d1 + d2)
        offset = 0.5
    elif method in ("sobel", "canny"):
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
        magnitude = np.hypot(gx, gy)
        offset = 0.0
    else:
        raise ValueError(f"unknown edge method {method!r} (canny, sobel, roberts)")
    if method == "canny":
        edges = cv2.Canny(gray, low, high, L2gradient=True) > 0
    else:
        if threshold is None:
            scaled = np.clip(magnitude * (255.0 / max(float(magnitude.max()), 1e-9)), 0, 255).astype(np.uint8)
            threshold = (otsu_level(np.bincount(scaled.ravel(), minlength=256)) + 0.5) * max(
                float(magnitude.max()), 1e-9) / 255.0
        edges = magnitude > threshold
    y, x = np.nonzero(edges)
    return (
        x + offset,
        y + offset,
        magnitude[y, x].astype(np.float64),
        np.mod(np.arctan2(gy[y, x], gx[y, x]), 2 * math.pi),
    )


def _edges(method: str) -> Callable[..., Keypoints]:
    def run(gray: np.ndarray, mask: np.ndarray | None, **params: Any) -> Keypoints:
        x, y, magnitude, direction = edge_map(gray, method, **params)
        kp = make_keypoints(np.column_stack([x, y]), 2.0 if method == "roberts" else 3.0, direction, magnitude)
        return _inside_mask(kp, mask)
    return run


def _surf(gray: np.ndarray, mask: np.ndarray | None, **params: Any) -> Keypoints:
    kp = surf_module.detect_surf(gray, mask=mask, **params)
    angle = surf_module.surf_orientation(gray, kp)
    return make_keypoints(kp.xy, kp.size, angle, kp.response, kp.octave)


METHODS: dict[str, Callable[..., Keypoints]] = {
    "sift": _opencv_detector("sift"), "surf": _surf, "orb": _opencv_detector("orb"),
    "akaze": _opencv_detector("akaze"), "brisk": _opencv_detector("brisk"), "mser": _mser,
    "fast": _opencv_detector("fast"), "agast": _opencv_detector("agast"),
    "harris": _gftt(True), "shi-tomasi": _gftt(False), "log": _blobs("log"), "dog": _blobs("dog"),
    "canny": _edges("canny"), "sobel": _edges("sobel"), "roberts": _edges("roberts"),
}


def detect(image: np.ndarray, method: str, max_keypoints: int | None = None, mask: np.ndarray | None = None,
           **params: Any) -> Keypoints:
    """Keypoints of `image` (grey or BGR uint8) by `method` (a key of METHODS).

    `params` go to the detector (OpenCV's parameter names for OpenCV detectors, e.g.
    `threshold=20` for FAST, `nfeatures=1000` for ORB); `max_keypoints` keeps the strongest
    responses; `mask` (uint8) restricts detection to its non-zero pixels.
    """
    if method not in METHODS:
        raise UserError(f"unknown feature detector {method!r} (choose from {', '.join(METHODS)})")
    gray = to_gray(image)
    kp = METHODS[method](gray, mask, **params)
    return kp[strongest(kp, max_keypoints)]


# --- descriptors ---------------------------------------------------------------------------------


def describe(image: np.ndarray, keypoints: Keypoints, method: str, **params: Any) -> tuple[Keypoints, np.ndarray]:
    """Descriptors of `keypoints` by `method` (a key of DESCRIPTORS); returns the keypoints kept
    (extractors drop some near the border) and their descriptors, row for row."""
    if method not in DESCRIPTORS:
        raise UserError(f"unknown descriptor {method!r} (choose from {', '.join(DESCRIPTORS)})")
    gray = to_gray(image)
    if method == "surf":
        return surf_module.describe_surf(gray, keypoints, **params)
    if method == "akaze":
        raise UserError("the AKAZE descriptor needs AKAZE's own keypoints: use detect_and_describe(..., 'akaze')")
    extractor = _create(method, params)
    # OpenCV extractors read `octave` as their own pyramid index: recode it for foreign keypoints
    octave = sift_octave(keypoints.size) if method == "sift" else 0
    plain = make_keypoints(keypoints.xy, keypoints.size, keypoints.angle, keypoints.response, octave)
    kept, descriptors = extractor.compute(gray, to_cv(plain))
    found = from_cv(kept)
    if method == "sift" and len(found) == len(keypoints):   # SIFT keeps every keypoint, in order
        found = make_keypoints(found.xy, found.size, found.angle, found.response, keypoints.octave)
    return found, _rows(descriptors, method)


def sift_octave(size: np.ndarray, sigma: float = 1.6, layers: int = 3) -> np.ndarray:
    """OpenCV SIFT's packed octave (octave | layer << 8) whose Gaussian image has the scale of
    keypoints of `size` (SIFT's size is 2 sigma): the descriptor then samples a suitably
    blurred, subsampled image, as for SIFT's own keypoints, instead of the full-size one."""
    t = np.log2(np.maximum(np.asarray(size, dtype=np.float64), 1e-6) / (2.0 * sigma))
    octave = np.clip(np.floor(t), -1, 30).astype(np.int64)
    layer = np.clip(np.round(layers * (t - octave)), 0, layers).astype(np.int64)
    return (octave & 255) | (layer << 8)


def _rows(descriptors: np.ndarray | None, method: str) -> np.ndarray:
    if descriptors is not None:
        return descriptors
    width = {"sift": 128, "surf": 64}.get(method, 64 if method == "brisk" else 32)
    return np.empty((0, width), np.float32 if DESCRIPTORS[method] == "l2" else np.uint8)


def detect_and_describe(image: np.ndarray, method: str, descriptor: str | None = None,
                        max_keypoints: int | None = None, mask: np.ndarray | None = None,
                        **params: Any) -> Features:
    """Detect by `method` and describe by `descriptor` (default: the method's own descriptor,
    SIFT's for detectors that have none). `params` go to the detector."""
    descriptor = descriptor or (method if method in DESCRIPTORS else "sift")
    if descriptor not in DESCRIPTORS:
        raise UserError(f"unknown descriptor {descriptor!r} (choose from {', '.join(DESCRIPTORS)})")
    if method == descriptor and method in _OPENCV:
        gray = to_gray(image)
        if max_keypoints is not None and method in ("sift", "orb") and "nfeatures" not in params:
            params["nfeatures"] = max_keypoints
        found, descriptors = _create(method, params).detectAndCompute(gray, mask)
        kp = from_cv(found)
        keep = strongest(kp, max_keypoints)
        return Features(kp[keep], _rows(descriptors, method)[keep], DESCRIPTORS[method])
    if method == descriptor == "surf":
        kp, descriptors = surf_module.surf(image, max_keypoints=max_keypoints, mask=mask, **params)
        return Features(kp, descriptors, "l2")
    kp, descriptors = describe(image, detect(image, method, max_keypoints, mask, **params), descriptor)
    return Features(kp, descriptors, DESCRIPTORS[descriptor])
