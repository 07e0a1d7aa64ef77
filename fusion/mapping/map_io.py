"""Map and trajectory files: map_server PGM + YAML (and its picture, see map_plot), trajectory and landmark CSV.

The PGM/YAML pair is what ROS's ``map_saver`` writes in trinary mode (nav2 defaults): occupied
cells (>= 65 %) black 0, free cells (<= 25 %) 254, unknown 205, top image row = largest y; the
YAML gives ``image``, ``mode``, ``resolution``, ``origin [x, y, yaw]``, ``negate``,
``occupied_thresh`` and ``free_thresh``, so ``map_server`` and nav2 load it as is. The YAML's
thresholds are those of the trinary pixels, not the ones the cells were classified with: 0.65 and
0.196 (as ROS 1's map_saver and nav2 since ros-navigation/navigation2#5278 write them), so the
unknown grey 205 (p = 0.1961) reads back as unknown; with ``free_thresh: 0.25`` map_server read
every unknown cell as free.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import cv2
import numpy as np
from ruamel.yaml import YAML, YAMLError

from trundle.logs.errors import DataError, UserError
from trundle.logs.messages import OccupancyGrid
from trundle.logs.outputs import encode_image, writing_file, writing_files
from trundle.logs.paths import input_file, read_text

OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.25  # the cells' classification (percent occupancy / 100)
SAVED_FREE_THRESH = 0.196  # the YAML's free_thresh: between the free (254) and unknown (205) pixels
OCCUPIED, FREE, UNKNOWN = 0, 254, 205


def map_image(grid: OccupancyGrid) -> np.ndarray:
    """Trinary grey image (H, W) uint8 of a map, north (largest y) up."""
    data = grid.data
    image = np.full(data.shape, UNKNOWN, np.uint8)
    image[(data >= 0) & (data <= FREE_THRESH * 100)] = FREE
    image[data >= OCCUPIED_THRESH * 100] = OCCUPIED
    return image[::-1].copy()


def save_map(grid: OccupancyGrid, base: str | os.PathLike[str], title: str = "occupancy map",
             replace: bool = False) -> tuple[Path, Path, Path]:
    """Write ``base.pgm``, ``base.yaml`` (map_server) and ``base.png`` (the map in metres with a scale
    bar and legend, :func:`trundle.fusion.mapping.map_plot.map_figure`), the three or none
    (:func:`trundle.logs.outputs.writing_files`; ``replace`` for a folder the command owns); returns them."""
    from trundle.fusion.mapping.map_plot import DPI, map_figure  # map_plot draws with map_image from here

    base = Path(base)
    pgm, yaml, png = base.with_suffix(".pgm"), base.with_suffix(".yaml"), base.with_suffix(".png")
    with writing_files(pgm, yaml, png, replace=replace) as (pgm_tmp, yaml_tmp, png_tmp):
        pgm_tmp.write_bytes(encode_image(map_image(grid), ".pgm", pgm))
        map_figure(grid, title).savefig(png_tmp, dpi=DPI, format="png")
        yaml_tmp.write_text(f"image: {pgm.name}\nmode: trinary\nresolution: {grid.resolution:.6g}\n"
                            f"origin: [{grid.origin_x:.6g}, {grid.origin_y:.6g}, {grid.origin_theta:.6g}]\n"
                            f"negate: 0\noccupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {SAVED_FREE_THRESH}\n")
    return pgm, yaml, png


def _map_number(data: dict, key: str, where: Path, low: float, high: float, default: float | None = None) -> float:
    """The map YAML's number ``key``, finite and within [low, high]; otherwise a DataError naming it."""
    value = data.get(key, default)
    if value is None:
        raise DataError(f"{where}: map YAML has no {key!r}")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (low <= value <= high):
        raise DataError(f"{where}: {key} = {value!r} must be a number in [{low:g}, {high:g}]")
    return float(value)


def load_map(yaml_path: str | os.PathLike[str], stamp_ns: int = 0, frame_id: str = "map") -> OccupancyGrid:
    """Read a map_server YAML + image as an OccupancyGrid (trinary: 100 occupied, 0 free, -1 unknown).

    Follows map_server: ``p = (255 - v) / 255`` (or ``v / 255`` with ``negate: 1``), occupied
    above ``occupied_thresh``, free below ``free_thresh``, unknown between. A missing, binary or
    inconsistent file (resolution <= 0, thresholds outside [0, 1], an unreadable image) is a
    DataError naming what is wrong (a missing one a UserError).
    """
    yaml_path = Path(yaml_path)
    if yaml_path.suffix.lower() in (".pgm", ".png", ".bmp", ".jpg", ".tif", ".tiff"):
        raise UserError(f"{yaml_path} is a map image: give its YAML (map.yaml) or the folder holding both")
    try:
        data = YAML(typ="safe", pure=True).load(read_text(yaml_path, "map YAML"))
    except YAMLError as error:
        raise DataError(f"{yaml_path} is not valid YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(data, dict) or not isinstance(data.get("image"), str):
        raise DataError(f"{yaml_path} is not a map_server map YAML (no image: line)")
    resolution = _map_number(data, "resolution", yaml_path, 1e-6, 1e3)  # metres per cell
    origin = data.get("origin")
    if not (isinstance(origin, list) and len(origin) in (2, 3)
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin)):
        raise DataError(f"{yaml_path}: origin = {origin!r} must be [x, y, yaw] (metres, radians)")
    negate = data.get("negate", 0)
    if negate not in (0, 1):
        raise DataError(f"{yaml_path}: negate = {negate!r} must be 0 or 1")
    occupied = _map_number(data, "occupied_thresh", yaml_path, 0.0, 1.0, OCCUPIED_THRESH)
    free = _map_number(data, "free_thresh", yaml_path, 0.0, 1.0, FREE_THRESH)
    if free > occupied:
        raise DataError(f"{yaml_path}: free_thresh {free} is above occupied_thresh {occupied}")
    image_path = input_file(yaml_path.parent / data["image"], "map image")
    image = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise DataError(f"cannot read map image {image_path}")
    p = image.astype(np.float64) / 255.0 if negate else (255.0 - image) / 255.0
    values = np.full(image.shape, -1, np.int8)
    values[p > occupied] = 100
    values[p < free] = 0
    return OccupancyGrid(stamp_ns, frame_id, resolution, float(origin[0]), float(origin[1]),
                         float(origin[2]) if len(origin) > 2 else 0.0, values[::-1])


def write_trajectory_csv(path: str | os.PathLike[str], stamps_ns: np.ndarray, poses: np.ndarray,
                         replace: bool = False, sessions: np.ndarray | None = None) -> None:
    """``t_ns,x,y,theta`` per row (metres, radians), header first, and a ``session`` column when ``sessions``
    are given (the map of several sessions); a new file (``replace``: or one of a folder the command owns),
    complete or not at all (:func:`trundle.logs.outputs.writing_file`)."""
    poses = np.asarray(poses, np.float64)
    with writing_file(path, replace=replace) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t_ns", "x", "y", "theta"] + ([] if sessions is None else ["session"]))
        tail = [[]] * len(poses) if sessions is None else [[int(k)] for k in sessions]
        for t, (x, y, theta), more in zip(np.asarray(stamps_ns, np.int64), poses, tail, strict=True):
            writer.writerow([int(t), f"{x:.6f}", f"{y:.6f}", f"{theta:.6f}", *more])


def read_trajectory_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (ns) and poses (N, 3) from a ``t_ns,x,y,theta`` file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"no such trajectory file: {path}")
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=str)
        stamps = np.array([int(v) for v in table[:, 0]], np.int64)
        poses = table[:, 1:4].astype(np.float64)
    except (ValueError, IndexError):
        raise DataError(f"{path}: not a t_ns,x,y,theta trajectory") from None
    return stamps, poses


LANDMARKS_HEADER = ["id", "x", "y", "sx", "sy"]


def write_landmarks_csv(path: str | os.PathLike[str], ids: list[str], positions: np.ndarray,
                        sigmas: np.ndarray, replace: bool = False) -> None:
    """``id,x,y,sx,sy`` per landmark: map-frame position (m) and its standard deviations in x and y (m);
    a new file (``replace``: or one of a folder the command owns), complete or not at all."""
    with writing_file(path, replace=replace) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(LANDMARKS_HEADER)
        for name, (x, y), (sx, sy) in zip(ids, np.asarray(positions, np.float64).reshape(-1, 2),
                                          np.asarray(sigmas, np.float64).reshape(-1, 2), strict=True):
            writer.writerow([name, f"{x:.6f}", f"{y:.6f}", f"{sx:.6f}", f"{sy:.6f}"])


def read_landmarks_csv(path: str | os.PathLike[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Ids, positions (M, 2) and standard deviations (M, 2) from an ``id,x,y,sx,sy`` file."""
    rows = list(csv.reader(io.StringIO(read_text(path, "landmark file (id,x,y,sx,sy)"), newline="")))
    if not rows or [c.strip() for c in rows[0]] != LANDMARKS_HEADER:
        raise DataError(f"{path}: not an {','.join(LANDMARKS_HEADER)} landmark file")
    try:
        values = np.array([[float(v) for v in row[1:5]] for row in rows[1:] if row], np.float64).reshape(-1, 4)
    except (ValueError, IndexError):
        raise DataError(f"{path}: a row is not id,x,y,sx,sy") from None
    if not np.all(np.isfinite(values[:, :2])):
        raise DataError(f"{path}: non-finite landmark position")
    return [row[0] for row in rows[1:] if row], values[:, :2], values[:, 2:]
