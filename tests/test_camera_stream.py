"""The camera emulator (MJPEG over HTTP) and the driver reading it: pass-through, stamps at
capture (X-Timestamp) or arrival, stalls, unplug/replug, corrupt frames, servers that are silent
or no MJPEG stream; the stream checked with the standard library's MIME parser."""

from __future__ import annotations

import email
import socket
import threading
import urllib.request
from itertools import pairwise
from pathlib import Path

import cv2
import numpy as np
import pytest
from camera_clips import avi_video_chunks, wait_for, write_clip

from trundle.drivers.camera import CameraDriver, driver_from_url
from trundle.drivers.jpeg_check import jpeg_problem
from trundle.drivers.mjpeg_stream import MjpegStreamSource, capture_clock
from trundle.logs import messages as m
from trundle.logs.errors import DeviceError
from trundle.logs.reader import LogReader
from trundle.tools.cli.main import main
from trundle.tools.emulators.camera_emulator import BOUNDARY, CameraEmulator, synthetic_frame


def start_driver(url: str, log_times: list[int] | None = None,
                 **options: object) -> tuple[CameraDriver, list[m.CompressedImage]]:
    """A started driver on ``url`` and the images it publishes (their log times into ``log_times``)."""
    logged: list[m.CompressedImage] = []
    times = [] if log_times is None else log_times

    def sink(topic: str, msg: m.Message, t: int) -> None:
        if topic.endswith("compressed"):
            logged.append(msg)  # type: ignore[arg-type]
            times.append(t)

    driver = driver_from_url(url, sink, dict(options))
    driver.start()
    return driver, logged


def is_subsequence(items: list[bytes], sequence: list[bytes]) -> bool:
    it = iter(sequence)
    return all(any(item == other for other in it) for item in items)


def test_stream_is_logged_byte_for_byte() -> None:
    with CameraEmulator(fps=30, width=320, height=240, history=1000) as emulator:
        driver, logged = start_driver(emulator.url)
        wait_for(lambda: len(logged) >= 15, what="frames")
        driver.stop()
        sent = list(emulator.history)
    assert is_subsequence([msg.data for msg in logged], sent)
    assert driver.settings["pass_through"] == "true"
    assert driver.counters["corrupt"] == 0
    stamps = [msg.stamp_ns for msg in logged]
    assert all(b > a for a, b in pairwise(stamps))


def test_frames_are_stamped_when_captured_not_when_they_arrive() -> None:
    """Every third frame is held back 40 ms before it is sent: its stamp still is its capture time
    (the emulator's X-Timestamp on the host clock, plus the quickest delivery), not its arrival."""
    log_times: list[int] = []
    with CameraEmulator(fps=30, width=160, height=120, history=1000,
                        send_delay=lambda n: 0.04 if n % 3 == 0 else 0.0) as emulator:
        driver, logged = start_driver(emulator.url, log_times)
        wait_for(lambda: len(logged) >= 40, what="frames")
        values = dict(driver.diagnostics().values)
        driver.stop()
        captured = dict(zip(emulator.history, emulator.capture_ns, strict=True))
    assert driver.settings["timestamps"] == "capture"
    capture = np.array([captured[msg.data] for msg in logged])
    stamp_error = np.array([msg.stamp_ns for msg in logged]) - capture
    arrival_error = np.array(log_times) - capture
    assert np.sum(arrival_error > 40_000_000) >= 8  # the held-back frames arrived late ...
    settled = stamp_error[10:]  # after the first frames (the offset comes from the quickest one)
    assert np.all((settled > -100_000) & (settled < 3_000_000))  # ... stamped on time
    assert np.median(settled) < 1_000_000
    assert float(values["latency_max_ms"]) >= 40.0 and values["setting.timestamps"] == "capture"


def test_a_minute_on_a_busy_host_gives_the_camera_clock_no_drift() -> None:
    """The demo's case: a 10 Hz camera on the same machine (no drift), its first 2 s delivered
    40 ms late, then 1 ms plus 20 ms of random delay on average. The stamps keep the quickest
    delivery's latency to the end; a drift fitted to half a minute of it (-145 ppm) would move
    them 8 ms early within the minute."""
    ms = 1_000_000
    true = 1_764_675_000 * 10**9 + np.arange(600) * 100 * ms
    latency = (ms + np.random.default_rng(3).exponential(20 * ms, true.size)).astype(np.int64)
    latency[:20] += 40 * ms
    clock = capture_clock()
    stamps = np.array([clock.update(int(t) + 3_200 * ms, int(t + lat)).stamp_ns for t, lat in zip(true, latency,
                                                                                                  strict=True)])
    settled = np.argmin(latency) + 1
    assert clock.drift_ppm == 0.0 and np.all(stamps[settled:] - true[settled:] == latency.min())


def test_a_stream_without_x_timestamp_is_stamped_on_arrival() -> None:
    log_times: list[int] = []
    with CameraEmulator(fps=30, width=160, height=120, timestamps=False) as emulator:
        driver, logged = start_driver(emulator.url, log_times)
        wait_for(lambda: len(logged) >= 10, what="frames")
        driver.stop()
    assert driver.settings["timestamps"] == "arrival"
    assert [msg.stamp_ns for msg in logged] == log_times


def test_a_silent_server_or_no_mjpeg_stream_is_a_device_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as silent:  # accepts, never answers
        source = MjpegStreamSource(f"http://127.0.0.1:{silent.getsockname()[1]}/stream.mjpg", timeout_s=0.3)
        with pytest.raises(DeviceError, match="cannot open http://127.0.0.1:.*timed out"):
            source.open()
    with CameraEmulator(fps=30, width=160, height=120) as emulator:
        source = MjpegStreamSource(emulator.url.replace("stream.mjpg", "snapshot.jpg"))
        with pytest.raises(DeviceError, match=r"snapshot.jpg is not an MJPEG stream \(HTTP 404"):
            source.open()


def test_a_frame_cut_off_by_the_connection_is_handed_over_as_it_came_then_the_end_is_a_device_error() -> None:
    """A server writing as mjpg-streamer does that dies inside its second frame: the first frame
    whole, the second as far as it came (the driver's JPEG check drops it), then a lost device."""
    whole = cv2.imencode(".jpg", synthetic_frame(0.0, 64, 48))[1].tobytes()
    head = b"Content-Type: image/jpeg\r\nContent-Length: %d\r\nX-Timestamp: 5.250000\r\n\r\n" % len(whole)
    reply = (b"HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=boundarydonotcross\r\n\r\n"
             b"--boundarydonotcross\r\n" + head + whole + b"\r\n--boundarydonotcross\r\n" + head + whole[:500])

    def serve_once(server: socket.socket) -> None:
        connection, _ = server.accept()
        with connection:
            connection.recv(65536)
            connection.sendall(reply)

    with socket.create_server(("127.0.0.1", 0)) as server:
        threading.Thread(target=serve_once, args=(server,), daemon=True).start()
        source = MjpegStreamSource(f"http://127.0.0.1:{server.getsockname()[1]}/?action=stream", timeout_s=5.0)
        source.open()
        try:
            first, cut = source.read(), source.read()
            with pytest.raises(DeviceError, match=r"/\?action=stream: the stream ended"):
                source.read()
        finally:
            source.close()
    assert first.data == whole and jpeg_problem(whole) is None and source.settings()["timestamps"] == "capture"
    assert cut.data == whole[:500] and jpeg_problem(cut.data) == "no EOI marker at the end (truncated frame)"


def test_a_stream_without_a_size_gets_its_camera_info_from_the_first_frame(tmp_path: Path) -> None:
    """MJPEG over HTTP says no size: the CameraInfo (never 0x0) comes with the first frame."""
    with CameraEmulator(fps=30, width=320, height=240) as emulator:
        driver = driver_from_url(emulator.url, lambda *a: None, {})
        assert [topic for topic, _ in driver.static_messages()] == ["/tf_static"]  # the size is not known yet
        out = tmp_path / "cam.mcap"
        assert main(["record", "--camera", emulator.url, "--duration", "2", "-o", str(out)]) == 0
    reader = LogReader(out)
    infos = [x.msg for x in reader.messages(["/camera/camera_info"])]
    first_image = next(reader.messages(["/camera/image_raw/compressed"]))
    assert [(i.width, i.height) for i in infos] == [(320, 240)]
    assert infos[0].stamp_ns <= first_image.msg.stamp_ns


def test_stream_parts_parse_as_mime_multipart() -> None:
    with CameraEmulator(fps=30, width=160, height=120, history=100) as emulator:
        with urllib.request.urlopen(emulator.url, timeout=5) as response:
            content_type = response.headers["Content-Type"]
            body = b""
            while body.count(f"--{BOUNDARY}".encode()) < 4:
                body += response.read1(65536)
        sent = list(emulator.history)
    assert content_type == f"multipart/x-mixed-replace; boundary={BOUNDARY}"
    complete = body[: body.rindex(f"--{BOUNDARY}".encode())] + f"--{BOUNDARY}--\r\n".encode()
    message = email.message_from_bytes(f"Content-Type: {content_type}\r\n\r\n".encode() + complete)
    parts = message.get_payload()
    assert len(parts) == 3
    for part in parts:
        assert part.get_content_type() == "image/jpeg"
        payload = part.get_payload(decode=True)
        assert payload in sent and int(part["Content-Length"]) == len(payload)
        assert cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_COLOR).shape == (120, 160, 3)


def test_stall_is_detected_without_a_long_hang_and_recovers() -> None:
    with CameraEmulator(fps=30, width=160, height=120) as emulator:
        driver, logged = start_driver(emulator.url, stall_timeout_s=0.4)
        wait_for(lambda: len(logged) >= 5, what="frames")
        emulator.stall(1.5)
        wait_for(lambda: driver.counters["stalls"] >= 1, what="stall detection")
        assert "no frame for 0.4 s" in driver.last_error
        before = len(logged)
        wait_for(lambda: driver.counters["reconnects"] >= 1 and len(logged) >= before + 5, what="recovery")
        driver.stop()
    assert driver.state == "stopped" and not driver._thread.is_alive()


def test_unplug_and_replug_reconnects() -> None:
    with CameraEmulator(fps=30, width=160, height=120, history=1000) as emulator:
        driver, logged = start_driver(emulator.url)
        wait_for(lambda: len(logged) >= 5, what="frames")
        emulator.unplug()
        wait_for(lambda: driver.counters["errors"] >= 2, what="failed reconnects")
        assert driver.counters["reconnects"] == 0
        before = len(logged)
        emulator.replug()
        wait_for(lambda: driver.counters["reconnects"] == 1 and len(logged) >= before + 5, what="frames after replug")
        driver.stop()
        sent = list(emulator.history)
    assert is_subsequence([msg.data for msg in logged], sent)


def test_damaged_frames_from_the_link_are_counted_not_logged() -> None:
    with CameraEmulator(fps=30, width=160, height=120, history=1000) as emulator:
        driver, logged = start_driver(emulator.url)
        wait_for(lambda: len(logged) >= 3, what="frames")
        emulator.corrupt_next(3, "truncate")
        emulator.corrupt_next(2, "marker")
        wait_for(lambda: emulator.corrupted == 5 and len(logged) >= 15, what="damaged frames sent")
        driver.stop()
        sent = list(emulator.history)
    assert driver.counters["corrupt"] == 5
    assert is_subsequence([msg.data for msg in logged], sent)


def test_emulator_serves_mjpeg_file_packets_unchanged(tmp_path: Path) -> None:
    clip = tmp_path / "clip.avi"
    write_clip(clip, count=10, fps=30.0, size=(160, 120))
    chunks = [payload for _, payload in avi_video_chunks(clip)]
    with CameraEmulator(source=clip, history=100) as emulator:
        assert emulator.fps == 30.0
        driver, logged = start_driver(emulator.url)
        wait_for(lambda: len(logged) >= 12, what="frames")
        driver.stop()
        sent = list(emulator.history)
    assert sent[:10] == chunks and sent[10:20] == chunks[: len(sent[10:20])]  # looped
    assert {msg.data for msg in logged} <= set(chunks)


def test_emulator_renders_frames_from_a_callable() -> None:
    times: list[float] = []

    def frame_at(t_s: float) -> np.ndarray:
        times.append(t_s)
        return synthetic_frame(t_s, 200, 100)

    with CameraEmulator(frame_at, fps=50, history=10) as emulator:
        wait_for(lambda: len(times) >= 5, what="rendered frames")
        first = emulator.history[0]
    steps = np.diff(times[:5])
    assert np.all(np.isclose(steps, 0.02) | (steps > 0.02))  # scene time advances at 1/fps (or skips when late)
    assert cv2.imdecode(np.frombuffer(first, np.uint8), cv2.IMREAD_COLOR).shape == (100, 200, 3)


def test_synthetic_scene_moves_and_has_texture() -> None:
    a, b = synthetic_frame(0.0, 320, 240), synthetic_frame(0.5, 320, 240)
    assert a.shape == (240, 320, 3) and a.dtype == np.uint8
    assert np.mean(a != b) > 0.1
    assert len(cv2.ORB_create().detect(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY))) > 50


def test_cli_serves_and_reports(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["emulate", "camera", "--port", "0", "--duration", "0.3", "--width", "160", "--height", "120"]) == 0
    out = capsys.readouterr().out
    assert "http://127.0.0.1:" in out and "/stream.mjpg" in out and "served" in out


def test_cli_bad_source_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["emulate", "camera", "--source", str(tmp_path / "none.avi"), "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not found" in err
