"""Read a frame source on its own thread so the driver never blocks in a device call.

A live camera's frames are handed over newest-first: when the reader falls behind, older
frames are overwritten (counted), so a logged frame is never several buffers stale. A file's
frames are all handed over in order (the grabber waits for room). A paced source's frames are
held until their capture time. The grabber owns the source from ``start`` on and closes it
itself, even when ``stop`` had to leave it blocked in a read (a stalled device): nothing else
touches the capture object afterwards, so a stalled read can never race a release.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import replace

from trundle.drivers.frame_source import EndOfStream, Frame, FrameSource


class FrameGrabber:
    """Frames from ``source`` via ``get(timeout_s)``; ``error`` and ``ended`` tell why none came."""

    def __init__(self, source: FrameSource, *, depth: int | None = None,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.source = source
        self.depth = depth or (1 if source.live else 2)
        self.monotonic_ns = monotonic_ns
        self.error: BaseException | None = None
        self.ended = False
        self.overwritten = 0
        self._frames: collections.deque[Frame] = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._done = False
        self._thread = threading.Thread(target=self._run, name=f"grab-{source.description}", daemon=True)

    def start(self) -> FrameGrabber:
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                if frame is None:
                    continue
                if self.source.paced:
                    wait_ns = frame.t_ns - self.monotonic_ns()
                    if wait_ns > 0 and self._stop.wait(wait_ns * 1e-9):
                        break
                    frame = replace(frame, recv_ns=self.monotonic_ns())
                self._hand_over(frame)
        except EndOfStream:
            self.ended = True
        except Exception as error:  # any failure of the device call ends this connection
            self.error = error
        finally:
            self.source.close()
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def _hand_over(self, frame: Frame) -> None:
        with self._cond:
            if self.source.live:
                while len(self._frames) >= self.depth:
                    self._frames.popleft()
                    self.overwritten += 1
            else:
                while len(self._frames) >= self.depth and not self._stop.is_set():
                    self._cond.wait(0.1)
            self._frames.append(frame)
            self._cond.notify_all()

    def get(self, timeout_s: float) -> Frame | None:
        """The next frame, or None after ``timeout_s`` or once the source has failed or ended."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._frames and not self._done:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            if not self._frames:
                return None
            frame = self._frames.popleft()
            self._cond.notify_all()
            return frame

    def stop(self, timeout_s: float = 0.5) -> None:
        """Ask the thread to finish; wait at most ``timeout_s`` (a blocked read is left to end)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()
