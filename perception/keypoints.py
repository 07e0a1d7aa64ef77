"""Keypoints as arrays: position, size, orientation, response, octave of N local features.

Units follow OpenCV's `cv2.KeyPoint` so the two convert losslessly, except the angle: pixels
with the origin at the centre of the top-left pixel (x right, y down); `size` is the diameter
of the meaningful neighbourhood in pixels; `angle` is in radians in [0, 2 pi), measured from +x
towards +y (clockwise on screen, as OpenCV's degrees), NaN where a detector gives none.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Keypoints:
    """N keypoints: xy (N, 2) float64, size, angle, response (N,) float64, octave (N,) int."""

    xy: np.ndarray
    size: np.ndarray
    angle: np.ndarray
    response: np.ndarray
    octave: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)

    def __getitem__(self, index: np.ndarray | slice) -> Keypoints:
        return Keypoints(self.xy[index], self.size[index], self.angle[index], self.response[index],
                         self.octave[index])


def make_keypoints(xy: np.ndarray, size: np.ndarray | float, angle: np.ndarray | float = math.nan,
                   response: np.ndarray | float = 0.0, octave: np.ndarray | int = 0) -> Keypoints:
    """Keypoints from arrays or scalars broadcast to the number of positions."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)

    def column(value: np.ndarray | float, dtype: type) -> np.ndarray:
        return np.ascontiguousarray(np.broadcast_to(np.asarray(value, dtype=dtype), (n,)))

    angles = np.mod(column(angle, np.float64), 2 * math.pi)
    return Keypoints(xy, column(size, np.float64), angles, column(response, np.float64), column(octave, np.int64))


def concatenate(parts: list[Keypoints]) -> Keypoints:
    """All keypoints of `parts`, in order."""
    if not parts:
        return make_keypoints(np.empty((0, 2)), 0.0)
    return Keypoints(*(np.concatenate([getattr(k, name) for k in parts])
                       for name in ("xy", "size", "angle", "response", "octave")))


def from_cv(keypoints: Sequence[cv2.KeyPoint]) -> Keypoints:
    """Convert OpenCV keypoints (angle in degrees, -1 for none)."""
    if not keypoints:
        return make_keypoints(np.empty((0, 2)), 0.0)
    xy = np.array([k.pt for k in keypoints], dtype=np.float64)
    degrees = np.array([k.angle for k in keypoints], dtype=np.float64)
    return make_keypoints(xy, np.array([k.size for k in keypoints]),
                          np.where(degrees < 0, np.nan, np.radians(degrees)),
                          np.array([k.response for k in keypoints]), np.array([k.octave for k in keypoints]))


def to_cv(keypoints: Keypoints) -> list[cv2.KeyPoint]:
    """Convert to OpenCV keypoints (for OpenCV descriptors and drawing)."""
    degrees = np.where(np.isnan(keypoints.angle), -1.0, np.degrees(keypoints.angle))
    return [cv2.KeyPoint(float(x), float(y), float(s), float(a), float(r), int(o))
            for (x, y), s, a, r, o in zip(keypoints.xy, keypoints.size, degrees, keypoints.response,
                                          keypoints.octave, strict=True)]


def strongest(keypoints: Keypoints, limit: int | None) -> np.ndarray:
    """Indices of the `limit` keypoints with the largest response (all, in order, if None)."""
    if limit is None or limit >= len(keypoints):
        return np.arange(len(keypoints))
    return np.sort(np.argsort(-keypoints.response, kind="stable")[:limit])
