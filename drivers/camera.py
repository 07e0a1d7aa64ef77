"""The camera driver: frames from a V4L2 camera, a video file, an image folder or an MJPEG
stream, checked, stamped and published as ROS 2 image messages.

Topics (``NAME`` is the ``name`` option, default ``camera``):
  /NAME/image_raw/compressed  sensor_msgs/CompressedImage, format "jpeg": the camera's own JPEG
                              bytes unchanged (MJPG pass-through), or raw frames encoded at
                              ``jpeg_quality`` when ``raw_output = "jpeg"``
  /NAME/image_raw             sensor_msgs/Image (bgr8 or mono8) when ``raw_output`` asks for it
  /NAME/camera_info           sensor_msgs/CameraInfo, latched (calibration YAML or size only; a source
                              that does not give its size, such as MJPEG over HTTP, gets it from
                              its first frame, and the CameraInfo is published then)
  /tf_static                  parent_frame -> frame_id (config) -> optical_frame_id (REP 103)

Time: the message stamp is the capture time (V4L2 buffer timestamp or file media time, on
CLOCK_MONOTONIC; for an MJPEG stream its ``X-Timestamp`` mapped to the host clock, else its arrival)
moved to wall time by the offset ``time_ns() - monotonic_ns()`` taken when the connection opens;
MCAP log time is when the frame arrived. Diagnostics give the median and largest ``latency_ms``
(arrival minus capture) of the last 60 frames. Frames missing from the timing (gaps
over 1.5 periods) are counted as ``dropped``.

Faults: no frame for ``stall_timeout_s`` -> ``stalls`` and reconnect with back-off; a device
or file that disappears -> reconnect; a JPEG failing the marker check or the sampled decode ->
``corrupt``, never logged. The end of a file (without ``loop``) stops the driver and sets
``finished``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import os
import stat
import threading
import time
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trundle.drivers.camera_config import CameraConfig, parse_camera_url
from trundle.drivers.camera_info import load_camera_info, uncalibrated_camera_info
from trundle.drivers.frame_grabber import FrameGrabber
from trundle.drivers.frame_source import Frame, FrameSource, StallError
from trundle.drivers.jpeg_check import CorruptJpeg, JpegChecker, jpeg_header
from trundle.drivers.lifecycle import Driver, Sink, wall_ns
from trundle.drivers.mjpeg_stream import MjpegStreamSource
from trundle.drivers.v4l2_capture import V4L2Source, device_path
from trundle.drivers.video_file import JPEG_SUFFIXES, ImageFolderSource, VideoFileSource, folder_images, probe_video
from trundle.logs import messages as m
from trundle.logs.errors import ProtocolError, UserError
from trundle.logs.frames import rpy_transform
from trundle.logs.topics import TF_STATIC_TOPIC

# camera body (x forward, y left, z up) -> optical frame (x right, y down, z forward): rpy (-pi/2, 0, -pi/2)
OPTICAL_ROTATION = (-0.5, 0.5, -0.5, 0.5)
DROP_GAP = 1.5  # a gap longer than this many frame periods means frames were lost
log = logging.getLogger("trundle.camera")


def static_transforms(config: CameraConfig, stamp_ns: int) -> m.TFMessage:
    """parent_frame -> frame_id from ``config.transform`` and frame_id -> optical_frame_id."""
    x, y, z, roll, pitch, yaw = config.transform
    mount = rpy_transform(stamp_ns, config.parent_frame, config.frame_id, (x, y, z), (roll, pitch, yaw))
    optical = m.TransformStamped(stamp_ns, config.frame_id, config.optical_frame_id, np.zeros(3),
                                 np.array(OPTICAL_ROTATION))
    return m.TFMessage((mount, optical))


def count_dropped(previous_ns: int | None, t_ns: int, period_ns: float) -> int:
    """Frames missing between capture times ``previous_ns`` and ``t_ns`` at ``period_ns`` spacing."""
    if previous_ns is None or period_ns <= 0:
        return 0
    gap = t_ns - previous_ns
    return max(0, round(gap / period_ns) - 1) if gap > DROP_GAP * period_ns else 0


class CameraDriver(Driver):
    """Supervised capture from ``source_factory()`` (a new source per connection).

    Counters: ``frames`` published, ``corrupt`` JPEGs dropped, ``dropped`` frames missing from the
    timing, ``overwritten`` frames replaced by newer ones before we read them, ``stalls``.
    """

    usable = "frames"

    def __init__(self, config: CameraConfig, sink: Sink, source_factory: Callable[[], FrameSource], *,
                 camera_info: m.CameraInfo | None = None, clock: Callable[[], int] = wall_ns,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(config.name, sink, hardware_id=config.target, clock=clock)
        self.config = config
        self.source_factory = source_factory
        self.monotonic_ns = monotonic_ns
        self.counters.update(frames=0, corrupt=0, dropped=0, overwritten=0, stalls=0)
        self.finished = threading.Event()
        self.settings: dict[str, str] = {}
        self.last_corrupt = ""
        self.offset_ns = 0
        stamp = clock()
        self.camera_info = camera_info or uncalibrated_camera_info(config.width, config.height,
                                                                   config.optical_frame_id, stamp)
        self._info_topic = f"{config.topic_prefix}/camera_info"
        self._static: list[tuple[str, m.Message]] = [(TF_STATIC_TOPIC, static_transforms(config, stamp))]
        if self.camera_info.width:  # else the first frame tells the size (never a 0x0 CameraInfo)
            self._static.insert(0, (self._info_topic, self.camera_info))
        self._checker = JpegChecker(config.decode_check_every)
        self._grabber: FrameGrabber | None = None
        self._overwritten_before = 0
        self._period_ns = 0.0
        self._last_t_ns: int | None = None
        self._recent: collections.deque[int] = collections.deque(maxlen=61)
        self._latency: collections.deque[int] = collections.deque(maxlen=60)  # arrival - capture (ns)

    def static_messages(self) -> list[tuple[str, m.Message]]:
        return list(self._static)

    def open(self) -> None:
        source = self.source_factory()
        source.open()
        self.offset_ns = self.clock() - self.monotonic_ns()
        self.settings = source.settings()
        self._grabber = FrameGrabber(source).start()
        width, height = int(self.settings.get("width", 0)), int(self.settings.get("height", 0))
        self._checker.expected_size = (width, height) if width and height else None
        fps = float(self.settings.get("fps", 0)) or self.config.fps
        self._period_ns = 1e9 / fps if fps > 0 else 0.0
        self._last_t_ns = None
        self._recent.clear()
        self._latency.clear()
        log.info("%s: %s open, %s", self.name, source.description,
                 ", ".join(f"{k}={v}" for k, v in sorted(self.settings.items())))

    def read_once(self) -> None:
        grabber = self._grabber
        assert grabber is not None
        deadline = time.monotonic() + self.config.stall_timeout_s
        frame = None
        while frame is None and not self.stopping and grabber.alive:  # short waits: stop() is prompt
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            frame = grabber.get(min(remaining, 0.1))
        if frame is None:
            frame = grabber.get(0.0)
        self.counters["overwritten"] = self._overwritten_before + grabber.overwritten
        if frame is not None:
            self._handle(frame)
            return
        if self.stopping:
            return
        if grabber.ended:
            self.finished.set()
            self.finish()
            return
        error = grabber.error
        if error is None or isinstance(error, StallError):
            self.counters["stalls"] += 1
        if error is None:
            raise StallError(f"no frame for {self.config.stall_timeout_s:g} s")
        raise error  # a device fault reconnects; anything else is a bug and crashes the driver

    def _handle(self, frame: Frame) -> None:
        if self._last_t_ns is None and self._grabber is not None:  # first frame: the clock is known now
            self.settings = self._grabber.source.settings()
        self.counters["dropped"] += count_dropped(self._last_t_ns, frame.t_ns, self._period_ns)
        self._last_t_ns = frame.t_ns
        stamp_ns = frame.t_ns + self.offset_ns
        msg = self._message(frame, stamp_ns)
        if msg is None:
            self.counters["corrupt"] += 1
            return
        if not self.camera_info.width:
            self._learn_size(msg, frame.recv_ns + self.offset_ns)
        topic = "image_raw/compressed" if isinstance(msg, m.CompressedImage) else "image_raw"
        self.publish(f"{self.config.topic_prefix}/{topic}", msg, frame.recv_ns + self.offset_ns)
        self.counters["frames"] += 1
        self._recent.append(frame.t_ns)
        self._latency.append(frame.recv_ns - frame.t_ns)

    def _message(self, frame: Frame, stamp_ns: int) -> m.CompressedImage | m.Image | None:
        """The message for a frame, or None (reason in ``last_corrupt``) for a damaged one."""
        frame_id = self.config.optical_frame_id
        if frame.jpeg:
            problem = self._checker.check(frame.data)  # type: ignore[arg-type]
            if problem is not None:
                self.last_corrupt = problem
                return None
            return m.CompressedImage(stamp_ns, frame_id, "jpeg", frame.data)  # type: ignore[arg-type]
        image = frame.data
        assert isinstance(image, np.ndarray)
        if image.size == 0:
            self.last_corrupt = "the source could not decode the frame"
            return None
        return encode_raw(image, stamp_ns, frame_id, self.config.raw_output, self.config.jpeg_quality)

    def _learn_size(self, msg: m.CompressedImage | m.Image, log_ns: int) -> None:
        """The image size from the first good frame: the CameraInfo is made, latched and published."""
        width, height = jpeg_header(msg.data) if isinstance(msg, m.CompressedImage) else (msg.width, msg.height)
        self.camera_info = uncalibrated_camera_info(width, height, self.config.optical_frame_id, msg.stamp_ns)
        self._static.insert(0, (self._info_topic, self.camera_info))
        self.publish(self._info_topic, self.camera_info, log_ns)

    def close(self) -> None:
        grabber, self._grabber = self._grabber, None
        if grabber is not None:
            grabber.stop()
            self._overwritten_before += grabber.overwritten

    def silence_reason(self) -> str:
        if self.counters["corrupt"]:
            return f"{self.counters['corrupt']} corrupt frames dropped (last: {self.last_corrupt})"
        return "the camera sends no frames"

    def measured_fps(self) -> float:
        """Frame rate over the last (up to) 60 published frames, from their capture times."""
        recent = tuple(self._recent)  # one snapshot: the driver thread appends meanwhile
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) * 1e9 / (recent[-1] - recent[0])

    def diagnostics(self) -> m.DiagnosticStatus:
        """The driver's status plus settings in effect, measured rate and clock offset; WARN when
        the camera streams below 80 % of its set rate (USB bandwidth, exposure time, ...)."""
        status = super().diagnostics()
        measured = self.measured_fps()
        extra = [(f"setting.{k}", v) for k, v in sorted(self.settings.items())]
        extra += [("fps_measured", f"{measured:.2f}"), ("clock_offset_ns", str(self.offset_ns))]
        latency = np.array(tuple(self._latency), np.int64)  # one snapshot, as above
        if latency.size:
            extra += [("latency_ms", f"{np.median(latency) / 1e6:.1f}"),
                      ("latency_max_ms", f"{latency.max() / 1e6:.1f}")]
        if self.last_corrupt:
            extra.append(("last_corrupt", self.last_corrupt))
        status = dataclasses.replace(status, values=status.values + tuple(extra))
        wanted = 1e9 / self._period_ns if self._period_ns else 0.0
        if status.level == m.OK and len(self._recent) == self._recent.maxlen and 0 < measured < 0.8 * wanted:
            status = dataclasses.replace(status, level=m.WARN,
                                         message=f"{measured:.1f} fps, below the set {wanted:g} fps")
        return status


def encode_raw(image: np.ndarray, stamp_ns: int, frame_id: str, output: str = "jpeg",
               quality: int = 90) -> m.CompressedImage | m.Image:
    """A raw (BGR or mono) frame as a JPEG at ``quality`` (1-100) or a bgr8/mono8 Image; a frame the
    device sent that cannot be converted (odd shape or type) is a ``ProtocolError``."""
    try:
        if output == "jpeg":
            ok, buffer = cv2.imencode(".jpg", image, (cv2.IMWRITE_JPEG_QUALITY, int(quality)))
            if not ok:
                raise ProtocolError("JPEG encoding failed")
            return m.CompressedImage(stamp_ns, frame_id, "jpeg", buffer.tobytes())
        if output == "mono8" and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif output == "bgr8" and image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    except cv2.error as error:
        raise ProtocolError(f"cannot convert a {image.shape} frame: {error}") from None
    return m.Image.from_array(stamp_ns, frame_id, image, output)


def _file_size(path: Path) -> tuple[int, int]:
    """Image size (w, h) of a video file or the first image of a folder (0, 0 when unknown)."""
    if path.is_dir():
        images = folder_images(path)
        if not images:
            raise UserError(f"{path} holds no images ({', '.join(sorted(JPEG_SUFFIXES))}, .png, ...)")
        first = images[0]
        if first.suffix.lower() in JPEG_SUFFIXES:
            try:
                return jpeg_header(first.read_bytes())
            except CorruptJpeg:
                return 0, 0
        image = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
        return (0, 0) if image is None else (image.shape[1], image.shape[0])
    probe = probe_video(path)
    return probe.width, probe.height


def _source_factory(config: CameraConfig, unsupported: set[str]) -> tuple[Callable[[], FrameSource], tuple[int, int]]:
    """How to open the source of ``config`` (checked now: a bad path is a ``UserError``) and its size."""
    if config.scheme == "v4l2":  # a camera not plugged in yet is waited for (the source's open retries)
        path = device_path(config.target)
        if os.path.exists(path) and not stat.S_ISCHR(os.stat(path).st_mode):
            raise UserError(f"{path} is not a video device (for a video file use file://{os.path.abspath(path)})")
        factory = partial(V4L2Source, path, width=config.width, height=config.height, fps=config.fps,
                          fourcc=config.fourcc, buffers=config.buffers, controls=config.controls,
                          unsupported=unsupported, stale_timeout_s=config.stall_timeout_s)
        return factory, (config.width, config.height)
    if config.scheme == "file":
        file = Path(config.target).expanduser()
        if not file.exists():
            raise UserError(f"camera file not found: {file}")
        size = _file_size(file)
        kind = ImageFolderSource if file.is_dir() else VideoFileSource
        return partial(kind, file, fps=config.fps or None, pace=config.pace, loop=config.loop), size
    return partial(MjpegStreamSource, config.target, timeout_s=2 * config.stall_timeout_s), (
        config.width,
        config.height,
    )


def driver_from_url(url: str, sink: Sink, config: Mapping[str, Any] | None = None) -> CameraDriver:
    """A camera driver for ``url`` with the options of ``config`` (the ``[camera]`` table).

    ``v4l2:///dev/video0?width=1280&height=720&fps=30&fourcc=MJPG``, ``file:///path/clip.avi``,
    ``file:///path/folder/`` or ``http://host:port/stream.mjpg``; an unknown scheme, a bad path or
    a bad option raises ``UserError``.
    """
    cfg = parse_camera_url(url, config)
    unsupported: set[str] = set()
    factory, (width, height) = _source_factory(cfg, unsupported)
    if not cfg.width and width:
        cfg = cfg.model_copy(update={"width": width, "height": height})
    info = None
    if cfg.calibration:
        info = load_camera_info(cfg.calibration, cfg.optical_frame_id, wall_ns())
        if cfg.width and (info.width, info.height) != (cfg.width, cfg.height):
            raise UserError(f"calibration {cfg.calibration} is for {info.width}x{info.height} images, "
                            f"the camera gives {cfg.width}x{cfg.height}")
    return CameraDriver(cfg, sink, factory, camera_info=info)

