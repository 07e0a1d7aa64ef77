"""V4L2 capture pieces testable without a camera (clock mapping, controls, refusal of
non-devices), the driver's timing logic, the grabber, and a hardware test when a camera exists."""

from __future__ import annotations

import logging
import os
import stat
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from camera_clips import wait_for, write_clip

from trundle.drivers.camera import CameraDriver, count_dropped, driver_from_url
from trundle.drivers.camera_config import parse_camera_url
from trundle.drivers.frame_grabber import FrameGrabber
from trundle.drivers.frame_source import Frame, StallError
from trundle.drivers.v4l2_capture import V4L2Source, apply_controls, device_path, frame_time_ns
from trundle.drivers.video_file import VideoFileSource
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError

S = 1_000_000_000


def test_monotonic_buffer_time_is_kept() -> None:
    # uvcvideo: buffer stamped 12 ms before the read returned, both on CLOCK_MONOTONIC
    assert frame_time_ns(5_000 * S - 12_000_000, 5_000 * S, 1_700_000_000 * S) == (5_000 * S - 12_000_000, "monotonic")


def test_realtime_buffer_time_is_moved_to_monotonic() -> None:
    wall, mono = 1_700_000_000 * S, 5_000 * S
    assert frame_time_ns(wall - 20_000_000, mono, wall) == (mono - 20_000_000, "realtime")


@pytest.mark.parametrize("buffer_ns", [0, 123 * S])
def test_missing_or_foreign_buffer_time_falls_back_to_arrival(buffer_ns: int) -> None:
    assert frame_time_ns(buffer_ns, 5_000 * S, 1_700_000_000 * S) == (5_000 * S, "none")


@pytest.mark.parametrize(
    "gap_ms, dropped", [(33.3, 0), (40.0, 0), (50.1, 1), (66.7, 1), (100.0, 2), (334.0, 9), (-5.0, 0)]
)
def test_drops_counted_from_timing_at_30_fps(gap_ms: float, dropped: int) -> None:
    assert count_dropped(10 * S, 10 * S + int(gap_ms * 1e6), 1e9 / 30) == dropped


def test_drop_count_needs_a_previous_frame_and_a_rate() -> None:
    assert count_dropped(None, 10 * S, 1e9 / 30) == 0
    assert count_dropped(10 * S, 11 * S, 0.0) == 0


def test_unsupported_controls_are_reported_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    clip = tmp_path / "clip.avi"
    write_clip(clip, count=2)
    cap = cv2.VideoCapture(str(clip), cv2.CAP_FFMPEG)  # a real capture object that refuses camera controls
    reported: set[str] = set()
    controls = {"exposure": 156.0, "gain": 10.0}
    with caplog.at_level(logging.WARNING, logger="trundle.camera"):
        first = apply_controls(cap, controls, reported)
        second = apply_controls(cap, controls, reported)  # a reconnect re-applies them
    cap.release()
    assert first == second == {"exposure": "unsupported", "gain": "unsupported"}
    assert [r.getMessage() for r in caplog.records] == [
        "camera control exposure=156 is not supported by this device; ignored",
        "camera control gain=10 is not supported by this device; ignored"]


def test_v4l2_refuses_a_regular_file(tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    write_clip(clip, count=2)
    with pytest.raises(DeviceError, match="cannot open as a V4L2 camera"):
        V4L2Source(str(clip)).open()
    with pytest.raises(DeviceError, match="no camera at .*video9 \\(unplugged"):
        V4L2Source(str(tmp_path / "video9")).open()


def test_device_index_and_by_id_paths() -> None:
    assert device_path("2") == "/dev/video2"
    assert device_path("/dev/v4l/by-id/usb-cam-video-index0") == "/dev/v4l/by-id/usb-cam-video-index0"


class ScriptedCamera:
    """A source replaying capture times (ms) from a script; ``"stall"`` raises StallError.
    ``live=False`` hands every frame over (no overwriting) so a test sees them all."""

    paced = False
    description = "scripted"

    def __init__(self, script: list, jpeg: bytes, live: bool = True) -> None:
        self.script, self.jpeg, self.live = list(script), jpeg, live
        self.closed = False

    def open(self) -> None:
        pass

    def read(self) -> Frame | None:
        if not self.script:
            time.sleep(0.01)
            return None
        item = self.script.pop(0)
        if item == "stall":
            raise StallError("scripted stall")
        t = int(item * 1e6)
        return Frame(self.jpeg, True, t, t)

    def close(self) -> None:
        self.closed = True

    def settings(self) -> dict[str, str]:
        return {"fps": "30", "width": "64", "height": "48"}


@pytest.fixture(scope="module")
def jpeg() -> bytes:
    return cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))[1].tobytes()


def scripted_driver(script: list, jpeg: bytes) -> tuple[CameraDriver, list]:
    logged: list = []
    config = parse_camera_url("v4l2:///dev/video0?stall_timeout_s=5")
    cameras = [ScriptedCamera(script, jpeg, live=False)]
    driver = CameraDriver(config, lambda topic, msg, t: logged.append((topic, msg, t)),
                          lambda: cameras.pop(0) if cameras else ScriptedCamera([], jpeg))
    return driver, logged


def test_driver_counts_drops_from_buffer_times(jpeg: bytes) -> None:
    # 30 fps with one frame missing after 66.7 ms and three after 166.7 ms
    script = [0.0, 33.3, 66.7, 133.3, 166.7, 300.0, 333.3]
    driver, logged = scripted_driver(script, jpeg)
    driver.start()
    wait_for(lambda: driver.counters["frames"] == 7, what="frames")
    driver.stop()
    assert driver.counters["dropped"] == 4
    stamps = [msg.stamp_ns - driver.offset_ns for topic, msg, _ in logged if topic.endswith("compressed")]
    assert stamps == [int(t * 1e6) for t in script]  # stamped with the buffer time, not the arrival


def test_source_stall_is_counted_and_reconnected(jpeg: bytes) -> None:
    driver, logged = scripted_driver([0.0, 33.3, "stall"], jpeg)
    driver.start()
    wait_for(lambda: driver.counters["reconnects"] == 1, what="reconnect after the stall")
    driver.stop()
    assert driver.counters["stalls"] == 1 and "scripted stall" in driver.last_error
    assert driver.counters["frames"] == 2


def test_grabber_keeps_only_the_newest_live_frame(jpeg: bytes) -> None:
    camera = ScriptedCamera([float(i) for i in range(10)], jpeg)
    grabber = FrameGrabber(camera).start()
    wait_for(lambda: grabber.overwritten == 9, what="frames read and overwritten")
    frame = grabber.get(1.0)
    grabber.stop()
    assert frame is not None and frame.t_ns == 9_000_000
    assert grabber.overwritten == 9
    wait_for(lambda: camera.closed, what="the grabber closing its source")


def test_grabber_hands_over_every_file_frame_in_order(tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    write_clip(clip, count=8)
    source = VideoFileSource(clip, pace=False)
    source.open()
    grabber = FrameGrabber(source).start()
    time.sleep(0.1)  # the reader is slow: a file source must wait, not overwrite
    frames = []
    while (frame := grabber.get(2.0)) is not None:
        frames.append(frame)
    grabber.stop()
    assert len(frames) == 8 and grabber.ended and grabber.overwritten == 0
    assert [f.t_ns for f in frames] == sorted(f.t_ns for f in frames)


def video_devices() -> list[str]:
    return sorted(str(p) for p in Path("/dev").glob("video*") if stat.S_ISCHR(os.stat(p).st_mode))


@pytest.mark.skipif(not video_devices(), reason="no V4L2 camera on this machine (hardware-in-the-loop test)")
def test_real_camera_mjpeg_pass_through() -> None:
    logged: list = []
    driver = driver_from_url(f"v4l2://{video_devices()[0]}?fourcc=MJPG&width=640&height=480&fps=30",
                             lambda topic, msg, t: logged.append((msg, t)), {})
    driver.start()
    try:
        wait_for(lambda: driver.counters["frames"] >= 30, timeout_s=20, what="camera frames")
    finally:
        driver.stop()
    assert driver.settings["pass_through"] == "true", "CONVERT_RGB=0 no longer yields raw MJPEG"
    assert driver.settings["clock"] == "monotonic"
    assert all(msg.data[:2] == b"\xff\xd8" for msg, _ in logged)
    assert all(msg.stamp_ns <= t for msg, t in logged)  # captured before it arrived


def test_stop_is_prompt_while_waiting_for_a_silent_camera(jpeg: bytes) -> None:
    config = parse_camera_url("v4l2:///dev/video0?stall_timeout_s=60")
    driver = CameraDriver(config, lambda *a: None, lambda: ScriptedCamera([], jpeg))
    driver.start()
    wait_for(lambda: driver.state == "streaming", what="streaming")
    driver.stop(timeout=2.0)  # bounded wait; a driver stuck for the stall timeout would still be alive
    assert not driver._thread.is_alive() and driver.counters["stalls"] == 0


def test_health_warns_when_the_camera_runs_below_its_set_rate(jpeg: bytes) -> None:
    script = [i * 1000 / 15 for i in range(70)]  # set to 30 fps, delivering 15
    driver, _ = scripted_driver(script, jpeg)
    driver.start()
    wait_for(lambda: driver.counters["frames"] == 70, what="frames")
    status = driver.diagnostics()
    driver.stop()
    values = dict(status.values)
    assert status.level == m.WARN and status.message == "15.0 fps, below the set 30 fps"
    assert values["fps_measured"] == "15.00" and values["setting.fps"] == "30"
    assert driver.counters["dropped"] == 69  # every gap is two periods: one frame missing each


def test_health_is_ok_at_the_set_rate(jpeg: bytes) -> None:
    driver, _ = scripted_driver([i * 1000 / 30 for i in range(70)], jpeg)
    driver.start()
    wait_for(lambda: driver.counters["frames"] == 70, what="frames")
    status = driver.diagnostics()
    driver.stop()
    assert status.level == m.OK and dict(status.values)["fps_measured"] == "30.00"


def test_opencv_v4l2_select_timeout_is_short_before_any_capture() -> None:
    # OpenCV reads it once, at the first V4L2 capture: importing the driver must have set it
    assert int(os.environ["OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT"]) <= 2
