"""Camera driver on file sources, end to end into an MCAP log: MJPEG pass-through byte for byte,
capture-time stamps, corrupt frames, a vanishing source, raw-frame outputs, static messages."""

from __future__ import annotations

import math
import shutil
import tempfile
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
import pytest
from camera_clips import avi_video_chunks, scene, wait_for, write_clip
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from trundle.drivers.camera import CameraDriver, driver_from_url
from trundle.drivers.jpeg_check import jpeg_problem
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError, UserError
from trundle.logs.reader import LogMessage, LogReader
from trundle.logs.writer import Logger
from trundle.tools.cli.main import main

IMAGE_TOPIC = "/camera/image_raw/compressed"


def record(url: str, out: Path, config: dict | None = None) -> tuple[CameraDriver, list[LogMessage]]:
    """Run a file-source driver to the end of its file into ``out``; the driver and the log."""
    with Logger(out, salvage=False) as logger:
        driver = driver_from_url(url, logger, config or {})
        for topic, msg in driver.static_messages():
            logger.write(topic, msg)
        driver.start()
        assert driver.finished.wait(30), driver.last_error
        driver.stop()
    with LogReader(out) as reader:
        return driver, list(reader.messages())


def images(log: list[LogMessage], topic: str = IMAGE_TOPIC) -> list:
    return [entry.msg for entry in log if entry.topic == topic]


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("clip") / "clip.avi"
    write_clip(path, count=30, fps=30.0)
    return path


def test_ffmpeg_demux_returns_packets_as_one_row(clip: Path) -> None:
    # the shape the pass-through path relies on (OpenCV behaviour has changed before)
    cap = cv2.VideoCapture(str(clip), cv2.CAP_FFMPEG)
    assert cap.set(cv2.CAP_PROP_FORMAT, -1)
    ok, packet = cap.read()
    cap.release()
    assert ok and packet.ndim == 2 and packet.shape[0] == 1 and packet.dtype == np.uint8


def test_mjpeg_clip_is_logged_byte_for_byte(clip: Path, tmp_path: Path) -> None:
    driver, log = record(f"file://{clip}?pace=0", tmp_path / "run.mcap")
    logged = images(log)
    assert [msg.data for msg in logged] == [payload for _, payload in avi_video_chunks(clip)]
    assert {(msg.format, msg.frame_id) for msg in logged} == {("jpeg", "camera_optical")}
    assert (driver.counters["frames"], driver.counters["corrupt"], driver.counters["dropped"]) == (30, 0, 0)
    assert driver.settings["pass_through"] == "true"


@pytest.mark.parametrize("fps", [30.0, 25.0])
def test_stamps_are_monotonic_and_spaced_at_the_clip_rate(tmp_path: Path, fps: float) -> None:
    path = tmp_path / "clip.avi"
    write_clip(path, count=12, fps=fps)
    driver, log = record(f"file://{path}?pace=0", tmp_path / "run.mcap")
    stamps = np.array([msg.stamp_ns for msg in images(log)])
    steps = np.diff(stamps)
    assert len(stamps) == 12 and (steps > 0).all()
    assert np.abs(steps - 1e9 / fps).max() <= 1.0  # media time, rounded to whole nanoseconds
    assert abs(stamps[0] - log[0].log_time_ns) < 60e9  # host wall-clock time, not CLOCK_MONOTONIC
    assert driver.counters["dropped"] == 0


def test_paced_frames_arrive_no_earlier_than_their_capture_time(clip: Path, tmp_path: Path) -> None:
    _, log = record(f"file://{clip}?fps=100", tmp_path / "run.mcap")
    entries = [entry for entry in log if entry.topic == IMAGE_TOPIC]
    stamps = np.array([entry.msg.stamp_ns for entry in entries])
    assert np.abs(np.diff(stamps) - 10_000_000).max() <= 1  # the set rate overrides the recorded one
    assert all(entry.log_time_ns >= entry.msg.stamp_ns for entry in entries)


def corrupt_copy(clip: Path, target: Path) -> tuple[list[bytes], list[int]]:
    """Copy ``clip`` damaging four frames in place the ways a USB camera does; the good payloads
    (from the independent AVI walk) and the damaged indexes."""
    data = bytearray(clip.read_bytes())
    chunks = avi_video_chunks(clip)
    damage = {
        3: lambda o, n: data.__setitem__(slice(o + n - 2, o + n), b"\0\0"),                  # EOI lost
        7: lambda o, n: data.__setitem__(slice(o, o + 2), b"\0\0"),                          # SOI lost
        12: lambda o, n: data.__setitem__(slice(o + n // 2, o + n // 2 + 2), b"\xff\x01"),   # bad marker in scan
        20: lambda o, n: data.__setitem__(slice(o + n // 2, o + n), bytes(n - n // 2)),      # zero-filled tail
    }
    for index, hurt in damage.items():
        offset, payload = chunks[index]
        hurt(offset, len(payload))
    target.write_bytes(bytes(data))
    good = [payload for i, (_, payload) in enumerate(chunks) if i not in damage]
    return good, sorted(damage)


def test_corrupt_frames_are_counted_and_never_logged(clip: Path, tmp_path: Path) -> None:
    damaged = tmp_path / "damaged.avi"
    good, bad = corrupt_copy(clip, damaged)
    driver, log = record(f"file://{damaged}?pace=0", tmp_path / "run.mcap")
    assert [msg.data for msg in images(log)] == good
    assert (driver.counters["frames"], driver.counters["corrupt"]) == (len(good), len(bad))
    assert driver.counters["dropped"] == 0  # a damaged frame still arrived: not a drop
    assert driver.last_corrupt


def test_source_removed_and_restored_reconnects(clip: Path, tmp_path: Path) -> None:
    path = tmp_path / "live.avi"
    shutil.copy(clip, path)
    logged: list[m.CompressedImage] = []
    driver = driver_from_url(f"file://{path}?fps=60&loop=1", lambda topic, msg, t: logged.append(msg), {})
    driver.start()
    try:
        wait_for(lambda: driver.counters["frames"] >= 5, what="first frames")
        path.rename(tmp_path / "away.avi")  # the device node disappears
        wait_for(lambda: driver.counters["errors"] >= 2, what="failed reopen attempts")
        frames_while_gone = driver.counters["frames"]
        assert driver.counters["reconnects"] == 0 and driver.state in ("waiting", "connecting")
        (tmp_path / "away.avi").rename(path)
        wait_for(lambda: driver.counters["reconnects"] == 1 and driver.counters["frames"] >= frames_while_gone + 5,
                 what="frames after the reconnect")
    finally:
        driver.stop()
    assert not driver._thread.is_alive()
    good = {payload for _, payload in avi_video_chunks(clip)}
    assert all(msg.data in good for msg in logged)
    stamps = [msg.stamp_ns for msg in logged]
    assert all(b > a for a, b in pairwise(stamps))
    assert "disappeared" in driver.last_error or "cannot open" in driver.last_error


@pytest.fixture(scope="module")
def lossless(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[np.ndarray]]:
    path = tmp_path_factory.mktemp("ffv1") / "clip.avi"
    return path, write_clip(path, count=5, fps=10.0, size=(160, 120), fourcc="FFV1")


def test_decoded_video_as_bgr8_image(lossless, tmp_path: Path) -> None:
    path, frames = lossless
    driver, log = record(f"file://{path}?pace=0&raw_output=bgr8", tmp_path / "run.mcap")
    logged = images(log, "/camera/image_raw")
    assert [msg.encoding for msg in logged] == ["bgr8"] * 5
    for msg, frame in zip(logged, frames, strict=True):
        np.testing.assert_array_equal(msg.to_array(), frame)
    assert driver.settings["pass_through"] == "false"


def test_decoded_video_as_mono8_image(lossless, tmp_path: Path) -> None:
    path, frames = lossless
    _, log = record(f"file://{path}?pace=0&raw_output=mono8", tmp_path / "run.mcap")
    for msg, frame in zip(images(log, "/camera/image_raw"), frames, strict=True):
        assert msg.encoding == "mono8"
        np.testing.assert_array_equal(msg.to_array(), cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))


def luminance_dqt(data: bytes) -> np.ndarray:
    """The 64 entries of quantisation table 0 (8-bit) from the DQT segment."""
    pos = data.index(b"\xff\xdb")
    assert data[pos + 4] == 0x00  # precision 8 bit, table 0
    return np.frombuffer(data[pos + 5:pos + 69], np.uint8)


@pytest.mark.parametrize("quality", [60, 95])
def test_decoded_video_as_jpeg_at_the_set_quality(lossless, tmp_path: Path, quality: int) -> None:
    path, frames = lossless
    _, log = record(f"file://{path}?pace=0&jpeg_quality={quality}", tmp_path / "run.mcap")
    logged = images(log)
    for msg, frame in zip(logged, frames, strict=True):
        assert msg.data == cv2.imencode(".jpg", frame, (cv2.IMWRITE_JPEG_QUALITY, quality))[1].tobytes()
    # IJG scaling of the standard luminance table (ITU-T T.81 K.1, first entry 16):
    # scale = 200 - 2q for q >= 50, entry = (16 * scale + 50) // 100
    assert luminance_dqt(logged[0].data)[0] == (16 * (200 - 2 * quality) + 50) // 100


def test_image_folder_passes_jpegs_through_and_encodes_others(tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    jpegs = []
    for i in range(4):
        jpegs.append(cv2.imencode(".jpg", scene(i))[1].tobytes())
        (folder / f"img_{i:03d}.jpg").write_bytes(jpegs[-1])
    cv2.imwrite(str(folder / "img_004.png"), scene(4))
    (folder / "img_005.jpg").write_bytes(jpegs[0][:500])  # a truncated file
    (folder / "notes.txt").write_text("not an image")
    driver, log = record(f"file://{folder}?fps=20&pace=0&jpeg_quality=80", tmp_path / "run.mcap")
    logged = images(log)
    assert [msg.data for msg in logged[:4]] == jpegs
    assert logged[4].data == cv2.imencode(".jpg", scene(4), (cv2.IMWRITE_JPEG_QUALITY, 80))[1].tobytes()
    assert (driver.counters["frames"], driver.counters["corrupt"]) == (5, 1)
    stamps = np.array([msg.stamp_ns for msg in logged])
    assert np.abs(np.diff(stamps) - 50_000_000).max() <= 1


def test_static_messages_are_latched_in_the_log(clip: Path, tmp_path: Path) -> None:
    config = {"transform": [0.2, -0.05, 0.3, 0.0, 0.0, math.pi / 2], "name": "front"}
    _, log = record(f"file://{clip}?pace=0", tmp_path / "run.mcap", config)
    (info,) = images(log, "/front/camera_info")
    assert (info.width, info.height, info.frame_id) == (320, 240, "camera_optical")
    (tf,) = images(log, "/tf_static")
    mount, optical = tf.transforms
    assert (mount.frame_id, mount.child_frame_id) == ("base_link", "camera")
    np.testing.assert_allclose(mount.translation, [0.2, -0.05, 0.3])
    np.testing.assert_allclose(mount.rotation, [0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)], atol=1e-12)
    assert (optical.frame_id, optical.child_frame_id) == ("camera", "camera_optical")
    # REP 103: the optical z axis (forward) is the body x axis, optical x (right) is body -y
    x, y, z, w = optical.rotation
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(rotation @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rotation @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    with LogReader(tmp_path / "run.mcap") as reader:
        topics = reader.info().topics
    assert topics["/front/camera_info"].latched and topics["/tf_static"].latched
    assert not topics["/front/image_raw/compressed"].latched


def test_calibration_is_published(clip: Path, tmp_path: Path) -> None:
    calibration = tmp_path / "cam.yaml"
    calibration.write_text("image_width: 320\nimage_height: 240\ncamera_matrix: {rows: 3, cols: 3, data: "
                           "[300, 0, 160, 0, 300, 120, 0, 0, 1]}\ndistortion_model: plumb_bob\n"
                           "distortion_coefficients: {rows: 1, cols: 5, data: [0.1, -0.2, 0, 0, 0]}\n")
    driver = driver_from_url(f"file://{clip}", lambda *a: None, {"calibration": str(calibration)})
    (topic, info), _ = driver.static_messages()
    assert topic == "/camera/camera_info"
    assert info.k[0, 0] == 300 and list(info.d) == [0.1, -0.2, 0, 0, 0]


@pytest.mark.parametrize("url, config, fragment", [
    ("rtsp://camera/stream", {}, "unknown camera URL"),
    ("file:///no/such/clip.avi", {}, "not found"),
    ("file://{tmp}/empty", {}, "holds no images"),
    ("file://{tmp}/notes.txt", {}, "not a video file"),
    ("file://{clip}?width=640", {}, "width and height"),
    ("file://{clip}?fourcc=MJPEG", {}, "four characters"),
    ("file://{clip}?colour=1", {}, r"unknown key camera\.colour \(known in \[camera\]: buffers, "),
    ("file://{clip}", {"controls": {"exposur": 100}}, "unknown control 'exposur'"),
    ("file://{clip}", {"controls": {"exposure": "high"}}, r"camera\.controls\.exposure = \'high\': expected a number"),
    ("file://{clip}?jpeg_quality=101", {}, "jpeg_quality"),
    ("file://{clip}?pace=maybe", {}, "true or false"),
    ("file://{clip}?raw_output=rgb8", {}, "raw_output"),
    ("file://{clip}", {"transform": [1, 2, 3]}, "roll, pitch, yaw"),
    ("file://{clip}", {"calibration": "{tmp}/missing.yaml"}, "not found"),
    ("v4l2://{clip}", {}, "not a video device"),
])
def test_user_mistakes_are_one_line_errors(clip: Path, tmp_path: Path, url: str, config: dict, fragment: str) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.txt").write_text("hello")
    fill = {"tmp": tmp_path, "clip": clip}
    url = url.format(**fill)
    config = {k: v.format(**fill) if isinstance(v, str) else v for k, v in config.items()}
    with pytest.raises(UserError, match=fragment) as error:
        driver_from_url(url, lambda *a: None, config)
    assert "\n" not in str(error.value)


def test_calibration_for_another_size_is_refused(clip: Path, tmp_path: Path) -> None:
    calibration = tmp_path / "cam.yaml"
    calibration.write_text(
        "image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: "
        "[1, 0, 0, 0, 1, 0, 0, 0, 1]}\ndistortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n"
    )
    with pytest.raises(UserError, match="640x480"):
        driver_from_url(f"file://{clip}", lambda *a: None, {"calibration": str(calibration)})


def test_trundle_record_logs_a_camera(clip: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run.mcap"
    assert main(["record", "--camera", f"file://{clip}?pace=0", "--duration", "1", "-o", str(out)]) == 0
    with LogReader(out) as reader:
        topics = reader.info().topics
        logged = [entry.msg.data for entry in reader.messages([IMAGE_TOPIC])]
        diagnostics = [entry.msg for entry in reader.messages(["/diagnostics"])]
    assert logged == [payload for _, payload in avi_video_chunks(clip)]
    assert topics["/camera/camera_info"].count == 1 and topics["/tf_static"].count == 1
    values = dict(diagnostics[-1].status[0].values)
    assert values["frames"] == "30" and values["setting.fourcc"] == "MJPG"
    assert "camera: " in capsys.readouterr().out


def test_a_camera_not_plugged_in_is_waited_for_and_said(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Not a configuration mistake: the camera may come later (the daemon waits for it); `record`
    says the cause on stderr and, having recorded no frame, ends with exit code 1."""
    driver = driver_from_url("v4l2:///dev/video-trundle-none", lambda *a: None, {})
    assert "no camera at /dev/video-trundle-none" in str(pytest.raises(DeviceError, driver.open).value)
    assert (
        main(["record", "--camera", "v4l2:///dev/video-none", "--duration", "3", "-o", str(tmp_path / "x.mcap")]) == 1
    )
    err = capsys.readouterr().err.splitlines()
    assert err[-2].startswith("trundle record: camera: recorded no frames: no camera at /dev/video-none (unplugged?")
    assert err[-1].startswith("trundle record: no device recorded anything: no log was kept")
    assert not list(tmp_path.iterdir())


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(0, 255)), min_size=1, max_size=40))
def test_damaged_container_never_crashes_the_driver(clip: Path, damage: list[tuple[float, int]]) -> None:
    data = bytearray(clip.read_bytes())
    for where, value in damage:
        data[int(where * len(data))] = value
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "damaged.avi"
        path.write_bytes(bytes(data))
        logged: list[m.CompressedImage] = []
        try:
            driver = driver_from_url(f"file://{path}?pace=0", lambda topic, msg, t: logged.append(msg), {})
        except UserError:
            return  # FFmpeg no longer recognises the file: the user is told so
        driver.start()
        wait_for(lambda: driver.finished.is_set() or driver.counters["errors"] > 0, what="end or error")
        driver.stop()
    assert not driver._thread.is_alive()
    assert all(jpeg_problem(msg.data) is None for msg in logged)
    assert driver.counters["frames"] == len(logged)
