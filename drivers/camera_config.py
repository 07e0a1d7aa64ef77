"""Camera options from a URL and the ``[camera]`` table of the robot config.

    v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG
    v4l2:///dev/v4l/by-id/usb-Logitech_C920-video-index0?fourcc=YUYV&raw_output=bgr8
    file:///data/clip.avi?pace=0          file:///data/frames/?fps=15&loop=1
    http://127.0.0.1:8090/stream.mjpg     (MJPEG over HTTP: IP cameras, `trundle emulate camera`)

Every option may be given in the table or as a URL query parameter (the URL wins). A wrong
option is the user's mistake: ``UserError`` with one line naming it.
"""

from __future__ import annotations

import dataclasses
import math
import urllib.parse
from dataclasses import dataclass, field
from typing import Any, Mapping

from trundle.drivers.v4l2_capture import CONTROLS
from trundle.logs.errors import UserError

SCHEMES = ("v4l2", "file", "http", "https")
RAW_OUTPUTS = ("jpeg", "bgr8", "mono8")
_TRUE, _FALSE = {"1", "true", "yes", "on"}, {"0", "false", "no", "off"}


@dataclass(frozen=True)
class CameraConfig:
    """What a camera driver needs. Units: pixels, Hz, seconds, metres and radians.

    ``transform`` is the camera body frame (REP 103: x forward) in ``parent_frame`` as
    ``[x, y, z, roll, pitch, yaw]``; images are stamped in ``optical_frame_id`` (x right, y
    down, z forward). ``raw_output`` says what frames that are not JPEG already (YUYV, decoded
    video) become: ``jpeg`` at ``jpeg_quality`` or a ``bgr8``/``mono8`` sensor_msgs/Image.
    ``decode_check_every`` N: libjpeg decodes every N-th JPEG as a health check (0: never).
    ``pace``/``loop`` apply to files; ``fps`` on a file overrides its recorded rate.
    """

    scheme: str
    target: str
    name: str = "camera"
    frame_id: str = "camera"
    optical_frame_id: str = "camera_optical"
    parent_frame: str = "base_link"
    transform: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    width: int = 0
    height: int = 0
    fps: float = 0.0
    fourcc: str = "MJPG"
    buffers: int = 2
    controls: Mapping[str, float] = field(default_factory=dict)
    calibration: str = ""
    raw_output: str = "jpeg"
    jpeg_quality: int = 90
    decode_check_every: int = 30
    stall_timeout_s: float = 2.0
    pace: bool = True
    loop: bool = False

    @property
    def topic_prefix(self) -> str:
        return "/" + self.name.strip("/")


_FIELDS = {f.name: f for f in dataclasses.fields(CameraConfig) if f.name not in ("scheme", "target")}


def _convert(name: str, value: Any) -> Any:
    """``value`` (from TOML or a URL string) as the type of option ``name``."""
    kind = _FIELDS[name].type
    text = isinstance(value, str)
    try:
        if kind == "bool":
            if isinstance(value, bool):
                return value
            if text and value.lower() in _TRUE | _FALSE:
                return value.lower() in _TRUE
            raise ValueError
        if kind == "int":
            if isinstance(value, bool) or (not text and not isinstance(value, int)):
                raise ValueError
            return int(value)
        if kind == "float":
            if isinstance(value, bool):
                raise ValueError
            number = float(value)
            if not math.isfinite(number):
                raise ValueError
            return number
        if kind == "str":
            if not text:
                raise ValueError
            return value
        if name == "transform":
            items = value.split(",") if text else value
            numbers = tuple(float(v) for v in items)
            if len(numbers) != 6 or not all(map(math.isfinite, numbers)):
                raise ValueError
            return numbers
        if name == "controls":
            if not isinstance(value, Mapping):
                raise ValueError
            return _controls(value)
    except (TypeError, ValueError):
        pass
    expected = {"bool": "true or false", "int": "an integer", "float": "a number", "str": "text"}.get(
        kind, "[x, y, z, roll, pitch, yaw]" if name == "transform" else "a table of control = value")
    raise UserError(f"camera option {name}={value!r} must be {expected}")


def _controls(table: Mapping[str, Any]) -> dict[str, float]:
    unknown = sorted(set(table) - set(CONTROLS))
    if unknown:
        raise UserError(f"unknown camera control {unknown[0]!r} (known: {', '.join(CONTROLS)})")
    values = {}
    for key, value in table.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"camera control {key}={value!r} must be a number")
        values[key] = float(value)
    return values


def _check(config: CameraConfig) -> None:
    if config.width < 0 or config.height < 0 or (config.width == 0) != (config.height == 0):
        raise UserError("camera width and height must be given together, as positive integers")
    if config.fps < 0:
        raise UserError(f"camera fps must be positive, not {config.fps:g}")
    if config.fourcc and (len(config.fourcc) != 4 or not config.fourcc.isascii()):
        raise UserError(f"camera fourcc must be four characters such as MJPG or YUYV, not {config.fourcc!r}")
    if not 1 <= config.buffers <= 32:
        raise UserError(f"camera buffers must be 1..32, not {config.buffers}")
    if config.raw_output not in RAW_OUTPUTS:
        raise UserError(f"camera raw_output must be one of {', '.join(RAW_OUTPUTS)}, not {config.raw_output!r}")
    if not 1 <= config.jpeg_quality <= 100:
        raise UserError(f"camera jpeg_quality must be 1..100, not {config.jpeg_quality}")
    if config.decode_check_every < 0:
        raise UserError("camera decode_check_every must be 0 (never) or a positive count")
    if config.stall_timeout_s <= 0:
        raise UserError("camera stall_timeout_s must be positive")
    if not config.name.strip("/"):
        raise UserError("camera name must not be empty")


def parse_camera_url(url: str, options: Mapping[str, Any] | None = None) -> CameraConfig:
    """The configuration for ``url`` with ``options`` (a config table) under its query parameters."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in SCHEMES:
        raise UserError(f"unknown camera URL {url!r}: use v4l2:///dev/videoN, file:///path or http://host:port/path")
    values: dict[str, Any] = {}
    table = {k: v for k, v in (options or {}).items() if k != "url"}
    query = urllib.parse.parse_qsl(parts.query, keep_blank_values=True)
    web = parts.scheme in ("http", "https")
    server_query = [(k, v) for k, v in query if web and k not in _FIELDS]  # the server's own parameters
    for source in (table, dict(kv for kv in query if kv not in server_query)):
        for key, value in source.items():
            if key not in _FIELDS:
                raise UserError(f"unknown camera option {key!r} (known: {', '.join(sorted(_FIELDS))})")
            values[key] = _convert(key, value)
    if web:
        target = urllib.parse.urlunsplit((parts.scheme, parts.netloc, parts.path,
                                          urllib.parse.urlencode(server_query), ""))
    else:
        target = urllib.parse.unquote(parts.netloc + parts.path)
        if not target:
            raise UserError(f"camera URL {url!r} names no device or file")
    config = CameraConfig(parts.scheme, target, **values)
    _check(config)
    return config
