"""Camera test helpers: clips written by OpenCV, an independent AVI reader, waiting on drivers."""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np


def scene(index: int, width: int = 320, height: int = 240) -> np.ndarray:
    """A distinct, textured BGR frame for ``index``."""
    rng = np.random.default_rng(index)
    image = cv2.resize(rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8), (width, height),
                       interpolation=cv2.INTER_NEAREST)
    cv2.putText(image, str(index), (width // 4, height * 2 // 3), cv2.FONT_HERSHEY_SIMPLEX, 3, (255, 255, 255), 5)
    return image


def write_clip(path: Path, count: int = 30, fps: float = 30.0, size: tuple[int, int] = (320, 240),
               fourcc: str = "MJPG") -> list[np.ndarray]:
    """Write ``count`` frames with cv2.VideoWriter; returns the frames written."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*fourcc), fps, size)
    assert writer.isOpened(), f"OpenCV cannot write {fourcc}"
    frames = [scene(i, *size) for i in range(count)]
    for frame in frames:
        writer.write(frame)
    writer.release()
    return frames


def avi_video_chunks(path: Path) -> list[tuple[int, bytes]]:
    """``(file offset, payload)`` of every video chunk (``##dc``/``##db``) in the AVI's ``movi``
    list, found by walking the RIFF tree (Microsoft AVI RIFF reference) - not via FFmpeg."""
    data = path.read_bytes()
    chunks: list[tuple[int, bytes]] = []

    def walk(offset: int, end: int, in_movi: bool) -> None:
        while offset + 8 <= end:
            fourcc, size = data[offset:offset + 4], struct.unpack("<I", data[offset + 4:offset + 8])[0]
            if fourcc in (b"RIFF", b"LIST"):
                walk(offset + 12, offset + 8 + size, in_movi or data[offset + 8:offset + 12] == b"movi")
            elif in_movi and fourcc[2:] in (b"dc", b"db"):
                chunks.append((offset + 8, data[offset + 8:offset + 8 + size]))
            offset += 8 + size + (size & 1)

    walk(0, len(data), False)
    return chunks


def wait_for(condition: Callable[[], bool], timeout_s: float = 15.0, what: str = "condition") -> None:
    """Poll ``condition`` until true; fail the test after ``timeout_s`` (a hang guard, not a timing check)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)
