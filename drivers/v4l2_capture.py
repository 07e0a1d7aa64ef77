"""A V4L2 camera through OpenCV's ``CAP_V4L2`` backend, with MJPEG pass-through.

Settings are applied in the order the backend needs (FOURCC, then width and height together,
fps, buffer count) and read back, because drivers silently round them. With MJPG and
``CAP_PROP_CONVERT_RGB = 0`` each read returns the camera's own JPEG (a 1 x bytesused array
copied out of the mmap buffer before it is re-queued), which is logged unchanged; other formats
(YUYV, ...) are converted to BGR by OpenCV. (``CAP_PROP_FORMAT = -1`` is an FFmpeg-backend
switch; on V4L2 ``CONVERT_RGB`` is what turns decoding off.)

Time: ``CAP_PROP_POS_MSEC`` is the V4L2 buffer timestamp, on CLOCK_MONOTONIC for uvcvideo
(start of exposure or first USB packet), so frames are stamped with it rather than with the
time ``read`` returned; a device that stamps with CLOCK_REALTIME, or not at all, is recognised.

Faults: OpenCV waits ``OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT`` seconds (default 10, read once per
process) for a frame; it is set to 2 s here, before any capture, unless the user set it.
After an unplug the backend may keep returning the last frame, so an unchanged buffer
timestamp for longer than ``stale_timeout_s`` or a vanished device node ends the connection.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Mapping

import cv2
import numpy as np

from trundle.drivers.frame_source import CaptureSource, Frame, StallError, quiet_opencv
from trundle.drivers.lifecycle import wall_ns
from trundle.drivers.video_file import JPEG_FOURCCS, fourcc_text
from trundle.logs.errors import DeviceError

os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", "2")

log = logging.getLogger("trundle.camera")

# control name in the config -> OpenCV property (V4L2 control) it sets
CONTROLS: dict[str, int] = {
    "exposure": cv2.CAP_PROP_EXPOSURE,              # V4L2_CID_EXPOSURE_ABSOLUTE (UVC: 100 us units)
    "auto_exposure": cv2.CAP_PROP_AUTO_EXPOSURE,    # V4L2_CID_EXPOSURE_AUTO (UVC menu: 1 manual, 3 auto)
    "gain": cv2.CAP_PROP_GAIN,
    "white_balance": cv2.CAP_PROP_WB_TEMPERATURE,   # kelvin
    "auto_white_balance": cv2.CAP_PROP_AUTO_WB,
    "focus": cv2.CAP_PROP_FOCUS,
    "autofocus": cv2.CAP_PROP_AUTOFOCUS,
    "brightness": cv2.CAP_PROP_BRIGHTNESS,
    "contrast": cv2.CAP_PROP_CONTRAST,
    "saturation": cv2.CAP_PROP_SATURATION,
    "hue": cv2.CAP_PROP_HUE,
    "sharpness": cv2.CAP_PROP_SHARPNESS,
    "gamma": cv2.CAP_PROP_GAMMA,
    "backlight": cv2.CAP_PROP_BACKLIGHT,
    "zoom": cv2.CAP_PROP_ZOOM,
}
CLOCK_TOLERANCE_NS = 10_000_000_000


def apply_controls(cap: cv2.VideoCapture, controls: Mapping[str, float], reported: set[str]) -> dict[str, str]:
    """Set each control and read it back: ``{name: value in effect, or "unsupported"}``.

    A control the device refuses is logged once per name across calls (``reported`` keeps the
    names already logged), so a reconnect does not repeat the warning.
    """
    effect: dict[str, str] = {}
    for name, value in controls.items():
        prop = CONTROLS[name]
        if cap.set(prop, float(value)):
            effect[name] = f"{cap.get(prop):g}"
        else:
            effect[name] = "unsupported"
            if name not in reported:
                reported.add(name)
                log.warning("camera control %s=%g is not supported by this device; ignored", name, value)
    return effect


def frame_time_ns(buffer_ns: int, mono_now_ns: int, wall_now_ns: int,
                  tolerance_ns: int = CLOCK_TOLERANCE_NS) -> tuple[int, str]:
    """The capture time on CLOCK_MONOTONIC of a buffer stamped ``buffer_ns``, and its clock.

    A buffer timestamp near ``mono_now_ns`` is monotonic (uvcvideo), one near ``wall_now_ns``
    is realtime (converted with the current offset); zero or anything else is unusable and the
    arrival time ``mono_now_ns`` is taken instead (clock "none").
    """
    if buffer_ns and abs(mono_now_ns - buffer_ns) < tolerance_ns:
        return buffer_ns, "monotonic"
    if buffer_ns and abs(wall_now_ns - buffer_ns) < tolerance_ns:
        return buffer_ns - (wall_now_ns - mono_now_ns), "realtime"
    return mono_now_ns, "none"


def device_path(device: str) -> str:
    """``/dev/videoN`` for a bare index ``N``; any path (``/dev/v4l/by-id/...``) as given."""
    return f"/dev/video{device}" if device.isdigit() else device


class V4L2Source(CaptureSource):
    """Frames from a V4L2 device: raw JPEG with ``fourcc="MJPG"``, else BGR converted by OpenCV.

    ``width``/``height``/``fps`` of 0 keep the device's current mode. ``controls`` maps names of
    ``CONTROLS`` to values; ``unsupported`` collects the names already reported.
    """

    live = True
    paced = False

    def __init__(self, device: str, *, width: int = 0, height: int = 0, fps: float = 0.0, fourcc: str = "MJPG",
                 buffers: int = 2, controls: Mapping[str, float] | None = None, unsupported: set[str] | None = None,
                 stale_timeout_s: float = 2.0, monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 wall_clock_ns: Callable[[], int] = wall_ns) -> None:
        self.path = device_path(device)
        self.description = self.path
        self.width, self.height, self.fps, self.fourcc, self.buffers = width, height, fps, fourcc, buffers
        self.controls = dict(controls or {})
        self.unsupported = unsupported if unsupported is not None else set()
        self.stale_timeout_ns = int(stale_timeout_s * 1e9)
        self.monotonic_ns = monotonic_ns
        self.wall_clock_ns = wall_clock_ns
        self.clock = ""
        self.repeated = 0
        super().__init__()
        self._raw = False
        self._last_buffer_ns = 0
        self._last_new_ns = 0

    def open(self) -> None:
        if not os.path.exists(self.path):
            raise DeviceError(f"no camera at {self.path} (unplugged? see ls /dev/v4l/by-id/)")
        quiet_opencv()
        try:
            cap = cv2.VideoCapture(self.path, cv2.CAP_V4L2)
        except cv2.error as error:
            raise DeviceError(f"{self.path}: {error}") from None
        if not cap.isOpened():
            cap.release()
            raise DeviceError(
                f"{self.path}: cannot open as a V4L2 camera (busy, no permission or not a capture device)"
            )
        try:
            self._configure(cap)
        except cv2.error as error:
            cap.release()
            raise DeviceError(f"{self.path}: {error}") from None
        self._cap = cap
        self._last_buffer_ns = 0
        self._last_new_ns = self.monotonic_ns()

    def _configure(self, cap: cv2.VideoCapture) -> None:
        if self.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc))
        if self.width and self.height:  # the size is applied once both are set
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.fps:
            cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, self.buffers)
        fourcc = fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        self._raw = fourcc in JPEG_FOURCCS and bool(cap.set(cv2.CAP_PROP_CONVERT_RGB, 0))
        self._settings = {
            "device": os.path.realpath(self.path),
            "fourcc": fourcc,
            "width": str(int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))),
            "height": str(int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))),
            "fps": f"{cap.get(cv2.CAP_PROP_FPS):g}",
            "buffers": str(int(cap.get(cv2.CAP_PROP_BUFFERSIZE))),
            "pass_through": str(self._raw).lower(),
        }
        if self.fourcc and fourcc != self.fourcc:
            log.warning("%s: asked for %s, the device delivers %s", self.path, self.fourcc, fourcc or "?")
        for name, value in apply_controls(cap, self.controls, self.unsupported).items():
            self._settings[f"control.{name}"] = value

    def read(self) -> Frame | None:
        assert self._cap is not None
        if not os.path.exists(self.path):
            raise DeviceError(f"{self.path} disappeared (unplugged)")
        try:
            ok, image = self._cap.read()
        except cv2.error as error:
            raise DeviceError(f"{self.path}: {error}") from None
        mono_now = self.monotonic_ns()
        if not ok or image is None:
            raise StallError(f"{self.path}: no frame (select timeout or device error)")
        buffer_ns = round(self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1e6)
        if buffer_ns and buffer_ns == self._last_buffer_ns:
            self.repeated += 1
            if mono_now - self._last_new_ns > self.stale_timeout_ns:
                raise StallError(f"{self.path}: the camera keeps returning the same frame")
            return None
        self._last_buffer_ns, self._last_new_ns = buffer_ns, mono_now
        t_ns, self.clock = frame_time_ns(buffer_ns, mono_now, self.wall_clock_ns())
        return Frame(*self._payload(image), t_ns, mono_now)

    @staticmethod
    def _payload(image: np.ndarray) -> tuple[bytes | np.ndarray, bool]:
        """The JPEG bytes of a raw MJPEG buffer (1 x bytesused), or a converted image as it is."""
        if image.ndim == 2 and image.shape[0] == 1:
            return image.tobytes(), True
        return image, False

    def settings(self) -> dict[str, str]:
        values = super().settings()
        if self.clock:
            values["clock"] = self.clock
        return values
