"""Camera logging cost: MJPEG pass-through against decode + re-encode, and end-to-end rate.

Goal (issue 5): pass-through >= 10x cheaper in CPU per logged frame at 1280x720.
Process CPU time (every thread, the logger's included) per frame, best of 3 runs:
  driver_cpu_ms_*          the camera's work only: pass-through = marker check (1-in-30 decode)
                           + message + CDR; reencode = imdecode + imencode (q 90) + message + CDR
  logged_cpu_ms_*_<comp>   the same plus the MCAP logger with <comp> chunk compression; JPEG does
                           not compress, so zstd spends ~1 ms a frame for nothing (lz4: ~0.2 ms)
  *_reencode_over_pass_through   the ratios
End to end: a 1280x720 MJPEG AVI played unpaced through the driver into the logger
  e2e_fps_<comp>, e2e_over_demux (lz4 run / FFmpeg demuxing the same file alone) and
  e2e_lz4_over_30fps (headroom over one real-time 30 fps camera).
Run: python tools/bench/bench_camera.py [--frames N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from trundle.drivers.camera import driver_from_url
from trundle.drivers.jpeg_check import JpegChecker
from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.topics import IMAGE_TOPIC
from trundle.logs.writer import Logger
from trundle.tools.bench import report
from trundle.tools.emulators.camera_emulator import synthetic_frame

WIDTH, HEIGHT, QUALITY = 1280, 720, 90


def camera_frames(count: int) -> list[np.ndarray]:
    """A moving scene with sensor-like noise, so JPEG sizes resemble a real 720p camera's."""
    rng = np.random.default_rng(0)
    return [
        np.clip(synthetic_frame(i / 30, WIDTH, HEIGHT) + rng.normal(0, 4, (HEIGHT, WIDTH, 3)), 0, 255).astype(np.uint8)
        for i in range(count)
    ]


def cpu_per_frame(jpegs: list[bytes], to_message: Callable[[bytes, int], m.CompressedImage], folder: Path,
                  compression: str | None) -> float:
    """Best-of-3 process CPU seconds per frame: ``to_message`` + CDR, then the logger unless
    ``compression`` is None."""
    best = float("inf")
    for run in range(3):
        path = folder / f"cpu{run}.mcap"
        path.unlink(missing_ok=True)  # the bench's own scratch file (a logger never overwrites)
        logger = None if compression is None else Logger(path, compression=compression,
                                                          queue_size=len(jpegs) + 1, salvage=False)
        start = time.process_time()
        for i, data in enumerate(jpegs):
            msg = to_message(data, i)
            if logger is None:
                ros2.encode(msg)
            else:
                logger.write(IMAGE_TOPIC, msg, i)
        if logger is not None:
            logger.close()
        best = min(best, (time.process_time() - start) / len(jpegs))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=150)
    args = parser.parse_args()
    frames = camera_frames(args.frames)
    jpegs = [cv2.imencode(".jpg", f, (cv2.IMWRITE_JPEG_QUALITY, QUALITY))[1].tobytes() for f in frames]
    checker = JpegChecker(decode_every=30)

    def pass_through(data: bytes, stamp: int) -> m.CompressedImage:
        if checker.check(data) is not None:
            raise AssertionError("benchmark frame rejected")
        return m.CompressedImage(stamp, "camera_optical", "jpeg", data)

    def reencode(data: bytes, stamp: int) -> m.CompressedImage:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None, "benchmark frame does not decode"
        ok, buffer = cv2.imencode(".jpg", image, (cv2.IMWRITE_JPEG_QUALITY, QUALITY))
        return m.CompressedImage(stamp, "camera_optical", "jpeg", buffer.tobytes())

    figures: dict[str, float | int | str] = {"frame_size": f"{WIDTH}x{HEIGHT}",
                                              "mean_jpeg_kib": float(np.mean([len(j) for j in jpegs]) / 1024)}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for compression in (None, "zstd", "lz4"):
            prefix = "driver" if compression is None else "logged"
            suffix = "" if compression is None else f"_{compression}"
            passing = cpu_per_frame(jpegs, pass_through, folder, compression)
            reencoding = cpu_per_frame(jpegs, reencode, folder, compression)
            figures[f"{prefix}_cpu_ms_pass_through{suffix}"] = passing * 1e3
            figures[f"{prefix}_cpu_ms_reencode{suffix}"] = reencoding * 1e3
            figures[f"{prefix}_reencode_over_pass_through{suffix}"] = reencoding / passing

        clip = folder / "clip.avi"
        writer = cv2.VideoWriter(str(clip), cv2.VideoWriter.fourcc(*"MJPG"), 30, (WIDTH, HEIGHT))
        for frame in frames:
            writer.write(frame)
        writer.release()

        def demux() -> None:
            cap = cv2.VideoCapture(str(clip), cv2.CAP_FFMPEG)
            cap.set(cv2.CAP_PROP_FORMAT, -1)
            while cap.read()[0]:
                pass
            cap.release()

        def end_to_end(compression: str) -> None:
            (folder / "e2e.mcap").unlink(missing_ok=True)  # the bench's own scratch file (never overwritten)
            with Logger(folder / "e2e.mcap", compression=compression, salvage=False) as logger:
                driver = driver_from_url(f"file://{clip}?pace=0", logger, {})
                driver.start()
                driver.finished.wait(120)
                driver.stop()
            assert driver.counters["frames"] == len(frames), driver.counters
            assert logger.stats_dict()[IMAGE_TOPIC]["dropped"] == 0

        demux_fps = len(frames) / report.best_of(demux, repeat=3)
        figures["demux_fps"] = demux_fps
        e2e_fps = {c: len(frames) / report.best_of(partial(end_to_end, c), repeat=3) for c in ("zstd", "lz4")}
        figures.update({f"e2e_fps_{c}": fps for c, fps in e2e_fps.items()})
        figures["e2e_over_demux"] = e2e_fps["lz4"] / demux_fps
        figures["e2e_lz4_over_30fps"] = e2e_fps["lz4"] / 30.0  # real-time headroom
    report.write("camera", figures)


if __name__ == "__main__":
    main()
