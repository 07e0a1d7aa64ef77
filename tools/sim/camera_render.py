"""What a level pinhole camera sees in a ``trundle.tools.sim.world.World``: walls, floor, ceiling, ArUco
markers and coloured objects, rendered exactly (no approximation beyond pixel sampling).

Every face in the world is vertical and floor-to-ceiling and the camera is level (no pitch or
roll), so each image column is one vertical plane: one ray cast per column (``cast_rays``, all
columns x all segments) gives the visible face and its depth, and each pixel of the column is
wall, floor or ceiling by its height. Pixels are coloured by vectorised look-ups: wall colour x a
plaster texture x Lambertian shading, a tiled floor, and each decal in view sampled with one
``cv2.remap`` from a pre-filtered (mip-mapped) image. Occlusion is exact.

Camera conventions are OpenCV's (optical frame: x right, y down, z forward; pixel (0, 0) is the
centre of the top-left pixel), so projections can be compared with ``cv2.aruco`` detections.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.tools.sim.world import MARKER_MARGIN, Decal, RayHits, World, cast_rays

TEXTURE_TILE_M = 2.0
TEXTURE_PX = 256
DECAL_MAX_PX = 384
WALL_PX_PER_M = 64.0
FLOOR_PX_PER_M = 40.0
ATLAS_WIDTH = 4096
ATLAS_MAX_PX = 32000  # cv2.remap needs source images under 32767 pixels a side
MIN_SIDE_PX, MAX_INCIDENCE_DEG = 24.0, 60.0   # a decal a detector should find: sides (px), facing within (deg)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of an undistorted pinhole camera (pixels)."""

    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def camera_info(self, stamp_ns: int = 0, frame_id: str = "camera_optical") -> m.CameraInfo:
        """sensor_msgs/CameraInfo for these intrinsics (plumb_bob, zero distortion)."""
        k = self.matrix()
        return m.CameraInfo(stamp_ns, frame_id, self.height, self.width, "plumb_bob", np.zeros(5), k,
                            np.eye(3), np.hstack([k, np.zeros((3, 1))]))

    def calibration_yaml(self, name: str = "trundle_sim") -> str:
        """The ROS ``camera_calibration`` file of these intrinsics (YAML in flow style, i.e. JSON),
        as a camera driver loads it to publish a calibrated CameraInfo."""
        k = self.matrix()
        return json.dumps({
            "image_width": self.width, "image_height": self.height, "camera_name": name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": k.ravel().tolist()},
            "distortion_model": "plumb_bob", "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": np.hstack([k, np.zeros((3, 1))]).ravel().tolist()},
        }, indent=1) + "\n"

    def scaled(self, width: int, height: int) -> PinholeCamera:
        """The same lens on a sensor of ``width`` x ``height`` pixels: horizontal field of view and
        pixel aspect kept, principal point offset from the centre scaled (e.g. 4:3 -> 16:9 crops)."""
        s = width / self.width
        return PinholeCamera(
            width,
            height,
            self.fx * s,
            self.fy * s,
            (width - 1) / 2 + (self.cx - (self.width - 1) / 2) * s,
            (height - 1) / 2 + (self.cy - (self.height - 1) / 2) * s,
        )


class CameraPose(NamedTuple):
    """A level camera in the map: position (m) and heading of its optical axis (rad)."""

    x: float
    y: float
    z: float
    yaw: float


def optical_rotation(yaw: float) -> np.ndarray:
    """Rotation (3x3) whose columns are the optical x (right), y (down), z (forward) axes in the map."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])


def project(points: np.ndarray, pose: CameraPose, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and depths (N,) (m along the optical axis) of map points (N, 3)."""
    local = (np.asarray(points, dtype=np.float64) - np.array([pose.x, pose.y, pose.z])) @ optical_rotation(pose.yaw)
    depth = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = np.stack([camera.fx * local[:, 0] / depth + camera.cx, camera.fy * local[:, 1] / depth + camera.cy], 1)
    return pixels, depth


def marker_image(dictionary: str, marker_id: int, cell_px: int) -> np.ndarray:
    """A printed marker: the ``cv2.aruco`` pattern with its white paper margin, grey uint8."""
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    bits = aruco.markerSize + 2
    pattern = cv2.aruco.generateImageMarker(aruco, marker_id, bits * cell_px, borderBits=1)
    pad = round(MARKER_MARGIN * bits * cell_px)
    return cv2.copyMakeBorder(pattern, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)


def _decal_rgba(decal: Decal, dictionary: str) -> np.ndarray:
    """The decal's picture (BGRA, alpha 0 where the wall shows through), paper edges included."""
    if decal.kind == "marker":
        aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        bits = aruco.markerSize + 2
        cell = max(4, round(DECAL_MAX_PX / (bits * (1 + 2 * MARKER_MARGIN))))
        grey = marker_image(dictionary, decal.marker_id, cell)
        return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)
    w = DECAL_MAX_PX
    h = max(8, round(DECAL_MAX_PX * decal.height / decal.width))
    image = np.zeros((h, w, 4), np.uint8)
    color = (*decal.color_bgr, 255)
    if decal.shape == "ellipse":
        cv2.ellipse(image, (((w - 1) / 2, (h - 1) / 2), (w, h), 0.0), color, -1, cv2.LINE_AA)
    else:
        image[:] = color
    return image


def _mip_levels(image: np.ndarray) -> list[np.ndarray]:
    """The image halved (area-averaged) down to 4 px wide, largest first."""
    levels = [image]
    while levels[-1].shape[1] > 8:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (max(1, w // 2), max(1, h // 2)), interpolation=cv2.INTER_AREA))
    return levels


def _plaster_texture(rng: np.random.Generator) -> np.ndarray:
    """A tileable grey texture (float32, mean 1, period ``TEXTURE_TILE_M``) giving walls the detail
    feature detectors need."""
    texture = np.zeros((TEXTURE_PX, TEXTURE_PX), np.float32)
    for scale, weight in ((4, 0.10), (16, 0.06), (64, 0.04)):
        coarse = rng.standard_normal((scale, scale)).astype(np.float32)
        big = cv2.resize(np.tile(coarse, (3, 3)), (3 * TEXTURE_PX, 3 * TEXTURE_PX), interpolation=cv2.INTER_CUBIC)
        texture += weight * big[TEXTURE_PX:2 * TEXTURE_PX, TEXTURE_PX:2 * TEXTURE_PX]
    return 1.0 + texture


class _Atlas(NamedTuple):
    """Every wall face, the floor and the ceiling in one BGR image, so a frame is one ``cv2.remap``.

    Atlas coordinates (pixel centres at integers) of a wall point ``(segment, along, z)`` are
    ``(wall_x[segment] + along * WALL_PX_PER_M, wall_y[segment] - z * WALL_PX_PER_M)``; of a floor
    point ``(X, Y)``, ``(floor_x + X * floor_px_per_m, floor_y + Y * floor_px_per_m)``.
    """

    image: np.ndarray
    wall_x: np.ndarray
    wall_y: np.ndarray
    floor_x: float
    floor_y: float
    floor_px_per_m: float
    ceiling_xy: tuple[float, float]


def _build_atlas(world: World, plaster: np.ndarray, skirting_m: float) -> _Atlas:
    """Paint each face (colour x plaster x fixed-light shading, dark skirting) and the tiled floor."""
    x0, y0, x1, y1 = world.bounds()
    x0, y0, x1, y1 = x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0
    floor_ppm = min(FLOOR_PX_PER_M, (ATLAS_MAX_PX - 2) / max(x1 - x0, y1 - y0))
    fw, fh = int(math.ceil((x1 - x0) * floor_ppm)), int(math.ceil((y1 - y0) * floor_ppm))
    centres_x = x0 + (np.arange(fw) + 0.5) / floor_ppm
    centres_y = y0 + (np.arange(fh) + 0.5) / floor_ppm
    tile = world.floor_tile_m
    parity = (np.floor(centres_x / tile)[None, :] + np.floor(centres_y / tile)[:, None]) % 2 == 0
    floor = np.where(
        parity[:, :, None], np.asarray(world.floor_bgr[0], np.uint8), np.asarray(world.floor_bgr[1], np.uint8)
    )

    seg = world.segments
    lengths = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    strip_w = np.ceil(lengths * WALL_PX_PER_M).astype(int) + 2      # one replicated texel each side
    strip_h = int(math.ceil(world.wall_height * WALL_PX_PER_M)) + 2
    width = int(max(ATLAS_WIDTH, fw, strip_w.max()))
    if width > ATLAS_MAX_PX:
        raise UserError(f"world '{world.name}': a wall of {lengths.max():.1f} m is too long to texture")
    positions, x, y = [], 0, fh
    for w in strip_w:                                                # shelf packing below the floor
        if x + w > width:
            x, y = 0, y + strip_h
        positions.append((x, y))
        x += w
    height = y + strip_h + 4
    atlas = np.empty((height, width, 3), np.uint8)
    atlas[:] = world.ceiling_bgr
    atlas[:fh, :fw] = floor

    light = np.array([0.6, 0.8])
    normal = np.stack([-(seg[:, 3] - seg[:, 1]), seg[:, 2] - seg[:, 0]], 1) / lengths[:, None]
    shade = 0.75 + 0.25 * np.abs(normal @ light)
    z = world.wall_height - (np.arange(strip_h) - 0.5) / WALL_PX_PER_M          # texel centre heights
    rows = ((z % TEXTURE_TILE_M) * TEXTURE_PX / TEXTURE_TILE_M).astype(int) % TEXTURE_PX
    skirting = np.clip((skirting_m - z) * WALL_PX_PER_M + 0.5, 0.0, 1.0).astype(np.float32)  # texel coverage
    for i, ((px, py), w) in enumerate(zip(positions, strip_w, strict=True)):
        along = (np.arange(w) - 0.5) / WALL_PX_PER_M
        cols = ((along % TEXTURE_TILE_M) * TEXTURE_PX / TEXTURE_TILE_M).astype(int) % TEXTURE_PX
        texture = plaster[rows[:, None], cols[None, :]]
        texture += skirting[:, None] * (0.45 - texture)
        colour = world.colors_bgr[i].astype(np.float32) * np.float32(shade[i])
        atlas[py:py + strip_h, px:px + w] = np.clip(texture[:, :, None] * colour, 0, 255).astype(np.uint8)
    positions_a = np.asarray(positions, dtype=np.float64)
    wall_x = positions_a[:, 0] + 1.0 - 0.5
    wall_y = positions_a[:, 1] + 1.0 + world.wall_height * WALL_PX_PER_M - 0.5
    return _Atlas(atlas, wall_x, wall_y, -x0 * floor_ppm - 0.5, -y0 * floor_ppm - 0.5, floor_ppm,
                  (width - 2.0, height - 2.0))


class CameraRenderer:
    """Renders BGR frames of ``world`` for a ``camera``; holds the pre-computed texture atlas.

    ``skirting_m`` is the height of the dark strip at the bottom of every wall; ``noise_sigma`` the
    standard deviation of pixel noise (grey levels) when ``render`` gets a generator. ``seed``
    fixes the textures so two renderers of the same world draw the same images.
    """

    def __init__(self, world: World, camera: PinholeCamera = PinholeCamera(), *, skirting_m: float = 0.1,
                 noise_sigma: float = 2.0, seed: int = 7) -> None:
        self.world = world
        self.camera = camera
        rng = np.random.default_rng(seed)
        self._atlas = _build_atlas(world, _plaster_texture(rng), skirting_m)
        self._noise = [rng.normal(0.0, noise_sigma, (camera.height, camera.width, 3)).round().astype(np.int16)
                       for _ in range(4)]
        self._decal_mips = [_mip_levels(_decal_rgba(d, world.aruco_dictionary)) for d in world.decals]
        u = np.arange(camera.width, dtype=np.float64)
        v = np.arange(camera.height, dtype=np.float64)
        self._col_angle = -np.arctan((u - camera.cx) / camera.fx)
        self._col_cos = np.cos(self._col_angle)
        self._lateral = (-(u - camera.cx) / camera.fx).astype(np.float32)[None, :]   # (1, W) left per metre ahead
        self._rows = v.astype(np.float32)[:, None]
        self._row_slope = ((v - camera.cy) / camera.fy).astype(np.float32)[:, None]  # (H, 1) down per metre ahead
        self._horizon = int(math.floor(camera.cy)) + 1                               # first row below the horizon
        seg = world.segments
        edge = seg[:, 2:] - seg[:, :2]
        self._unit = edge / np.hypot(edge[:, 0], edge[:, 1])[:, None]

    def render(self, pose: CameraPose, rng: np.random.Generator | None = None) -> np.ndarray:
        """The (H, W, 3) uint8 BGR image seen from ``pose``; with ``rng``, sensor noise added."""
        world, cam, atlas = self.world, self.camera, self._atlas
        if not 0.0 < pose.z < world.wall_height:
            raise ValueError(f"camera height {pose.z} m is not between floor and ceiling")
        angles = pose.yaw + self._col_angle
        hits = cast_rays(world.segments, (pose.x, pose.y), angles)
        seg = np.maximum(hits.segment, 0)
        hit = hits.segment >= 0
        depth = np.where(hit, hits.distance * self._col_cos, 0.0)                    # (W,) m along the axis
        v_bottom = np.where(hit, cam.cy + cam.fy * pose.z / np.where(hit, depth, 1.0), cam.cy)
        v_top = np.where(hit, cam.cy + cam.fy * (pose.z - world.wall_height) / np.where(hit, depth, 1.0), np.inf)
        wall = (self._rows >= v_top.astype(np.float32)) & (self._rows <= v_bottom.astype(np.float32))

        # Walls (and ceiling where no wall): atlas coordinates per pixel.
        ppm = WALL_PX_PER_M
        wall_x = (atlas.wall_x[seg] + np.nan_to_num(hits.along) * ppm).astype(np.float32)[None, :]
        wall_y0 = (atlas.wall_y[seg] - pose.z * ppm).astype(np.float32)[None, :]
        map_x = np.where(wall, wall_x, np.float32(atlas.ceiling_xy[0]))
        map_y = np.where(wall, wall_y0 + self._row_slope * (depth * ppm).astype(np.float32)[None, :],
                         np.float32(atlas.ceiling_xy[1]))

        # Floor: below the horizon, every pixel that is not wall sees the floor plane z = 0.
        below = slice(self._horizon, cam.height)
        ahead = np.float32(pose.z) / self._row_slope[below]                        # (Hb, 1) metres ahead
        c, s, f = math.cos(pose.yaw), math.sin(pose.yaw), atlas.floor_px_per_m
        floor_x = atlas.floor_x + pose.x * f + ahead * (f * (c - s * self._lateral))
        floor_y = atlas.floor_y + pose.y * f + ahead * (f * (s + c * self._lateral))
        on_floor = ~wall[below]
        np.copyto(map_x[below], floor_x.astype(np.float32), where=on_floor)
        np.copyto(map_y[below], floor_y.astype(np.float32), where=on_floor)
        image = cv2.remap(atlas.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

        ray = np.stack([np.cos(angles), np.sin(angles)], 1)
        for decal, mips in zip(world.decals, self._decal_mips, strict=True):
            self._draw_decal(image, decal, mips, hits, ray, depth, pose.z)
        if rng is not None:
            image = cv2.add(image, self._noise[rng.integers(len(self._noise))], dtype=cv2.CV_8U)
        return image

    def _draw_decal(self, image: np.ndarray, decal: Decal, mips: list[np.ndarray], hits: RayHits,
                    ray: np.ndarray, depth: np.ndarray, camera_z: float) -> None:
        """Paint one decal where its face is the visible surface, sampling a mip level that fits."""
        half_w, half_h = decal.width / 2 + decal.margin, decal.height / 2 + decal.margin
        facing = ray @ decal.normal < 0.0
        # Signed distance along the decal's "right" axis (viewer's right when facing it).
        right_dot_edge = self._unit[decal.segment] @ np.array([-math.sin(decal.yaw), math.cos(decal.yaw)])
        s = (hits.along - decal.along) * right_dot_edge
        cols = np.flatnonzero((hits.segment == decal.segment) & facing & (np.abs(s) <= half_w))
        if cols.size == 0:
            return
        c0, c1 = cols[0], cols[-1] + 1
        z = camera_z - self._row_slope * depth[None, c0:c1]                          # (H, C) heights
        inside = (np.abs(z - decal.z) <= half_h) & np.isin(np.arange(c0, c1), cols)[None, :]
        rows = np.flatnonzero(inside.any(axis=1))
        if rows.size == 0:
            return
        r0, r1 = rows[0], rows[-1] + 1
        z, inside = z[r0:r1], inside[r0:r1]
        level = next((lv for lv in reversed(mips) if lv.shape[1] >= max(c1 - c0, r1 - r0)), mips[0])
        h, w = level.shape[:2]
        map_x = np.broadcast_to(((s[c0:c1] + half_w) / (2 * half_w) * w - 0.5).astype(np.float32), z.shape)
        map_y = ((decal.z + half_h - z) / (2 * half_h) * h - 0.5).astype(np.float32)
        sampled = cv2.remap(level, np.ascontiguousarray(map_x), map_y, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        alpha = sampled[:, :, 3:4] * (inside[:, :, None] / np.float32(255.0))
        patch = image[r0:r1, c0:c1].astype(np.float32)
        image[r0:r1, c0:c1] = np.clip(patch + alpha * (sampled[:, :, :3] - patch) + 0.5, 0, 255).astype(np.uint8)

    def visible_decals(self, pose: CameraPose, *, min_side_px: float = MIN_SIDE_PX,
                       max_incidence_deg: float = MAX_INCIDENCE_DEG,
                       border_px: float = 4.0) -> list[tuple[Decal, np.ndarray]]:
        """Decals a detector should find from ``pose``, each with its projected corners (4, 2).

        A decal counts when it faces the camera within ``max_incidence_deg``, all its corners are
        in the image by ``border_px`` and in front of the camera, nothing stands between the camera
        and any corner, and its shortest projected side is at least ``min_side_px``.
        """
        cam = self.camera
        found = []
        for decal in self.world.decals:
            to_cam = np.array([pose.x - decal.x, pose.y - decal.y])
            dist = float(np.hypot(*to_cam))
            if dist == 0.0 or to_cam @ decal.normal / dist < math.cos(math.radians(max_incidence_deg)):
                continue
            corners = decal.corners()
            pixels, depth = project(corners, pose, cam)
            if (depth <= 0).any():
                continue
            inside = ((pixels[:, 0] >= border_px) & (pixels[:, 0] <= cam.width - 1 - border_px)
                      & (pixels[:, 1] >= border_px) & (pixels[:, 1] <= cam.height - 1 - border_px))
            sides = np.hypot(*(np.roll(pixels, -1, axis=0) - pixels).T)
            if not inside.all() or sides.min() < min_side_px:
                continue
            targets = corners[:, :2] + 1e-4 * decal.normal
            offsets = targets - np.array([pose.x, pose.y])
            reach = np.hypot(offsets[:, 0], offsets[:, 1])
            hits = cast_rays(self.world.segments, (pose.x, pose.y), np.arctan2(offsets[:, 1], offsets[:, 0]))
            if (hits.distance < reach - 1e-6).any():
                continue
            found.append((decal, pixels))
        return found
