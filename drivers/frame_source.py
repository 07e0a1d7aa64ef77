"""The seam between the camera driver and where frames come from (V4L2, a file, a stream).

A source yields ``Frame``s: either the camera's own JPEG bytes (to be logged unchanged) or a
pixel array, with the capture time on the host's CLOCK_MONOTONIC. The driver checks, stamps
(monotonic -> wall) and publishes them; the source only captures.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from trundle.logs.errors import DeviceError


@dataclass(frozen=True, slots=True)
class Frame:
    """One captured frame.

    ``data`` is the JPEG bytes when ``jpeg`` is True, else an H x W x 3 BGR (or H x W mono)
    uint8 array. ``t_ns`` is the capture time on CLOCK_MONOTONIC (the V4L2 buffer timestamp,
    or for a file its media time after the stream's start); ``recv_ns`` when the host got it,
    on the same clock.
    """

    data: bytes | np.ndarray
    jpeg: bool
    t_ns: int
    recv_ns: int


class EndOfStream(Exception):
    """A file source has delivered its last frame."""


class StallError(DeviceError):
    """The source delivered no new frame in time."""


class FrameSource(Protocol):
    """Where frames come from. ``live`` sources are cameras (keep only the newest frame when the
    reader falls behind); others are files (deliver every frame). A ``paced`` source's frames
    are handed over no earlier than their ``t_ns``, as a camera would deliver them."""

    description: str
    live: bool
    paced: bool

    def open(self) -> None:
        """Open the device or file; raise ``DeviceError`` (or ``OSError``) when it cannot be opened."""

    def read(self) -> Frame | None:
        """The next frame; None when no new frame came (not an error); raise ``DeviceError`` on
        loss of the device, ``StallError`` when it stopped delivering, ``EndOfStream`` at the end."""

    def close(self) -> None:
        """Release the device; must not raise."""

    def settings(self) -> dict[str, str]:
        """The settings actually in effect (read back from the device), for diagnostics."""


def quiet_opencv() -> None:
    """Silence OpenCV's and FFmpeg's own warnings on stderr (a file or device it cannot open):
    the driver reports every failure itself, in one line and in its diagnostics.
    A user's ``OPENCV_LOG_LEVEL`` / ``OPENCV_FFMPEG_LOGLEVEL`` still wins (for debugging)."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; read when FFmpeg is first used
    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class CaptureSource:
    """Base of the sources that wrap one ``cv2.VideoCapture`` (``_cap``): releasing it and
    reporting the settings read back from it (``_settings``)."""

    _cap: Any = None

    def __init__(self) -> None:
        self._settings: dict[str, str] = {}

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def settings(self) -> dict[str, str]:
        return dict(self._settings)
