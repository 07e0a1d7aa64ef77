"""Synthetic planar scenes for feature tests: many corners and blobs of every grey level."""

from __future__ import annotations

import cv2
import numpy as np


def scene(seed: int = 0, shape: tuple[int, int] = (240, 320), shapes: int = 80, noise: float = 0.0) -> np.ndarray:
    """Grey uint8 image of random filled circles and rectangles, lightly blurred (+ Gaussian noise)."""
    rng = np.random.default_rng(seed)
    image = np.full(shape, 115, np.uint8)
    for _ in range(shapes):
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        colour = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(image, (x, y), int(rng.integers(3, 18)), colour, -1)
        else:
            cv2.rectangle(image, (x, y), (x + int(rng.integers(4, 30)), y + int(rng.integers(4, 30))), colour, -1)
    blurred = cv2.GaussianBlur(image, (0, 0), 0.8).astype(np.float64)
    return np.clip(blurred + rng.normal(0, noise, shape), 0, 255).round().astype(np.uint8)
