"""An MJPEG-over-HTTP camera stream (``multipart/x-mixed-replace``: IP cameras, mjpg-streamer,
``trundle emulate camera``), read by OpenCV's FFmpeg backend in demux-only mode so each part's
JPEG bytes reach the log unchanged, as a V4L2 camera's MJPEG buffers do.

The stream carries no capture clock, so frames are stamped when they arrive. FFmpeg's own open
and read time-outs bound every call, so a silent server cannot hang the reader.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2

from trundle.drivers.frame_source import CaptureSource, Frame
from trundle.drivers.video_file import fourcc_text, open_ffmpeg, read_ffmpeg
from trundle.logs.errors import DeviceError


class MjpegStreamSource(CaptureSource):
    """Frames of an ``http://`` MJPEG stream; ``timeout_s`` bounds opening and each read."""

    live = True
    paced = False

    def __init__(self, url: str, *, timeout_s: float = 4.0,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.url = url
        self.timeout_s = timeout_s
        self.monotonic_ns = monotonic_ns
        self.description = url
        self._raw = False
        super().__init__()

    def open(self) -> None:
        ms = max(1, round(self.timeout_s * 1000))
        self._cap, self._raw = open_ffmpeg(self.url, (cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms,
                                                      cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms))
        self._settings = {"width": str(int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))),
                          "height": str(int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))),
                          "fourcc": fourcc_text(self._cap.get(cv2.CAP_PROP_FOURCC)),
                          "pass_through": str(self._raw).lower(), "timestamps": "arrival"}

    def read(self) -> Frame:
        assert self._cap is not None
        data = read_ffmpeg(self._cap, self._raw)
        if data is None:
            raise DeviceError(f"{self.url}: stream closed or silent for {self.timeout_s:g} s")
        now = self.monotonic_ns()
        return Frame(data, self._raw, now, now)
