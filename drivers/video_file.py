"""File frame sources: a video file or a folder of images, paced like a camera.

An MJPEG video (AVI, MOV, MKV) is demuxed by OpenCV's FFmpeg backend with
``CAP_PROP_FORMAT = -1``: each read returns the container's packet, the JPEG bytes exactly as
stored, so these frames take the same pass-through path as a V4L2 camera's MJPEG buffers. Any
other video is decoded to BGR. A folder's ``*.jpg``/``*.jpeg`` files are passed through as
bytes; other images are decoded. Frames carry ``t_ns = t0 + media time`` on CLOCK_MONOTONIC,
where the media time comes from the container (or frame index / ``fps`` when ``fps`` is set,
and always for folders); with ``pace`` they are handed over at that time.

At the end of the file the source raises ``EndOfStream``, or with ``loop`` reopens the file
from its path and continues (media time keeps running). A file or folder that disappears
while streaming is a lost device (``DeviceError``), as an unplugged camera is.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from trundle.drivers.frame_source import CaptureSource, EndOfStream, Frame, quiet_opencv
from trundle.logs.errors import DeviceError, UserError

JPEG_FOURCCS = frozenset({"MJPG", "mjpg", "MJPA", "mjpa", "jpeg", "JPEG", "AVRn", "dmb1"})
JPEG_SUFFIXES = frozenset({".jpg", ".jpeg"})
IMAGE_SUFFIXES = JPEG_SUFFIXES | {".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
FOLDER_FPS = 10.0


def fourcc_text(value: float) -> str:
    """The four characters of an OpenCV FOURCC property value ("" when unset)."""
    code = int(value)
    text = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return text if code and text.isprintable() else ""


def open_ffmpeg(target: str) -> tuple[cv2.VideoCapture, bool]:
    """Open the video file ``target`` with the FFmpeg backend; ``(capture, raw_jpeg)``.

    ``raw_jpeg`` is True when the stream is MJPEG and demux-only mode is on, so reads return
    the JPEG packets undecoded. Raises ``DeviceError`` when FFmpeg cannot open it.
    """
    quiet_opencv()
    try:
        cap = cv2.VideoCapture(target, cv2.CAP_FFMPEG)
    except cv2.error as error:
        raise DeviceError(f"cannot open {target}: {error}") from None
    if not cap.isOpened():
        cap.release()
        raise DeviceError(f"cannot open {target} (missing, unreadable or not a video)")
    raw = fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)) in JPEG_FOURCCS and cap.set(cv2.CAP_PROP_FORMAT, -1)
    return cap, bool(raw)


def read_ffmpeg(cap: cv2.VideoCapture, raw: bool) -> bytes | np.ndarray | None:
    """The next packet's JPEG bytes (``raw``) or decoded BGR image; None at the end of the stream."""
    try:
        ok, data = cap.read()
    except cv2.error as error:
        raise DeviceError(f"read failed: {error}") from None
    if not ok or data is None:
        return None
    return data.tobytes() if raw else data


@dataclass(frozen=True)
class VideoProbe:
    """What a video file holds: size (px), frame rate (Hz), frame count and whether it is MJPEG."""

    width: int
    height: int
    fps: float
    frames: int
    jpeg: bool


def probe_video(path: Path) -> VideoProbe:
    """Size, rate and codec of a video file; a file FFmpeg cannot open is a ``UserError``."""
    try:
        cap, raw = open_ffmpeg(str(path))
    except DeviceError:
        raise UserError(f"{path} is not a video file OpenCV/FFmpeg can read") from None
    try:
        return VideoProbe(int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                          float(cap.get(cv2.CAP_PROP_FPS)), int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), raw)
    finally:
        cap.release()


def folder_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` in name order."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


class _PacedFile:
    """Media-time bookkeeping shared by the file sources."""

    live = False

    def __init__(self, path: Path, *, fps: float | None, pace: bool, loop: bool,
                 monotonic_ns: Callable[[], int]) -> None:
        self.path = Path(path)
        self.fps = fps
        self.paced = pace
        self.loop = loop
        self.monotonic_ns = monotonic_ns
        self.description = str(self.path)
        self._t0_ns = 0
        self._index = 0
        self._last_media_ns = 0

    def _start(self) -> None:
        self._t0_ns = self.monotonic_ns()
        self._index = 0
        self._last_media_ns = 0

    def _restart(self, period_ns: int) -> None:
        """Continue after the last frame as if the file went on: next media time one period later."""
        self._t0_ns += self._last_media_ns + period_ns
        self._index = 0
        self._last_media_ns = 0

    def _frame(self, data: bytes | np.ndarray, jpeg: bool, media_ns: int) -> Frame:
        self._last_media_ns = media_ns
        self._index += 1
        return Frame(data, jpeg, self._t0_ns + media_ns, self.monotonic_ns())

    def _check_present(self) -> None:
        if not self.path.exists():
            raise DeviceError(f"{self.path} disappeared")


class VideoFileSource(CaptureSource, _PacedFile):
    """Frames of a video file: MJPEG packets as stored, other codecs decoded to BGR."""

    def __init__(self, path: Path, *, fps: float | None = None, pace: bool = True, loop: bool = False,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        _PacedFile.__init__(self, path, fps=fps, pace=pace, loop=loop, monotonic_ns=monotonic_ns)
        CaptureSource.__init__(self)
        self._raw = False

    def open(self) -> None:
        self._open_capture()
        self._start()

    def _open_capture(self) -> None:
        self._check_present()
        self._cap, self._raw = open_ffmpeg(str(self.path))
        cap = self._cap
        native_fps = cap.get(cv2.CAP_PROP_FPS)
        self._settings = {
            "width": str(int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))),
            "height": str(int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))),
            "fps": f"{self.fps or native_fps:g}",
            "file_fps": f"{native_fps:g}",
            "fourcc": fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
            "pass_through": str(self._raw).lower(),
            "frames": str(int(cap.get(cv2.CAP_PROP_FRAME_COUNT))),
        }

    def read(self) -> Frame:
        self._check_present()
        assert self._cap is not None
        data = read_ffmpeg(self._cap, self._raw)
        if data is None:
            if not self.loop:
                raise EndOfStream(str(self.path))
            fps = self.fps or float(self._settings["file_fps"]) or 30.0
            self._cap.release()
            self._open_capture()
            self._restart(round(1e9 / fps))
            data = read_ffmpeg(self._cap, self._raw)
            if data is None:
                raise DeviceError(f"{self.path} has no frames")
        if self.fps:
            media_ns = round(self._index * 1e9 / self.fps)
        else:
            media_ns = round(self._cap.get(cv2.CAP_PROP_POS_MSEC) * 1e6)
        return self._frame(data, self._raw, media_ns)


class ImageFolderSource(_PacedFile):
    """Frames from the image files of a folder in name order, at ``fps`` (default 10 Hz)."""

    def __init__(self, path: Path, *, fps: float | None = None, pace: bool = True, loop: bool = False,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(path, fps=fps or FOLDER_FPS, pace=pace, loop=loop, monotonic_ns=monotonic_ns)
        self._files: list[Path] = []

    def open(self) -> None:
        self._check_present()
        self._files = folder_images(self.path)
        if not self._files:
            raise DeviceError(f"{self.path} holds no images")
        self._start()

    def read(self) -> Frame:
        assert self.fps is not None
        if self._index >= len(self._files):
            if not self.loop:
                raise EndOfStream(str(self.path))
            self._next_round()
        path = self._files[self._index]
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise DeviceError(f"{path} disappeared") from None
        media_ns = round(self._index * 1e9 / self.fps)
        if path.suffix.lower() in JPEG_SUFFIXES:
            return self._frame(data, True, media_ns)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return self._frame(np.zeros((0, 0, 3), np.uint8) if image is None else image, False, media_ns)

    def _next_round(self) -> None:
        """Start the folder again (re-listing it) after its last image."""
        assert self.fps is not None
        self._check_present()
        self._files = folder_images(self.path)
        if not self._files:
            raise DeviceError(f"{self.path} holds no images")
        self._restart(round(1e9 / self.fps))

    def close(self) -> None:
        self._files = []

    def settings(self) -> dict[str, str]:
        return {"fps": f"{self.fps:g}", "images": str(len(self._files)), "pass_through": "jpeg files"}
