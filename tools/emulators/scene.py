"""Static polygon scenes for the laser emulators, and the range source they hand to a device.

A scene file is TOML, units metres and radians, REP 103 (x forward, counter-clockwise)::

    pose = [0.0, 0.0, 0.0]     # x, y, yaw of the laser in the scene
    noise_m = 0.0              # standard deviation of Gaussian range noise
    [[polygon]]                # closed: the last point joins the first (a room, a box)
    points = [[-4.0, -3.0], [5.0, -3.0], [5.0, 3.5], [-4.0, 3.5]]
    [[polyline]]               # open: a wall piece
    points = [[1.0, 2.0], [2.5, 2.0]]

An emulator's range source is any callable ``ranges_at(t_s) -> ranges`` (metres, one per beam
of the emulator's ``angles``, +inf where nothing is hit): ``Scene.range_source`` makes one,
and the world simulator can pass its own instead.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from trundle.logs.errors import UserError
from trundle.logs.paths import read_text
from trundle.tools.sim.world import cast_rays

DEFAULT_SCENE = Path(__file__).with_name("room.toml")
RangeSource = Callable[[float], np.ndarray]


@dataclass(frozen=True)
class Scene:
    """Wall ``segments`` (S, 4) as x1 y1 x2 y2, the laser ``pose`` (x, y, yaw) and range noise."""

    segments: np.ndarray
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_m: float = 0.0

    def ranges(self, angles: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Distances (m) along beams at ``angles`` (rad, laser frame); +inf where nothing is hit."""
        x, y, yaw = self.pose
        distance = cast_rays(self.segments, (x, y), np.asarray(angles, np.float64) + yaw).distance
        if rng is not None and self.noise_m > 0:
            distance = distance + rng.normal(0.0, self.noise_m, distance.shape)
        return distance

    def range_source(self, angles: np.ndarray, seed: int = 0) -> RangeSource:
        """``ranges_at(t_s)`` for beams at ``angles``: exact ranges plus fresh noise per call."""
        angles = np.asarray(angles, np.float64).copy()
        exact = self.ranges(angles)
        rng = np.random.default_rng(seed)

        def ranges_at(t_s: float) -> np.ndarray:
            if self.noise_m <= 0:
                return exact.copy()
            return exact + rng.normal(0.0, self.noise_m, exact.shape)

        return ranges_at


def _points(value: Any, where: str) -> np.ndarray:
    try:
        points = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        points = np.zeros((0,))
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 2 or not np.all(np.isfinite(points)):
        raise UserError(f"{where}: points must be a list of at least two [x, y] pairs in metres")
    return points


def parse_scene(data: dict[str, Any], where: str = "scene") -> Scene:
    """Build a scene from parsed TOML (see the module docstring); UserError on a mistake."""
    unknown = set(data) - {"pose", "noise_m", "polygon", "polyline"}
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} (pose, noise_m, polygon, polyline)")
    segments = []
    for kind in ("polygon", "polyline"):
        items = data.get(kind, [])
        if not isinstance(items, list):
            raise UserError(f"{where}: [[{kind}]] must be an array of tables")
        for i, item in enumerate(items):
            if not isinstance(item, dict) or "points" not in item:
                raise UserError(f"{where}: {kind} {i + 1} needs points = [[x, y], ...]")
            points = _points(item["points"], f"{where}: {kind} {i + 1}")
            if kind == "polygon":
                points = np.vstack((points, points[:1]))
            segments.append(np.hstack((points[:-1], points[1:])))
    if not segments:
        raise UserError(f"{where}: no [[polygon]] or [[polyline]]: a scene needs walls")
    pose = data.get("pose", [0.0, 0.0, 0.0])
    try:
        x, y, yaw = (float(v) for v in pose)
        noise = float(data.get("noise_m", 0.0))
    except (TypeError, ValueError):
        raise UserError(f"{where}: pose must be [x, y, yaw] and noise_m a number") from None
    if not noise >= 0:
        raise UserError(f"{where}: noise_m must be non-negative")
    return Scene(np.vstack(segments), (x, y, yaw), noise)


def load_scene(path: str | Path = DEFAULT_SCENE) -> Scene:
    """Read a scene file; a missing or malformed file is a UserError."""
    path = Path(path)
    try:
        data = tomllib.loads(read_text(path, "scene file"))
    except tomllib.TOMLDecodeError as error:
        raise UserError(f"{path} is not a valid TOML scene: {error}") from None
    return parse_scene(data, str(path))
