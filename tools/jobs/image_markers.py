"""Drawing detections as visualization_msgs/ImageMarker that Foxglove draws over the image.

Points are image pixel coordinates (x right, y down); a marker is stamped and framed like the
image it belongs to.
"""

from __future__ import annotations

import math

import numpy as np

from trundle.logs import messages as m

Rgba = tuple[float, float, float, float]
GREEN, YELLOW, CYAN, MAGENTA = (0.0, 1.0, 0.0, 1.0), (1.0, 1.0, 0.0, 1.0), (0.0, 1.0, 1.0, 1.0), (1.0, 0.0, 1.0, 1.0)
ELLIPSE_VERTICES = 36


def image_marker(msg: m.CompressedImage | m.Image, ns: str, kind: int, points: np.ndarray, color: Rgba,
                 scale: float = 2.0) -> m.ImageMarker:
    """One marker of ``kind`` (POINTS, LINE_LIST, ...) over the image ``msg``: ``points`` (N, 2) px,
    drawn ``scale`` px wide in ``color``."""
    return m.ImageMarker(msg.stamp_ns, msg.frame_id, ns, 0, kind, scale=scale, outline_color=color,
                         points=np.asarray(points, dtype=np.float64).reshape(-1, 2))


def closed_line_list(polygons: list[np.ndarray]) -> np.ndarray:
    """LINE_LIST points (pairs) drawing each (K, 2) polygon closed."""
    if not polygons:
        return np.zeros((0, 2))
    return np.concatenate([np.stack([p, np.roll(p, -1, axis=0)], axis=1).reshape(-1, 2) for p in polygons])


def ellipse_outline(centre: tuple[float, float], a: float, b: float, theta: float,
                    vertices: int = ELLIPSE_VERTICES) -> np.ndarray:
    """(vertices, 2) points on the ellipse with semi-axes a, b (px) rotated by theta (rad; image coordinates)."""
    t = np.linspace(0.0, 2 * math.pi, vertices, endpoint=False)
    c, s = math.cos(theta), math.sin(theta)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.column_stack([centre[0] + c * x - s * y, centre[1] + s * x + c * y])
