"""An emulated network camera: JPEG frames served as MJPEG over HTTP
(``multipart/x-mixed-replace``, the protocol of IP cameras and mjpg-streamer).

Frames come from ``frame_at(t_s) -> BGR image`` (the world simulator's renderer, or the
built-in ``synthetic_frame`` scene) encoded at ``quality``, or from a video file or image folder
(MJPEG packets and ``.jpg`` files are served byte for byte, other frames encoded). Frames are
produced at ``fps`` whether or not anyone watches, as a camera does; every client gets the
newest frame. Faults for tests: ``corrupt_next`` (truncated or damaged JPEG), ``stall``
(connection stays open, nothing is sent), ``unplug``/``replug`` (server and connections
closed, then back on the same port), ``send_delay`` (a frame held back before it is written, as
a busy camera or network delays it).

Each part says when its frame was captured, as mjpg-streamer's output_http plugin does:
``X-Timestamp: <sec>.<usec>`` (``"%d.%06d"`` of a ``struct timeval``), the time the frame was
taken, not the time it is sent. mjpg-streamer's input_uvc copies the V4L2 buffer's timestamp
(CLOCK_MONOTONIC of the camera's machine); its other inputs and many IP cameras use
``gettimeofday``. This emulator uses the wall clock (``time.time_ns()``), read just before the
frame is rendered at its fps tick; ``timestamps=False`` leaves the header out, as plainer
servers do.
"""

from __future__ import annotations

import collections
import contextlib
import socket
import threading
import time
from collections.abc import Callable
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np

from trundle.drivers.frame_source import FrameSource
from trundle.drivers.video_file import ImageFolderSource, VideoFileSource, probe_video
from trundle.logs.errors import DeviceError, UserError
from trundle.logs.paths import input_file

BOUNDARY = "trundleframe"
STREAM_PATH = "/stream.mjpg"


def synthetic_frame(t_s: float, width: int = 640, height: int = 480) -> np.ndarray:
    """A moving test scene at time ``t_s`` (s): a scrolling checkerboard, a disc going round and
    the time written in the corner; textured enough for feature detectors (BGR, uint8)."""
    cell = max(8, min(width, height) // 12)
    shift = int(40 * t_s)
    xs = (np.arange(width) + shift) // cell
    ys = np.arange(height) // cell
    board = ((xs[None, :] + ys[:, None]) & 1).astype(np.uint8)
    image = np.empty((height, width, 3), np.uint8)
    image[...] = (board * 170 + 40)[:, :, None]
    image[:, :, 0] += (np.arange(width, dtype=np.uint16) * 40 // max(width, 1)).astype(np.uint8)
    radius = min(width, height) // 4
    centre = (int(width / 2 + radius * np.cos(t_s)), int(height / 2 + radius * np.sin(t_s)))
    cv2.circle(image, centre, max(4, radius // 3), (30, 60, 220), -1)
    cv2.putText(image, f"t={t_s:8.3f}s", (8, max(16, height // 16)), cv2.FONT_HERSHEY_SIMPLEX,
                max(0.4, height / 960), (0, 255, 255), max(1, height // 480), cv2.LINE_AA)
    return image


def _corrupt(data: bytes, mode: str) -> bytes:
    """A damaged copy of a JPEG: ``truncate`` (first half only, as a short USB transfer) or
    ``marker`` (an invalid marker written into the image data)."""
    if mode == "truncate":
        return data[: len(data) // 2]
    damaged = bytearray(data)
    middle = len(damaged) * 3 // 4
    damaged[middle:middle + 2] = b"\xff\x02"
    return bytes(damaged)


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        emulator = self.server.emulator
        if self.path.split("?")[0] not in (STREAM_PATH, "/"):
            self.send_error(404, f"the stream is at {STREAM_PATH}")
            return
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache, no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        emulator._serve(self)

    def log_message(self, format: str, *args: object) -> None:
        pass


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    emulator: CameraEmulator


class CameraEmulator:
    """An MJPEG-over-HTTP camera at ``url``; ``start()`` it, ``close()`` it (or use ``with``).

    ``history`` > 0 keeps that many of the last frames served (bytes) for tests to compare.
    ``corrupt_every`` N damages every N-th frame (truncated), as a flaky USB link would.
    ``capture_ns`` holds the capture time (wall clock, ns) of each frame in ``history``.
    ``send_delay(n)`` (a test hook) gives the seconds to wait before writing frame ``n`` (counted
    from 1) to a client; ``timestamps`` False sends no ``X-Timestamp``.
    """

    def __init__(self, frame_at: Callable[[float], np.ndarray] | None = None, *, source: str | Path | None = None,
                 fps: float | None = None, width: int = 640, height: int = 480, quality: int = 85,
                 host: str = "127.0.0.1", port: int = 0, history: int = 0, corrupt_every: int = 0,
                 timestamps: bool = True, send_delay: Callable[[int], float] | None = None) -> None:
        self.width, self.height, self.quality = width, height, quality
        self.host, self.port = host, port
        self.corrupt_every = corrupt_every
        self.frames_made = 0
        self.corrupted = 0
        self.error: Exception | None = None
        self.history: collections.deque[bytes] = collections.deque(maxlen=history)
        self.capture_ns: collections.deque[int] = collections.deque(maxlen=history)
        self.timestamps = timestamps
        self.send_delay = send_delay
        self._file: FrameSource | None = None
        if source is not None:
            path = Path(source)
            if not path.exists():
                raise UserError(f"emulator source not found: {path}")
            if not path.is_dir():
                input_file(path, "video file or image folder")  # not a device that reads forever
            if path.is_dir():
                self._file = ImageFolderSource(path, fps=fps, pace=False, loop=True)
            else:
                fps = fps or probe_video(path).fps or 30.0
                self._file = VideoFileSource(path, pace=False, loop=True)
        self.fps = fps or 30.0
        self.frame_at = frame_at or (lambda t: synthetic_frame(t, self.width, self.height))
        self._cond = threading.Condition()
        self._latest: tuple[int, bytes, int] = (0, b"", 0)  # frame number, JPEG, capture time (wall ns)
        self._corrupt_pending: list[str] = []
        self._stall_until = 0.0
        self._stop = threading.Event()
        self._server: _Server | None = None
        self._server_thread: threading.Thread | None = None
        self._clients: set[socket.socket] = set()
        self._producer = threading.Thread(target=self._produce, name="camera-emulator", daemon=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}{STREAM_PATH}"

    def start(self) -> CameraEmulator:
        if self._file is not None:
            try:
                self._file.open()
            except DeviceError as error:
                raise UserError(f"emulator source: {error}") from None
        self.replug()
        self._producer.start()
        return self

    # --- frames ------------------------------------------------------------------------------

    def _next_jpeg(self, t_s: float) -> bytes:
        if self._file is None:
            image = self.frame_at(t_s)
        else:
            frame = self._file.read()
            assert frame is not None
            if frame.jpeg:
                return bytes(frame.data)
            image = frame.data  # type: ignore[assignment]
        ok, buffer = cv2.imencode(".jpg", image, (cv2.IMWRITE_JPEG_QUALITY, self.quality))
        if not ok:
            raise ValueError("JPEG encoding failed")
        return buffer.tobytes()

    def _produce(self) -> None:
        start = time.monotonic()
        index = 0
        while not self._stop.wait(max(0.0, start + index / self.fps - time.monotonic())):
            index = max(index, int((time.monotonic() - start) * self.fps))  # too slow: skip, as a camera drops
            t_s = index / self.fps
            index += 1
            if time.monotonic() < self._stall_until:
                continue
            captured_ns = time.time_ns()
            try:
                data = self._next_jpeg(t_s)
            except Exception as error:  # a failing renderer or file ends the stream, reported in .error
                self.error = error
                return
            with self._cond:
                mode = self._corrupt_pending.pop(0) if self._corrupt_pending else None
                if mode is None and self.corrupt_every and (self.frames_made + 1) % self.corrupt_every == 0:
                    mode = "truncate"
                if mode is not None:
                    data = _corrupt(data, mode)
                    self.corrupted += 1
                else:
                    self.history.append(data)
                    self.capture_ns.append(captured_ns)
                self.frames_made += 1
                self._latest = (self.frames_made, data, captured_ns)
                self._cond.notify_all()

    def _news_for(self, connection: socket.socket, seen: int) -> bool:
        """True once a frame newer than ``seen`` is out, the emulator stops or the client is dropped."""
        return self._latest[0] != seen or self._stop.is_set() or connection not in self._clients

    def _serve(self, handler: _Handler) -> None:
        """Send every new frame to one client until it leaves or the emulator is unplugged."""
        connection = handler.connection
        with self._cond:
            self._clients.add(connection)
            seen = self._latest[0]
        try:
            while not self._stop.is_set() and connection in self._clients:
                with self._cond:
                    self._cond.wait_for(partial(self._news_for, connection, seen), timeout=0.5)
                    if self._latest[0] == seen:
                        continue
                    seen, data, captured_ns = self._latest
                if self.send_delay is not None:
                    time.sleep(self.send_delay(seen))
                handler.wfile.write(self._part_head(data, captured_ns) + data + b"\r\n")
                handler.wfile.flush()
        except OSError:
            return
        finally:
            with self._cond:
                self._clients.discard(connection)

    def _part_head(self, data: bytes, captured_ns: int) -> bytes:
        """A part's delimiter and headers; ``X-Timestamp`` as mjpg-streamer writes it (``%d.%06d``)."""
        head = f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(data)}\r\n"
        if self.timestamps:
            head += f"X-Timestamp: {captured_ns // 1_000_000_000}.{captured_ns // 1000 % 1_000_000:06d}\r\n"
        return (head + "\r\n").encode()

    # --- faults --------------------------------------------------------------------------------

    def corrupt_next(self, count: int = 1, mode: str = "truncate") -> None:
        """Damage the next ``count`` frames: ``truncate`` or ``marker``."""
        if mode not in ("truncate", "marker"):
            raise ValueError(f"unknown corruption {mode!r}")
        with self._cond:
            self._corrupt_pending.extend([mode] * count)

    def stall(self, seconds: float) -> None:
        """Send nothing for ``seconds`` while keeping connections open."""
        self._stall_until = time.monotonic() + seconds

    def unplug(self) -> None:
        """Close the server and every connection, as pulling the camera's cable does."""
        server, self._server = self._server, None
        if server is None:
            return
        server.shutdown()
        server.server_close()
        with self._cond:
            clients, self._clients = list(self._clients), set()
            self._cond.notify_all()
        for connection in clients:
            with contextlib.suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)
        if self._server_thread is not None:
            self._server_thread.join(2.0)

    def replug(self) -> None:
        """Serve again on the same port."""
        if self._server is not None:
            return
        try:
            server = _Server((self.host, self.port), _Handler)
        except OSError as error:
            raise UserError(f"cannot listen on {self.host}:{self.port}: {error.strerror or error}") from None
        server.emulator = self
        self.port = server.server_address[1]
        self._server = server
        self._server_thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1},
                                               name="camera-emulator-http", daemon=True)
        self._server_thread.start()

    def close(self) -> None:
        self._stop.set()
        self.unplug()
        if self._producer.is_alive():
            self._producer.join(2.0)
        if self._file is not None:
            self._file.close()

    def __enter__(self) -> CameraEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
