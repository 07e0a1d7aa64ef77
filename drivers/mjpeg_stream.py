"""An MJPEG-over-HTTP camera stream (``multipart/x-mixed-replace``: IP cameras, mjpg-streamer,
``trundle emulate camera``): the transport. One GET, then the response body is fed to the codec
(``mjpeg_parts``) as it arrives; each part's JPEG bytes reach the log unchanged, as a V4L2
camera's MJPEG buffers do.

Time: a part with ``X-Timestamp: <sec>.<usec>`` (mjpg-streamer sends the V4L2 buffer's capture
time) is stamped at its capture: the camera's clock (epoch or monotonic seconds of its own
machine) is mapped to the host's CLOCK_MONOTONIC by a ``SensorClock`` in envelope mode (the
offset from the quickest deliveries, drift from the lower envelope of latency), so HTTP, network
and scheduling delays do not move the stamps. A part without it is stamped when it arrives.
``settings()["timestamps"]`` says which (``capture`` or ``arrival``).

Every socket call is bounded by ``timeout_s`` and so is the wait for each whole part, so a silent
or trickling server cannot hang the reader. A part cut off by the end of the connection is handed
over as it is (the driver's JPEG check counts and drops it); the end itself is a lost device.
"""

from __future__ import annotations

import http.client
import time
import urllib.parse
from collections import deque
from collections.abc import Callable

from trundle.drivers.frame_source import Frame
from trundle.drivers.jpeg_check import CorruptJpeg, jpeg_header
from trundle.drivers.mjpeg_parts import MultipartParser, Part, x_timestamp_ns
from trundle.drivers.sensor_clock import SensorClock
from trundle.logs.errors import DeviceError

CHUNK = 64 * 1024  # bytes asked of the socket per read


def capture_clock() -> SensorClock:
    """The clock mapping of a stream's ``X-Timestamp`` (nanoseconds, never wrapping) to host time:
    envelope mode, re-anchored after 5 s of latency off its median; drift from the lowest latency
    of each second, fitted only once 5 minutes of them are in: on a busy host that floor moves by
    tens of ms within a minute (the demo: 15 ms over its first 30 s, on one machine, no drift at
    all), which a shorter fit takes for drift and turns into a growing error."""
    return SensorClock(bits=64, tick_ns=1, bin_ticks=1_000_000_000, resync_after_ticks=5_000_000_000,
                       min_drift_bins=300, envelope=True)


class MjpegStreamSource:
    """Frames of an ``http://`` or ``https://`` MJPEG stream; ``timeout_s`` bounds opening and each part."""

    live = True
    paced = False

    def __init__(self, url: str, *, timeout_s: float = 4.0,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.url = url
        self.timeout_s = timeout_s
        self.monotonic_ns = monotonic_ns
        self.description = url
        self.clock = capture_clock()
        self._connection: http.client.HTTPConnection | None = None
        self._response: http.client.HTTPResponse | None = None
        self._parser: MultipartParser | None = None
        self._parts: deque[tuple[Part, int]] = deque()
        self._ended = False
        self._settings: dict[str, str] = {}

    def open(self) -> None:
        parts = urllib.parse.urlsplit(self.url)
        kind = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
        try:
            self._connection = kind(parts.hostname or "", parts.port, timeout=self.timeout_s)
            self._connection.request("GET", urllib.parse.urlunsplit(("", "", parts.path or "/", parts.query, "")),
                                     headers={"Accept": "multipart/x-mixed-replace"})
            self._response = response = self._connection.getresponse()
        except (OSError, http.client.HTTPException, ValueError) as error:
            self.close()
            raise DeviceError(f"cannot open {self.url}: {error or type(error).__name__}") from None
        boundary = response.headers.get_param("boundary")
        if response.status != 200 or response.headers.get_content_type() != "multipart/x-mixed-replace" \
                or not isinstance(boundary, str) or not boundary:
            self.close()
            what = f"HTTP {response.status} {response.reason}" if response.status != 200 else \
                f"Content-Type {response.headers.get('Content-Type')!r}"
            raise DeviceError(f"{self.url} is not an MJPEG stream ({what})")
        self._parser = MultipartParser(boundary)
        self._settings = {"fourcc": "MJPG", "pass_through": "true", "timestamps": "arrival"}

    def read(self) -> Frame:
        """The next part as a frame; ``DeviceError`` when the stream ended or sent no whole part in time."""
        deadline = time.monotonic() + self.timeout_s
        while not self._parts:
            if self._ended:
                raise DeviceError(f"{self.url}: the stream ended")
            self._receive(deadline)
        part, recv_ns = self._parts.popleft()
        return self._frame(part, recv_ns)

    def _receive(self, deadline: float) -> None:
        """One read from the socket into the codec; the parts it completed are queued with their arrival time."""
        assert self._response is not None and self._parser is not None and self._connection is not None
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceError(f"{self.url}: no whole frame for {self.timeout_s:g} s")
        try:
            if self._connection.sock is not None:
                self._connection.sock.settimeout(remaining)
            data = self._response.read1(CHUNK)
        except TimeoutError:
            raise DeviceError(f"{self.url}: stream silent for {self.timeout_s:g} s") from None
        except (OSError, http.client.HTTPException) as error:
            raise DeviceError(f"{self.url}: {error or type(error).__name__}") from None
        now = self.monotonic_ns()
        if data:
            self._parts.extend((part, now) for part in self._parser.feed(data))
            return
        self._ended = True
        cut = self._parser.finish()
        if cut is not None:
            self._parts.append((cut, now))

    def _frame(self, part: Part, recv_ns: int) -> Frame:
        """The part's body, stamped at its capture when it says the time, else at ``recv_ns``."""
        device_ns = x_timestamp_ns(part.headers.get("x-timestamp", ""))
        if device_ns is None:
            self._settings["timestamps"] = "arrival"
            t_ns = recv_ns
        else:
            self._settings["timestamps"] = "capture"
            t_ns = self.clock.update(device_ns, recv_ns).stamp_ns
        if "width" not in self._settings:
            try:
                width, height = jpeg_header(part.body)
            except CorruptJpeg:
                pass
            else:
                self._settings.update(width=str(width), height=str(height))
        return Frame(part.body, True, t_ns, recv_ns)

    def close(self) -> None:
        if self._response is not None:
            self._response.close()
        if self._connection is not None:
            self._connection.close()
        self._connection = self._response = None

    def settings(self) -> dict[str, str]:
        return dict(self._settings)
