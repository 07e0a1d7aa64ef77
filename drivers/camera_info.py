"""``sensor_msgs/CameraInfo`` from a ROS ``camera_calibration`` YAML file (what
``cameracalibrator`` saves and ``camera_calibration_parsers`` reads):

    image_width: 640
    image_height: 480
    camera_name: narrow_stereo
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}      # optional, default identity
    projection_matrix: {rows: 3, cols: 4, data: [...]}         # optional, default [K | 0]

Without a calibration a camera publishes an uncalibrated CameraInfo (size only, K all zero), as
ROS ``camera_info_manager`` does, so viewers still learn the image size.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np
from ruamel.yaml import YAML, YAMLError

from trundle.logs import messages as m
from trundle.logs.errors import UserError


def _matrix(data: Mapping[str, Any], key: str, rows: int, cols: int | None, where: str) -> np.ndarray:
    """The ``{rows, cols, data}`` entry ``key`` as a float array of shape (rows, cols)."""
    entry = data.get(key)
    if not isinstance(entry, Mapping) or "data" not in entry:
        raise UserError(f"{where}: {key} must have rows, cols and data")
    values = entry["data"]
    if not isinstance(values, list):
        raise UserError(f"{where}: {key}.data must be a list of numbers")
    try:
        array = np.array(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: {key}.data must be a list of numbers") from None
    n_rows, n_cols = entry.get("rows", rows), entry.get("cols", cols if cols is not None else array.size)
    if n_rows != rows or (cols is not None and n_cols != cols) or array.size != n_rows * n_cols:
        shape = f"{rows}x{cols}" if cols is not None else f"{rows}xN"
        raise UserError(f"{where}: {key} must be {shape} (rows {n_rows}, cols {n_cols}, {array.size} values)")
    if not np.all(np.isfinite(array)):
        raise UserError(f"{where}: {key} holds a non-finite value")
    return array.reshape(rows, -1)


def camera_info_from_calibration(
    data: Any, frame_id: str, stamp_ns: int = 0, where: str = "calibration"
) -> m.CameraInfo:
    """CameraInfo from the parsed YAML mapping; ``UserError`` naming the bad entry otherwise."""
    if not isinstance(data, Mapping):
        raise UserError(f"{where}: not a camera_calibration YAML mapping")
    width, height = data.get("image_width"), data.get("image_height")
    if not isinstance(width, int) or not isinstance(height, int) or width <= 0 or height <= 0:
        raise UserError(f"{where}: image_width and image_height must be positive integers")
    k = _matrix(data, "camera_matrix", 3, 3, where)
    d = _matrix(data, "distortion_coefficients", 1, None, where).reshape(-1)
    r = _matrix(data, "rectification_matrix", 3, 3, where) if "rectification_matrix" in data else np.eye(3)
    p = (
        _matrix(data, "projection_matrix", 3, 4, where)
        if "projection_matrix" in data
        else np.hstack([k, np.zeros((3, 1))])
    )
    model = data.get("distortion_model", "plumb_bob")
    if not isinstance(model, str):
        raise UserError(f"{where}: distortion_model must be a name such as plumb_bob")
    return m.CameraInfo(stamp_ns, frame_id, height, width, model, d, k, r, p)


def load_camera_info(path: str | os.PathLike[str], frame_id: str, stamp_ns: int = 0) -> m.CameraInfo:
    """CameraInfo from a camera_calibration YAML file; a missing or bad file is a ``UserError``."""
    try:
        with open(path, encoding="utf-8") as f:
            data = YAML(typ="safe", pure=True).load(f)
    except FileNotFoundError:
        raise UserError(f"camera calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise UserError(f"cannot read camera calibration {path}: {error}") from None
    except YAMLError as error:
        raise UserError(f"{path} is not valid YAML: {str(error).splitlines()[0]}") from None
    return camera_info_from_calibration(data, frame_id, stamp_ns, where=str(path))


def uncalibrated_camera_info(width: int, height: int, frame_id: str, stamp_ns: int = 0) -> m.CameraInfo:
    """The CameraInfo of a camera without calibration: image size only, all matrices zero."""
    return m.CameraInfo(stamp_ns, frame_id, height, width, "", np.zeros(0), np.zeros((3, 3)), np.zeros((3, 3)),
                        np.zeros((3, 4)))
