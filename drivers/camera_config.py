"""Camera options from a URL and the ``[camera]`` table of the robot config.

    v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG
    v4l2:///dev/v4l/by-id/usb-Logitech_C920-video-index0?fourcc=YUYV&raw_output=bgr8
    file:///data/clip.avi?pace=0          file:///data/frames/?fps=15&loop=1
    http://127.0.0.1:8090/stream.mjpg     (MJPEG over HTTP: IP cameras, `trundle emulate camera`)

Every option may be given in the table or as a URL query parameter (the URL wins). A wrong
option is the user's mistake: ``ConfigError`` with one line naming it.
"""

from __future__ import annotations

import urllib.parse
from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, field_validator, model_validator

from trundle.drivers.v4l2_capture import CONTROLS
from trundle.logs.errors import ConfigError, UserError
from trundle.logs.schema import Name, Schema, parse_text

SCHEMES = ("v4l2", "file", "http", "https")


def _numbers(value: Any) -> Any:
    """A transform as a TOML array, or as text ``x,y,z,roll,pitch,yaw`` (a URL parameter)."""
    items = value.split(",") if isinstance(value, str) else value
    if not isinstance(items, (list, tuple)) or len(items) != 6:
        raise ValueError("expected six numbers [x, y, z, roll, pitch, yaw]")
    if isinstance(value, str):
        try:
            return tuple(float(v) for v in items)
        except ValueError:
            raise ValueError("expected six numbers [x, y, z, roll, pitch, yaw]") from None
    return tuple(items)


class CameraConfig(Schema):
    """What a camera driver needs. Units: pixels, Hz, seconds, metres and radians.

    ``transform`` is the camera body frame (REP 103: x forward) in ``parent_frame`` as
    ``[x, y, z, roll, pitch, yaw]``; images are stamped in ``optical_frame_id`` (x right, y
    down, z forward). ``raw_output`` says what frames that are not JPEG already (YUYV, decoded
    video) become: ``jpeg`` at ``jpeg_quality`` or a ``bgr8``/``mono8`` sensor_msgs/Image.
    ``decode_check_every`` N: libjpeg decodes every N-th JPEG as a health check (0: never).
    ``pace``/``loop`` apply to files; ``fps`` on a file overrides its recorded rate.
    ``width`` and ``height`` go together (0 and 0: the device's).
    """

    scheme: Literal["v4l2", "file", "http", "https"]
    target: Name
    name: Name = "camera"
    frame_id: Name = "camera"
    optical_frame_id: Name = "camera_optical"
    parent_frame: Name = "base_link"
    transform: Annotated[tuple[float, float, float, float, float, float], BeforeValidator(_numbers)] = (
        0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    width: Annotated[int, Field(ge=0)] = 0
    height: Annotated[int, Field(ge=0)] = 0
    fps: Annotated[float, Field(ge=0)] = 0.0
    fourcc: str = "MJPG"
    buffers: Annotated[int, Field(ge=1, le=32)] = 2
    controls: dict[str, float] = {}
    calibration: str = ""
    raw_output: Literal["jpeg", "bgr8", "mono8"] = "jpeg"
    jpeg_quality: Annotated[int, Field(ge=1, le=100)] = 90
    decode_check_every: Annotated[int, Field(ge=0)] = 30
    stall_timeout_s: Annotated[float, Field(gt=0)] = 2.0
    pace: bool = True
    loop: bool = False

    @field_validator("name")
    @classmethod
    def _name(cls, name: str) -> str:
        if not name.strip("/"):
            raise ValueError("expected a name (the topics' prefix)")
        return name

    @field_validator("fourcc")
    @classmethod
    def _fourcc(cls, fourcc: str) -> str:
        if fourcc and (len(fourcc) != 4 or not fourcc.isascii()):
            raise ValueError("expected four characters such as MJPG or YUYV")
        return fourcc

    @field_validator("controls")
    @classmethod
    def _controls(cls, controls: dict[str, float]) -> dict[str, float]:
        unknown = sorted(set(controls) - set(CONTROLS))
        if unknown:
            raise ValueError(f"unknown control {unknown[0]!r} (known: {', '.join(CONTROLS)})")
        return controls

    @model_validator(mode="after")
    def _size(self) -> CameraConfig:
        if (self.width == 0) != (self.height == 0):
            raise ValueError("width and height must be given together, as positive integers")
        return self

    @property
    def topic_prefix(self) -> str:
        return "/" + self.name.strip("/")


OPTIONS = set(CameraConfig.model_fields) - {"scheme", "target"}
"""The options of a ``[camera]`` table or a camera URL."""


def parse_camera_url(url: str, options: Mapping[str, Any] | None = None) -> CameraConfig:
    """The configuration for ``url`` with ``options`` (a config table) under its query parameters."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in SCHEMES:
        raise UserError(f"unknown camera URL {url!r}: use v4l2:///dev/videoN, file:///path or http://host:port/path")
    if "scheme" in (options or {}) or "target" in (options or {}):
        raise ConfigError("camera: the scheme and the device or file are the URL's (v4l2:///dev/video0)")
    table = {k: v for k, v in (options or {}).items() if k not in ("url", "enabled")}
    query = urllib.parse.parse_qsl(parts.query, keep_blank_values=True)
    web = parts.scheme in ("http", "https")
    server_query = [(k, v) for k, v in query if web and k not in OPTIONS]  # the server's own parameters
    if web:
        target = urllib.parse.urlunsplit((parts.scheme, parts.netloc, parts.path,
                                          urllib.parse.urlencode(server_query), ""))
    else:
        target = urllib.parse.unquote(parts.netloc + parts.path)
        if not target:
            raise ConfigError(f"camera URL {url!r} names no device or file")
    text = dict(kv for kv in query if kv not in server_query)
    return parse_text(CameraConfig, {**table, "scheme": parts.scheme, "target": target}, text, "camera")
