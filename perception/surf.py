"""SURF: Speeded-Up Robust Features (Bay, Ess, Tuytelaars, Van Gool, CVIU 110(3), 2008).

No PyPI OpenCV wheel ships SURF (it is in the non-free part of opencv_contrib), so it is
implemented here, vectorised over all samples and keypoints:

- detector ("Fast-Hessian"): det = Dxx Dyy - (0.9 Dxy)^2 of box-filter second derivatives
  on the integral image, filter sizes 9, 15, 21, 27 per octave (x 2 and sampled every 2^o
  pixels in octave o), 3x3x3 non-maximum suppression, quadratic interpolation of position and
  scale (Brown and Lowe). By default the image is first doubled by linear interpolation (as
  Lowe does for SIFT), which adds a finer octave and localises keypoints better;
- orientation: Haar-wavelet responses of size 4s on a disc of radius 6s, sampled every s,
  Gaussian weights (sigma 2.5s, OpenCV's value; the paper says 2s), strongest vector sum in a
  sliding window of pi/3;
- descriptor: Haar responses of size 2s on a grid of spacing s along the orientation,
  pooled into 4 x 4 cells of (sum dx, sum dy, sum |dx|, sum |dy|): 64 floats of unit length.
  Layout "m-surf" (default; Agrawal, Konolige, Blas, ECCV 2008, as OpenSURF): 24s window,
  overlapping Gaussian-weighted cells; layout "surf": the paper's 20s window of disjoint cells.

Here s = 1.2 L / 9 for filter size L, and a keypoint's `size` is L (OpenCV's convention).
Box responses are box means, so `hessian_threshold` is on OpenCV's scale for 8-bit images.
Measured against OpenCV SIFT on the Oxford graf sequence: see docs/features.md.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from trundle.perception.images import to_gray
from trundle.perception.keypoints import Keypoints, concatenate, make_keypoints, strongest

BASE_SIZE = 9
SIZE_STEP = 6
ORIENTATION_RADIUS = 6
ORIENTATION_SIGMA = 2.5
ORIENTATION_BINS = 72                 # 5 degree bins
ORIENTATION_WINDOW = 12               # bins in the pi/3 sliding window
DEFAULT_THRESHOLD = 1000.0            # about as many keypoints as OpenCV SIFT's defaults give


def integral_image(gray: np.ndarray) -> np.ndarray:
    """(H+1, W+1) float64 integral image: ii[y, x] = sum of gray[:y, :x] (exact for uint8)."""
    return cv2.integral(gray, sdepth=cv2.CV_64F)


class _Grid:
    """Filter centres of one octave: anchors p = start + step * k on the integral image.

    A filter centre lies at p + 0.5 (a pixel centre) in the first octave and at p (a pixel
    corner) in the others, which keeps every box edge of the scaled filters on integers. In the
    first octave (every pixel a centre) box sums come from OpenCV's running-sum box filter
    (exact in float32 for these sizes); in the others from the integral image, strided.
    """

    def __init__(self, gray: np.ndarray, ii: np.ndarray, step: int, reach: float) -> None:
        self.gray, self.ii, self.step = gray, ii, step
        self.half = 0.5 if step == 1 else 0.0
        self.start = math.ceil(reach - self.half)
        rows, cols = ii.shape
        self.ky = max(0, (rows - 1 - math.ceil(reach + self.half) - self.start) // step + 1)
        self.kx = max(0, (cols - 1 - math.ceil(reach + self.half) - self.start) // step + 1)
        self._filtered: dict[tuple[int, int], np.ndarray] = {}
        self._phases: dict[tuple[int, int], np.ndarray] = {}

    def _corner(self, dy: float, dx: float) -> np.ndarray:
        y = self.start + int(round(dy * self.step + self.half))
        x = self.start + int(round(dx * self.step + self.half))
        phase = (y % self.step, x % self.step)
        if phase not in self._phases:   # contiguous copy per sampling phase: fast slices after
            self._phases[phase] = np.ascontiguousarray(self.ii[phase[0]::self.step, phase[1]::self.step])
        i, j = y // self.step, x // self.step
        return self._phases[phase][i:i + self.ky, j:j + self.kx]

    def box(self, y0: float, y1: float, x0: float, x1: float) -> np.ndarray:
        """Sum over [c + y0 s, c + y1 s) x [c + x0 s, c + x1 s) for every centre c."""
        if self.step > 1:
            total = self._corner(y1, x1) - self._corner(y0, x1) - self._corner(y1, x0) + self._corner(y0, x0)
            return total.astype(np.float32)
        h, w = int(y1 - y0), int(x1 - x0)
        if (h, w) not in self._filtered:
            self._filtered[h, w] = cv2.boxFilter(self.gray, cv2.CV_32F, (w, h), normalize=False,
                                                 borderType=cv2.BORDER_REPLICATE)
        y = self.start + int((y0 + y1) // 2)
        x = self.start + int((x0 + x1) // 2)
        return self._filtered[h, w][y:y + self.ky, x:x + self.kx]

    def pixel(self, k: np.ndarray) -> np.ndarray:
        """Pixel coordinate of the centre with grid index k."""
        return self.start + self.step * k + self.half - 0.5


def hessian_layer(grid: _Grid, size: int) -> np.ndarray:
    """det of the box-filter Hessian of base size `size` (9, 15, ...) on the grid's centres.

    Each second derivative is a sum of equal boxes (Dxx: lobes +1, -2, +1 of lobe x (2 lobe - 1);
    Dxy: four lobe x lobe quadrants +1, -1, -1, +1) divided by one box's area:
    det = Dxx Dyy - (0.9 Dxy)^2, the relative weight 0.9 of Bay et al.
    """
    lobe = size // 3
    tall, a, b = lobe - 0.5, lobe / 2, 1.5 * lobe
    dxx = np.add(grid.box(-tall, tall, -b, -a), grid.box(-tall, tall, a, b))
    middle = grid.box(-tall, tall, -a, a)
    dxx -= middle
    dxx -= middle
    dyy = np.add(grid.box(-b, -a, -tall, tall), grid.box(a, b, -tall, tall))
    middle = grid.box(-a, a, -tall, tall)
    dyy -= middle
    dyy -= middle
    near, far = 0.5, lobe + 0.5
    dxy = np.add(grid.box(-far, -near, -far, -near), grid.box(near, far, near, far))
    dxy -= grid.box(-far, -near, near, far)
    dxy -= grid.box(near, far, -far, -near)
    # det = Dxx Dyy / A^2 - 0.81 Dxy^2 / B^2 with A, B the box areas, in place
    area, quadrant = lobe * (2 * lobe - 1) * grid.step ** 2, lobe * lobe * grid.step ** 2
    dxx *= dyy
    dxy *= dxy
    dxy *= np.float32(0.81 * area ** 2 / quadrant ** 2)
    dxx -= dxy
    dxx *= np.float32(1.0 / area ** 2)
    return dxx


def _local_maxima(stack: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of samples above `threshold` that exceed all 26 neighbours (inner samples only)."""
    inner = stack[1:-1, 1:-1, 1:-1]
    z, y, x = np.nonzero(inner > threshold)
    z, y, x = z + 1, y + 1, x + 1
    value = stack[z, y, x]
    keep = np.ones(len(z), dtype=bool)
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dz or dy or dx:
                    keep &= value > stack[z + dz, y + dy, x + dx]
    return z[keep], y[keep], x[keep]


def _interpolate(stack: np.ndarray, z: np.ndarray, y: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (x, y, scale) of the quadratic's peak around each sample, and which are valid."""
    d = np.arange(-1, 2)
    cube = stack[z[:, None, None, None] + d[:, None, None], y[:, None, None, None] + d[:, None],
                 x[:, None, None, None] + d]
    c = cube[:, 1, 1, 1]
    grad = 0.5 * np.stack([cube[:, 1, 1, 2] - cube[:, 1, 1, 0], cube[:, 1, 2, 1] - cube[:, 1, 0, 1],
                           cube[:, 2, 1, 1] - cube[:, 0, 1, 1]], axis=1)
    hxx = cube[:, 1, 1, 2] - 2 * c + cube[:, 1, 1, 0]
    hyy = cube[:, 1, 2, 1] - 2 * c + cube[:, 1, 0, 1]
    hss = cube[:, 2, 1, 1] - 2 * c + cube[:, 0, 1, 1]
    hxy = 0.25 * (cube[:, 1, 2, 2] - cube[:, 1, 2, 0] - cube[:, 1, 0, 2] + cube[:, 1, 0, 0])
    hxs = 0.25 * (cube[:, 2, 1, 2] - cube[:, 2, 1, 0] - cube[:, 0, 1, 2] + cube[:, 0, 1, 0])
    hys = 0.25 * (cube[:, 2, 2, 1] - cube[:, 2, 0, 1] - cube[:, 0, 2, 1] + cube[:, 0, 0, 1])
    hessian = np.stack([np.stack([hxx, hxy, hxs], -1), np.stack([hxy, hyy, hys], -1),
                        np.stack([hxs, hys, hss], -1)], axis=1)
    solvable = np.abs(np.linalg.det(hessian)) > 1e-12 * np.maximum(np.abs(hessian).max(axis=(1, 2)) ** 3, 1e-300)
    offset = np.zeros_like(grad)
    if solvable.any():
        offset[solvable] = -np.linalg.solve(hessian[solvable], grad[solvable][:, :, None])[:, :, 0]
    valid = solvable & (np.abs(offset) <= 1.0).all(axis=1)
    return offset, valid


def detect_surf(image: np.ndarray, hessian_threshold: float = DEFAULT_THRESHOLD, n_octaves: int = 4,
                n_scales: int = 2, upsample: bool = True, mask: np.ndarray | None = None) -> Keypoints:
    """Fast-Hessian keypoints (no orientation yet), strongest first.

    `n_scales` interior filter sizes per octave are searched (each octave has n_scales + 2).
    `upsample`: search the image doubled by linear interpolation (filter sizes 4.5, 7.5, ...
    in image pixels in the first octave, numbered -1); the octaves then reach half as far.
    `mask`: uint8, keypoints only where it is non-zero. `octave` holds the octave.
    """
    gray = to_gray(image)
    zoom = 2 if upsample else 1
    # doubled in float32: the values are exact sixteenths, so box sums stay exact and the
    # result commutes with flips and transposition (uint8 resizing rounds axis by axis)
    work = cv2.resize(gray.astype(np.float32), None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR) if upsample else gray
    ii = integral_image(work)
    found = []
    for octave in range(n_octaves):
        step = 1 << octave
        sizes = [BASE_SIZE + SIZE_STEP * layer for layer in range(n_scales + 2)]
        grid = _Grid(work, ii, step, 1.5 * (sizes[-1] // 3) * step)
        if grid.ky < 3 or grid.kx < 3:
            break
        stack = np.empty((len(sizes), grid.ky, grid.kx), np.float32)
        for layer, size in enumerate(sizes):
            stack[layer] = hessian_layer(grid, size)
        z, y, x = _local_maxima(stack, hessian_threshold)
        offset, valid = _interpolate(stack, z, y, x)
        z, y, x, offset = z[valid], y[valid], x[valid], offset[valid]
        xy = np.column_stack([grid.pixel(x) + offset[:, 0] * step, grid.pixel(y) + offset[:, 1] * step])
        size = (BASE_SIZE + SIZE_STEP * (z + offset[:, 2])) * step
        found.append(make_keypoints((xy + 0.5) / zoom - 0.5, size / zoom, math.nan, stack[z, y, x],
                                    octave - (zoom - 1)))
    kp = concatenate(found)
    if mask is not None:
        col = np.clip(np.round(kp.xy).astype(int), 0, [gray.shape[1] - 1, gray.shape[0] - 1])
        kp = kp[np.asarray(mask)[col[:, 1], col[:, 0]] != 0]
    return kp[np.argsort(-kp.response, kind="stable")]


@functools.cache
def _disc() -> tuple[np.ndarray, np.ndarray]:
    r = np.arange(-ORIENTATION_RADIUS, ORIENTATION_RADIUS + 1)
    i, j = np.meshgrid(r, r, indexing="ij")
    inside = i * i + j * j <= ORIENTATION_RADIUS ** 2
    offsets = np.column_stack([j[inside], i[inside]]).astype(np.float64)
    weights = np.exp(-(offsets ** 2).sum(axis=1) / (2 * ORIENTATION_SIGMA ** 2))
    return offsets, weights


def _haar_disc(ii: np.ndarray, xy: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted Haar responses (dx, dy), each (N, 109), of size 4s on the disc of radius
    6s sampled every s around each point (pixel coordinates of the image `ii` integrates)."""
    offsets, weights = _disc()
    wavelet = 2 * np.maximum(np.round(2 * s), 1).astype(np.int64)
    rows, cols = ii.shape
    centre = xy[:, None, :] + offsets[None] * s[:, None, None]
    w = wavelet[:, None]
    x0 = np.round(centre[..., 0] - (w - 1) / 2).astype(np.int64)
    y0 = np.round(centre[..., 1] - (w - 1) / 2).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + w <= cols - 1) & (y0 + w <= rows - 1)
    x0, y0 = np.where(inside, x0, 0), np.where(inside, y0, 0)
    flat = ii.ravel()
    c = [[flat[yy * cols + xx] for xx in (x0, x0 + w // 2, x0 + w)] for yy in (y0, y0 + w // 2, y0 + w)]
    left = c[2][1] - c[0][1] - c[2][0] + c[0][0]
    right = c[2][2] - c[0][2] - c[2][1] + c[0][1]
    top = c[1][2] - c[0][2] - c[1][0] + c[0][0]
    bottom = c[2][2] - c[1][2] - c[2][0] + c[1][0]
    scale = weights[None] * inside / (w * w / 2.0)
    return (right - left) * scale, (bottom - top) * scale


def surf_orientation(image: np.ndarray, keypoints: Keypoints) -> np.ndarray:
    """Dominant orientation (radians, image frame) of each keypoint from Haar responses.

    Keypoints finer than a pixel (s < 1, from the doubled octave) are measured on the doubled
    image, so that their samples s apart stay distinct pixels.
    """
    if len(keypoints) == 0:
        return np.empty(0)
    gray = to_gray(image)
    s = 1.2 * keypoints.size / 9.0
    fine = s < 1.0
    dx = np.empty((len(keypoints), len(_disc()[1])))
    dy = np.empty_like(dx)
    if (~fine).any():
        dx[~fine], dy[~fine] = _haar_disc(integral_image(gray), keypoints.xy[~fine], s[~fine])
    if fine.any():
        doubled = cv2.resize(gray.astype(np.float32), None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
        dx[fine], dy[fine] = _haar_disc(integral_image(doubled), 2 * keypoints.xy[fine] + 0.5, 2 * s[fine])
    bins = (np.mod(np.arctan2(dy, dx), 2 * math.pi) * (ORIENTATION_BINS / (2 * math.pi))).astype(np.int64)
    bins = np.minimum(bins, ORIENTATION_BINS - 1) + ORIENTATION_BINS * np.arange(len(keypoints))[:, None]
    n_bins = ORIENTATION_BINS * len(keypoints)
    hx = np.bincount(bins.ravel(), dx.ravel(), n_bins).reshape(-1, ORIENTATION_BINS)
    hy = np.bincount(bins.ravel(), dy.ravel(), n_bins).reshape(-1, ORIENTATION_BINS)

    def windows(h: np.ndarray) -> np.ndarray:
        cs = np.cumsum(np.concatenate([np.zeros((len(h), 1)), h, h[:, :ORIENTATION_WINDOW - 1]], axis=1), axis=1)
        return cs[:, ORIENTATION_WINDOW:] - cs[:, :-ORIENTATION_WINDOW]

    wx, wy = windows(hx), windows(hy)
    best = np.argmax(wx * wx + wy * wy, axis=1)
    rows_ = np.arange(len(keypoints))
    return np.mod(np.arctan2(wy[rows_, best], wx[rows_, best]), 2 * math.pi)


class _Layout:
    """Sampling of the descriptor window: Haar responses on a `side` x `side` grid of spacing s,
    pooled into 4 x 4 cells by separable weights (4, side) and cell weights (4, 4)."""

    def __init__(self, name: str) -> None:
        if name == "surf":
            # Bay et al. 2008: 20s window, disjoint 5 x 5 cells, one Gaussian (3.3s) over it all
            self.side = 20
            pos = np.arange(self.side) + 0.5 - self.side / 2
            cell = np.arange(self.side) // 5
            self.weights = (cell[None] == np.arange(4)[:, None]) * np.exp(-pos ** 2 / (2 * 3.3 ** 2))[None]
            self.cells = np.ones((4, 4))
        elif name == "m-surf":
            # Agrawal, Konolige, Blas 2008 (CenSurE, "M-SURF"): 24s window, 9 x 9 cells 5s
            # apart (overlapping by 2s), Gaussian 2.5s per cell, Gaussian 1.5 cells over cells
            self.side = 24
            pos = np.arange(self.side) + 0.5 - self.side / 2
            d = pos[None] - ((np.arange(4) - 1.5) * 5)[:, None]
            self.weights = (np.abs(d) <= 4.5) * np.exp(-d ** 2 / (2 * 2.5 ** 2))
            c = np.arange(4) - 1.5
            self.cells = np.exp(-(c[:, None] ** 2 + c[None] ** 2) / (2 * 1.5 ** 2))
        else:
            raise ValueError(f"unknown SURF descriptor layout {name!r} (surf, m-surf)")


def _pyramid(gray: np.ndarray, finest: int, coarsest: int) -> list[np.ndarray]:
    """Images with pixels 2^k wide for k = finest (-1: doubled, or 0) .. coarsest (pyrDown)."""
    base = gray.astype(np.float32)
    levels: list[np.ndarray] = [base]
    if finest < 0:
        levels.insert(0, cv2.resize(base, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR))
    while finest + len(levels) <= coarsest and min(levels[-1].shape) >= 2:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def _sample_patches(gray: np.ndarray, keypoints: Keypoints, angle: np.ndarray, side: int) -> np.ndarray:
    """(N, side+1, side+1) grey values on each keypoint's rotated grid of spacing s, bilinear
    from the pyramid level whose pixel is just below s (so no level is undersampled)."""
    s = 1.2 * keypoints.size / 9.0
    exponent = np.floor(np.log2(np.maximum(s, 0.5))).astype(np.int64)
    first = min(int(exponent.min()), 0)
    levels = _pyramid(gray, first, int(exponent.max()))
    level = np.clip(exponent - first, 0, len(levels) - 1)
    grid = np.arange(side + 1, dtype=np.float64) - side / 2
    u, v = np.meshgrid(grid, grid)
    cos, sin = np.cos(angle), np.sin(angle)
    patches = np.empty((len(keypoints), side + 1, side + 1), np.float32)
    for k, image in enumerate(levels):
        idx = np.flatnonzero(level == k)
        if idx.size == 0:
            continue
        zoom = 2.0 ** (k + first)
        scale = (s[idx] / zoom)[:, None, None]
        # doubled level: x' = 2x + 0.5 (linear resize); pyrDown levels keep even pixels: x' = x / zoom
        shift = 0.5 if zoom < 1 else 0.0
        cx = (keypoints.xy[idx, 0] / zoom + shift)[:, None, None]
        cy = (keypoints.xy[idx, 1] / zoom + shift)[:, None, None]
        c, sn = cos[idx][:, None, None], sin[idx][:, None, None]
        map_x = (cx + scale * (u * c - v * sn)).astype(np.float32).reshape(len(idx), -1)
        map_y = (cy + scale * (u * sn + v * c)).astype(np.float32).reshape(len(idx), -1)
        for start in range(0, len(idx), 30000):
            part = slice(start, start + 30000)
            sampled = cv2.remap(image, map_x[part], map_y[part], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            patches[idx[part]] = sampled.reshape(-1, side + 1, side + 1)
    return patches


def describe_surf(image: np.ndarray, keypoints: Keypoints, upright: bool = False,
                  layout: str = "m-surf") -> tuple[Keypoints, np.ndarray]:
    """64-element SURF descriptors (float32, unit length) of `keypoints`.

    Keypoints without an angle get SURF's orientation (or angle 0 when `upright`); given
    angles are kept. `layout`: "m-surf" (default: overlapping Gaussian-weighted cells, as
    OpenSURF; more robust to viewpoint change) or "surf" (the 2008 paper's disjoint cells).
    Returns the keypoints (with their angles) and the descriptors, row for row.
    """
    gray = to_gray(image)
    pooling = _Layout(layout)
    if len(keypoints) == 0:
        return keypoints, np.empty((0, 64), np.float32)
    angle = keypoints.angle.copy()
    missing = np.isnan(angle)
    if upright:
        angle[missing] = 0.0
    elif missing.any():
        angle[missing] = surf_orientation(gray, keypoints[missing])
    keypoints = make_keypoints(keypoints.xy, keypoints.size, angle, keypoints.response, keypoints.octave)
    p = _sample_patches(gray, keypoints, angle, pooling.side)
    dx = p[:, :-1, 1:] - p[:, :-1, :-1] + p[:, 1:, 1:] - p[:, 1:, :-1]
    dy = p[:, 1:, :-1] - p[:, :-1, :-1] + p[:, 1:, 1:] - p[:, :-1, 1:]
    w = pooling.weights.astype(np.float32)

    def pool(a: np.ndarray) -> np.ndarray:
        return (w @ a @ w.T) * pooling.cells

    desc = np.stack([pool(dx), pool(dy), pool(np.abs(dx)), pool(np.abs(dy))], axis=-1).reshape(len(p), 64)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True) + 1e-7
    return keypoints, desc.astype(np.float32)


def surf(image: np.ndarray, hessian_threshold: float = DEFAULT_THRESHOLD, n_octaves: int = 4, n_scales: int = 2,
         upsample: bool = True, upright: bool = False, layout: str = "m-surf", max_keypoints: int | None = None,
         mask: np.ndarray | None = None) -> tuple[Keypoints, np.ndarray]:
    """Detect SURF keypoints and compute their 64-element descriptors (strongest first).

    `max_keypoints` keeps the strongest responses; other parameters as in `detect_surf` and
    `describe_surf`.
    """
    kp = detect_surf(image, hessian_threshold, n_octaves, n_scales, upsample, mask)
    kp = kp[strongest(kp, max_keypoints)]
    return describe_surf(image, kp, upright, layout)
