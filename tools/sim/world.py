"""A 2-D world read from a floor-plan file, and what a planar laser range finder sees in it.

The floor plan is JSON (see ``tools/sim/worlds/office.json``): wall polylines and obstacle polygons
(every edge a vertical face from the floor to ``wall_height_m``), ArUco markers and coloured
objects hung on those faces at known poses, and a waypoint route. Units are metres and radians,
map frame per REP 103 (x east, y north, yaw counter-clockwise from x).

Ray casting intersects every beam with every segment at once (numpy broadcasting over
beams x segments); ``simulate_scan`` adds the sensor model: range noise, random and grazing
no-returns, maximum and minimum range, encoded as REP 117 says (+inf no return, -inf too close).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from trundle.logs.errors import UserError
from trundle.logs.paths import read_text

DEFAULT_WORLD = Path(__file__).with_name("worlds") / "office.json"
ON_WALL_TOLERANCE_M = 0.01
MARKER_MARGIN = 0.25  # white paper around a marker's black square, as a fraction of its side


@dataclass(frozen=True)
class Decal:
    """A flat rectangle hung on a wall face: an ArUco marker or a coloured object.

    ``x, y`` is the centre on the face, ``z`` the centre height, ``yaw`` the direction the face
    looks at (outward normal in the map). ``width`` x ``height`` in metres; for a marker both are
    the side length of the black square. ``segment`` indexes ``World.segments``; ``along`` is the
    centre's distance from that segment's first point.
    """

    kind: str
    name: str
    x: float
    y: float
    z: float
    yaw: float
    width: float
    height: float
    segment: int
    along: float
    marker_id: int = -1
    shape: str = "rectangle"
    color_bgr: tuple[int, int, int] = (0, 0, 0)

    @property
    def margin(self) -> float:
        """Width (m) of the white paper border around a marker; 0 for an object."""
        return MARKER_MARGIN * self.width if self.kind == "marker" else 0.0

    @property
    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.yaw), math.sin(self.yaw)])

    def corners(self) -> np.ndarray:
        """(4, 3) map points: top-left, top-right, bottom-right, bottom-left as a viewer facing it
        sees them (the order of ``cv2.aruco`` corners)."""
        right = np.array([-math.sin(self.yaw), math.cos(self.yaw), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        centre = np.array([self.x, self.y, self.z])
        hw, hh = self.width / 2.0, self.height / 2.0
        return np.stack([centre - hw * right + hh * up, centre + hw * right + hh * up,
                         centre + hw * right - hh * up, centre - hw * right - hh * up])


@dataclass(frozen=True)
class World:
    """Vertical faces as segments (S, 4) ``x1 y1 x2 y2`` with a colour each, decals and a route."""

    name: str
    segments: np.ndarray
    colors_bgr: np.ndarray
    wall_height: float
    markers: tuple[Decal, ...]
    objects: tuple[Decal, ...]
    route: np.ndarray
    start: tuple[float, float, float]
    aruco_dictionary: str = "DICT_6X6_250"
    floor_bgr: tuple[tuple[int, int, int], tuple[int, int, int]] = ((150, 150, 150), (120, 120, 120))
    floor_tile_m: float = 0.5
    ceiling_bgr: tuple[int, int, int] = (235, 235, 235)
    source: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def decals(self) -> tuple[Decal, ...]:
        return self.markers + self.objects

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of all segments."""
        xs, ys = self.segments[:, [0, 2]], self.segments[:, [1, 3]]
        return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())

    def marker(self, marker_id: int) -> Decal:
        for decal in self.markers:
            if decal.marker_id == marker_id:
                return decal
        raise KeyError(marker_id)


class RayHits(NamedTuple):
    """Nearest hit per ray: ``distance`` (m, +inf when nothing within range), ``segment`` index
    (-1 for no hit) and ``along`` (m from the segment's first point)."""

    distance: np.ndarray
    segment: np.ndarray
    along: np.ndarray


def cast_rays(segments: np.ndarray, origins: np.ndarray | tuple[float, float], angles: np.ndarray,
              max_range: float = np.inf) -> RayHits:
    """Intersect rays with segments, all rays x all segments at once.

    Parameters
    ----------
    segments : (S, 4) array of ``x1 y1 x2 y2`` in metres, S >= 1.
    origins : (2,) or (N, 2) ray origins in metres.
    angles : (N,) ray directions in radians (map frame).
    max_range : hits farther than this are ignored (m).
    """
    angles = np.asarray(angles, dtype=np.float64)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    seg = np.asarray(segments, dtype=np.float64)
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]
    ex, ey = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
    wx, wy = seg[:, 0] - o[:, 0:1], seg[:, 1] - o[:, 1:2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / (dx * ey - dy * ex)
        t = (wx * ey - wy * ex) * inv  # distance along the ray
        u = (wx * dy - wy * dx) * inv  # fraction along the segment
        miss = (u * (u - 1.0) > 0.0) | ~(t > 0.0)
    if max_range < np.inf:
        miss |= t > max_range
    t[miss] = np.inf
    nearest = np.argmin(t, axis=1)
    rows = np.arange(angles.shape[0])
    distance = t[rows, nearest]
    hit = np.isfinite(distance)
    along = np.where(hit, u[rows, nearest] * np.hypot(ex, ey)[nearest], np.nan)
    return RayHits(distance, np.where(hit, nearest, -1), along)


@dataclass(frozen=True)
class LaserModel:
    """A planar LRF: beam layout and error model (defaults: Hokuyo UTM-30LX, 40 Hz, 1081 beams).

    ``noise_sigma_m`` is the standard deviation of the Gaussian range error; ``dropout`` the
    probability that a beam returns nothing; beams meeting a face more obliquely than
    ``max_incidence_rad`` from its normal return nothing; hits beyond ``range_max`` are +inf and
    closer than ``range_min`` -inf (REP 117). ``time_increment`` is the time (s) between two
    beams of a sweeping laser: a moving robot casts each beam from where it is at that beam's
    time, as a real scanner does (0: the whole scan from one pose).
    """

    beams: int = 1081
    angle_min: float = -math.radians(135.0)
    angle_max: float = math.radians(135.0)
    range_min: float = 0.023
    range_max: float = 30.0
    noise_sigma_m: float = 0.01
    dropout: float = 0.002
    max_incidence_rad: float = math.radians(88.0)
    scan_time: float = 0.025
    time_increment: float = 0.0

    @property
    def angle_increment(self) -> float:
        return (self.angle_max - self.angle_min) / (self.beams - 1)

    def angles(self) -> np.ndarray:
        """Beam angles in the laser frame (rad, counter-clockwise, 0 ahead)."""
        return self.angle_min + self.angle_increment * np.arange(self.beams)


def simulate_scan(world: World, pose: tuple[float, float, float] | np.ndarray, model: LaserModel = LaserModel(),
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """Ranges (m, float64) a laser at ``pose`` (x, y, yaw of the laser in the map) measures.

    ``pose`` may also be one pose per beam (beams, 3): a sweep during which the laser moved.
    With ``rng`` None the ranges are exact (no noise, no random dropouts); the deterministic
    parts of the model (max/min range, grazing incidence) always apply.
    """
    poses = np.asarray(pose, dtype=np.float64).reshape(-1, 3)
    angles = poses[:, 2] + model.angles()
    hits = cast_rays(world.segments, poses[:, :2], angles)
    ranges = hits.distance.copy()
    hit = hits.segment >= 0
    seg = world.segments[np.maximum(hits.segment, 0)]
    edge = seg[:, 2:] - seg[:, :2]
    cos_incidence = np.abs(np.cos(angles) * edge[:, 1] - np.sin(angles) * edge[:, 0]) / np.hypot(edge[:, 0], edge[:, 1])
    grazing = hit & (cos_incidence < math.cos(model.max_incidence_rad))
    if rng is not None:
        ranges = ranges + rng.normal(0.0, model.noise_sigma_m, ranges.shape)
        grazing |= rng.random(ranges.shape) < model.dropout
    ranges[grazing | (ranges > model.range_max)] = np.inf
    ranges[hit & (ranges < model.range_min)] = -np.inf
    return ranges


_MISSING = object()


def _require(mapping: dict[str, Any], key: str, where: str) -> Any:
    if key not in mapping:
        raise UserError(f"{where}: missing key '{key}'")
    return mapping[key]


def _number(mapping: dict[str, Any], key: str, where: str, default: Any = _MISSING, *,
            positive: bool = False) -> float:
    """A finite number from the plan (``default`` when absent; required when no default)."""
    value = _require(mapping, key, where) if default is _MISSING else mapping.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise UserError(f"{where}: '{key}' must be a finite{' positive' if positive else ''} number, got {value!r}")
    return float(value)


def _points(value: Any, where: str) -> np.ndarray:
    try:
        points = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        points = np.zeros((0,))
    if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] < 2 or not np.isfinite(points).all():
        raise UserError(f"{where}: expected a list of at least two [x, y] points")
    return points


def _color(value: Any, where: str) -> tuple[int, int, int]:
    if not (isinstance(value, list) and len(value) == 3 and all(isinstance(c, int) and 0 <= c <= 255 for c in value)):
        raise UserError(f"{where}: colour must be [b, g, r] with integers 0-255")
    return (value[0], value[1], value[2])


def _list(data: dict[str, Any], key: str, where: str) -> list[Any]:
    value = data.get(key, [])
    if not isinstance(value, list):
        raise UserError(f"{where}: '{key}' must be a list")
    return value


def _check_keys(item: dict[str, Any], allowed: set[str], where: str) -> None:
    if not isinstance(item, dict):
        raise UserError(f"{where}: expected an object")
    unknown = sorted(set(item) - allowed)
    if unknown:
        raise UserError(f"{where}: unknown key '{unknown[0]}' (allowed: {', '.join(sorted(allowed))})")


def _place_decal(kind: str, item: dict[str, Any], where: str, segments: np.ndarray, wall_height: float,
                 **extra: Any) -> Decal:
    """Find the face a decal hangs on: the segment through its centre whose normal side it faces."""
    x, y, z, yaw = (_number(item, k, where) for k in ("x", "y", "z", "yaw"))
    if kind == "marker":
        width = height = _number(item, "size", where, positive=True)
    else:
        width, height = _number(item, "width", where, positive=True), _number(item, "height", where, positive=True)
    margin = MARKER_MARGIN * width if kind == "marker" else 0.0
    paper_w, paper_h = width + 2 * margin, height + 2 * margin
    p, e = segments[:, :2], segments[:, 2:] - segments[:, :2]
    length = np.hypot(e[:, 0], e[:, 1])
    along = ((x - p[:, 0]) * e[:, 0] + (y - p[:, 1]) * e[:, 1]) / length
    off = np.abs((x - p[:, 0]) * e[:, 1] - (y - p[:, 1]) * e[:, 0]) / length
    normal_dot_edge = (math.cos(yaw) * e[:, 0] + math.sin(yaw) * e[:, 1]) / length
    fits = ((off < ON_WALL_TOLERANCE_M) & (along - paper_w / 2 >= -1e-9) & (along + paper_w / 2 <= length + 1e-9)
            & (np.abs(normal_dot_edge) < 1e-6))
    if not fits.any():
        raise UserError(f"{where}: not flat on any wall face (centre {x:.3f}, {y:.3f}, yaw {yaw:.4f} rad)")
    if z - paper_h / 2 < 0.0 or z + paper_h / 2 > wall_height:
        raise UserError(f"{where}: does not fit between floor and ceiling (z {z}, height {paper_h})")
    segment = int(np.flatnonzero(fits)[0])
    return Decal(kind, str(item.get("name", extra.get("marker_id", ""))), x, y, z, yaw, width, height, segment,
                 float(along[segment]), **extra)


def parse_world(data: dict[str, Any], where: str = "world") -> World:
    """Build a ``World`` from the decoded floor-plan JSON; every mistake is a one-line UserError."""
    _check_keys(data, {"name", "wall_height_m", "aruco_dictionary", "walls", "obstacles", "markers", "objects",
                       "route", "start", "floor", "ceiling_bgr", "comment"}, where)
    wall_height = _number(data, "wall_height_m", where, 2.5, positive=True)
    segments: list[np.ndarray] = []
    colors: list[tuple[int, int, int]] = []
    for kind in ("walls", "obstacles"):
        for i, item in enumerate(_list(data, kind, where)):
            at = f"{where}: {kind}[{i}]"
            _check_keys(item, {"name", "points", "closed", "color_bgr"}, at)
            points = _points(_require(item, "points", at), at)
            closed = item.get("closed", kind == "obstacles")
            if not isinstance(closed, bool):
                raise UserError(f"{at}: 'closed' must be true or false")
            if closed:
                points = np.vstack([points, points[:1]])
            pieces = np.hstack([points[:-1], points[1:]])
            if (np.hypot(pieces[:, 2] - pieces[:, 0], pieces[:, 3] - pieces[:, 1]) == 0).any():
                raise UserError(f"{at}: two consecutive points are equal")
            segments.append(pieces)
            colors.extend([_color(item.get("color_bgr", [200, 200, 200]), at)] * len(pieces))
    if not segments:
        raise UserError(f"{where}: no walls")
    seg = np.vstack(segments)
    dictionary = data.get("aruco_dictionary", "DICT_6X6_250")
    if not (isinstance(dictionary, str) and dictionary.startswith("DICT_") and hasattr(cv2.aruco, dictionary)):
        raise UserError(f"{where}: unknown aruco_dictionary {dictionary!r} (e.g. DICT_6X6_250)")
    id_count = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList.shape[0]
    markers, ids = [], set()
    for i, item in enumerate(_list(data, "markers", where)):
        at = f"{where}: markers[{i}]"
        _check_keys(item, {"id", "x", "y", "z", "yaw", "size", "name"}, at)
        marker_id = _require(item, "id", at)
        if (
            not isinstance(marker_id, int)
            or isinstance(marker_id, bool)
            or not 0 <= marker_id < id_count
            or marker_id in ids
        ):
            raise UserError(f"{at}: id {marker_id!r} is not in 0-{id_count - 1} or is repeated")
        ids.add(marker_id)
        markers.append(_place_decal("marker", item, at, seg, wall_height, marker_id=marker_id))
    objects = []
    for i, item in enumerate(_list(data, "objects", where)):
        at = f"{where}: objects[{i}]"
        _check_keys(item, {"name", "x", "y", "z", "yaw", "width", "height", "shape", "color_bgr"}, at)
        shape = item.get("shape", "rectangle")
        if shape not in ("rectangle", "ellipse"):
            raise UserError(f"{at}: shape must be 'rectangle' or 'ellipse'")
        objects.append(_place_decal("object", item, at, seg, wall_height, shape=shape,
                                    color_bgr=_color(_require(item, "color_bgr", at), at)))
    route = _points(_require(data, "route", where), f"{where}: route")
    heading = math.atan2(route[1, 1] - route[0, 1], route[1, 0] - route[0, 0])
    start = data.get("start", [route[0, 0], route[0, 1], heading])
    if not (isinstance(start, list) and len(start) == 3):
        raise UserError(f"{where}: 'start' must be [x, y, yaw]")
    start = [_number({"start": v}, "start", where) for v in start]
    floor = data.get("floor", {})
    _check_keys(floor, {"tile_m", "colors_bgr"}, f"{where}: floor")
    floor_colors = floor.get("colors_bgr", [[150, 150, 150], [120, 120, 120]])
    if not (isinstance(floor_colors, list) and len(floor_colors) == 2):
        raise UserError(f"{where}: floor 'colors_bgr' must be two [b, g, r] colours")
    return World(
        str(data.get("name", "world")),
        seg,
        np.array(colors, dtype=np.uint8),
        wall_height,
        tuple(markers),
        tuple(objects),
        route,
        (float(start[0]), float(start[1]), float(start[2])),
        dictionary,
        (_color(floor_colors[0], f"{where}: floor"), _color(floor_colors[1], f"{where}: floor")),
        _number(floor, "tile_m", f"{where}: floor", 0.5, positive=True),
        _color(data.get("ceiling_bgr", [235, 235, 235]), where),
        data,
    )


def load_world(path: str | Path = DEFAULT_WORLD) -> World:
    """Read a floor-plan JSON file (default: the office that ships with trundle)."""
    path = Path(path)
    try:
        data = json.loads(read_text(path, "floor-plan JSON file"))
    except json.JSONDecodeError as error:
        raise UserError(f"{path}: not valid JSON ({error.msg} at line {error.lineno})") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: a floor plan is a JSON object, not {type(data).__name__}")
    return parse_world(data, str(path))
