"""The onboard service: supervised drivers, the logger, online processing, health and status.

``Daemon(config).run()`` (what ``trundle daemon --config robot.toml`` does):

- builds every configured driver (``trundle.drivers.lrf``, ``trundle.drivers.wheels``, ``trundle.drivers.camera``
  through ``driver_from_url``) and runs each on its own supervised thread: a driver thread that
  dies of an unexpected exception is reported (stderr, ``/diagnostics``, status) and restarted
  after a back-off; device faults are the drivers' own business (they reconnect themselves);
- logs everything to MCAP in the configured folder (``trundle.logs.writer.Logger``: ``.active`` files,
  flush timer, splits repeating ``/tf_static`` and camera info), with a disk guard that deletes
  the oldest logs or stops recording below a free-space floor, and resumes above it;
- runs wheel odometry on the wheels driver's messages (``trundle.fusion.odometry.OdometrySink``, when the
  ``[can]`` table has ``wheel_radius_m`` and ``track_m``) and online processing off the drivers'
  threads (SLAM on ``/scan`` + ``/odom``, ArUco markers on camera images);
- streams the same topics to Foxglove over a WebSocket when ``[live] enabled`` (``trundle.tools.daemon.live_view``);
- publishes ``/diagnostics`` every period, answers ``trundle status`` on a UNIX socket with one
  JSON object, and speaks systemd's notify protocol (READY=1, WATCHDOG=1, STATUS=, STOPPING=1);
- SIGTERM/SIGINT stop it cleanly (every file closed and renamed), SIGHUP starts a new split.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import shutil
import signal
import socket
import socketserver
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from trundle.drivers import devices
from trundle.drivers.lifecycle import Driver, wall_ns
from trundle.fusion.odometry import OdometrySink, odometry_from_config
from trundle.fusion.slam import Slam, SlamConfig
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.writer import Logger, LoggerError, metadata_json
from trundle.perception.markers import MarkerDetector, marker_pose
from trundle.tools.daemon.config import DaemonConfig, Device
from trundle.tools.daemon.live_view import LiveView

DriverFactory = Callable[[str, str, Any, dict[str, Any]], Driver]
NO_SPLIT_BYTES = 1 << 62  # split only on request: the logger then numbers its files
LOGGER_RETRY_S = 5.0
STATUS_TIMEOUT_S = 2.0


def sd_notify(state: str) -> bool:
    """Send ``state`` (e.g. ``READY=1``) to systemd's notify socket; False when not under systemd."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.send(state.encode(), socket.MSG_DONTWAIT)  # never block the main loop on a slow reader
    except OSError:
        return False
    return True


def watchdog_period_s() -> float | None:
    """Half of systemd's ``WatchdogSec`` (from ``WATCHDOG_USEC``) when it is meant for this process."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    try:
        return max(int(usec) / 2e6, 0.01)
    except ValueError:
        return None


def static_transform(stamp_ns: int, parent: str, child: str, xyz: tuple[float, float, float],
                     rpy: tuple[float, float, float]) -> m.TransformStamped:
    quaternion = Rotation.from_euler("xyz", rpy).as_quat()  # x, y, z, w
    return m.TransformStamped(stamp_ns, parent, child, xyz, quaternion)


class Supervised:
    """One driver on a daemon thread; an exception escaping ``Driver.run`` is a crash."""

    def __init__(self, device: Device, driver: Driver, restart_delay_s: float, max_delay_s: float,
                 on_crash: Callable[[Supervised], None] = lambda s: None) -> None:
        self.device, self.driver, self.on_crash = device, driver, on_crash
        self.initial_delay_s, self.max_delay_s = restart_delay_s, max_delay_s
        self.delay_s = restart_delay_s
        self.crashes = 0
        self.last_crash = ""
        self.restart_at: float | None = None
        self.started_at = 0.0
        self.thread: threading.Thread | None = None

    def start(self) -> None:
        self.restart_at = None
        self.started_at = time.monotonic()
        self.thread = threading.Thread(target=self._run, name=f"driver-{self.device.name}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.driver.run()
        except BaseException as error:  # noqa: BLE001 -- a driver bug must not take the daemon down
            frame = traceback.extract_tb(error.__traceback__)[-1] if error.__traceback__ else None
            where = f" at {Path(frame.filename).name}:{frame.lineno}" if frame else ""
            self.last_crash = f"{type(error).__name__}: {error}{where}"
            self.crashes += 1
            now = time.monotonic()
            if now - self.started_at > 60.0:
                self.delay_s = self.initial_delay_s
            self.restart_at = now + self.delay_s
            self.delay_s = min(self.delay_s * 2.0, self.max_delay_s)
            print(f"trundle daemon: driver {self.device.name} crashed ({self.last_crash}); "
                  f"restarting in {self.restart_at - now:.1f} s", file=sys.stderr, flush=True)
            self.on_crash(self)

    @property
    def crashed(self) -> bool:
        return self.restart_at is not None

    def stop(self, timeout_s: float) -> None:
        self.restart_at = None
        self.driver.stop(timeout_s)
        if self.thread is not None:
            self.thread.join(timeout_s)


class TopicRates:
    """Message counts per topic and the rates over the last measuring period."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.rates: dict[str, float] = {}
        self._last: dict[str, int] = {}
        self._last_t = time.monotonic()

    def count(self, topic: str) -> None:
        self.counts[topic] += 1

    def update(self, now: float) -> None:
        dt = now - self._last_t
        if dt <= 0:
            return
        counts = dict(self.counts)
        self.rates = {t: (n - self._last.get(t, 0)) / dt for t, n in sorted(counts.items())}
        self._last, self._last_t = counts, now


class Processing:
    """Online processing on its own thread, fed through a bounded queue (drops counted)."""

    def __init__(self, daemon: Daemon) -> None:
        cfg = daemon.config.processing
        self.daemon = daemon
        self.config = cfg
        self.queue: collections.deque[tuple[str, m.Message] | None] = collections.deque()
        self.wake = threading.Event()
        self.dropped = 0
        self.skipped_scans = 0
        self.errors = 0
        self.last_error = ""
        self.markers_seen: collections.Counter[int] = collections.Counter()
        self._next_marker_t = 0.0
        self._next_map_t = 0.0
        self._camera_info: dict[str, m.CameraInfo] = {}
        self.slam: Slam | None = Slam(SlamConfig.from_mapping(daemon.config.slam)) if cfg.slam else None
        self.scan_topic = self.slam.config.scan_topic if self.slam is not None else ""
        self.detector = MarkerDetector(cfg.aruco_dictionary) if cfg.markers else None
        self.thread = threading.Thread(target=self._run, name="processing", daemon=True)

    @property
    def active(self) -> bool:
        return self.slam is not None or self.detector is not None

    def wants(self, topic: str, msg: m.Message) -> bool:
        if self.slam is not None and (topic == self.scan_topic or isinstance(msg, m.Odometry) or topic == "/tf_static"):
            return True
        if self.detector is not None:
            if isinstance(msg, m.CameraInfo):
                self._camera_info[msg.frame_id] = msg
            elif isinstance(msg, m.CompressedImage | m.Image):
                now = time.monotonic()
                if now >= self._next_marker_t:  # rate-limit before queueing: images are large
                    self._next_marker_t = now + 1.0 / max(self.config.markers_hz, 1e-3)
                    return True
        return False

    def put(self, topic: str, msg: m.Message) -> None:
        if len(self.queue) >= self.config.queue_size:
            self.dropped += 1
            return
        self.queue.append((topic, msg))
        self.wake.set()

    def stop(self) -> None:
        self.queue.append(None)
        self.wake.set()
        self.thread.join(10.0)

    def _run(self) -> None:
        while True:
            self.wake.wait(0.5)
            self.wake.clear()
            batch = [self.queue.popleft() for _ in range(len(self.queue))]
            # behind real time: of the scans waiting, SLAM takes the newest (odometry is all used)
            scans = [i for i, item in enumerate(batch) if item is not None and isinstance(item[1], m.LaserScan)]
            self.skipped_scans += max(len(scans) - 1, 0)
            stale = set(scans[:-1])
            for i, item in enumerate(batch):
                if item is None:
                    return
                if i in stale:
                    continue
                try:
                    self._handle(*item)
                except Exception as error:  # noqa: BLE001 -- keep processing the next message
                    self.errors += 1
                    self.last_error = f"{type(error).__name__}: {error}"

    def _handle(self, topic: str, msg: m.Message) -> None:
        frames = self.daemon.config.frames
        if isinstance(msg, m.CompressedImage | m.Image):
            self._detect_markers(topic, msg)
            return
        assert self.slam is not None
        result = self.slam.process(topic, msg)
        if result is None:
            return
        now = wall_ns()
        x, y, theta = (float(v) for v in result.pose_map)
        self.daemon.publish("/slam/pose", m.Pose2D(result.stamp_ns, frames.map, x, y, theta))
        mx, my, mt = (float(v) for v in self.slam.map_to_odom)
        self.daemon.publish("/tf", m.TFMessage((m.TransformStamped.planar(result.stamp_ns, frames.map, frames.odom,
                                                                          mx, my, mt),)))
        if time.monotonic() >= self._next_map_t:
            self._next_map_t = time.monotonic() + self.config.map_period_s
            self.daemon.publish("/map", self.slam.build_map().to_message(now, frames.map))

    def _detect_markers(self, topic: str, msg: m.CompressedImage | m.Image) -> None:
        if isinstance(msg, m.CompressedImage):
            image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        else:
            image = msg.to_array()
        if image is None:
            return
        assert self.detector is not None
        info = self._camera_info.get(msg.frame_id)
        base = topic.rsplit("/image_raw", 1)[0]
        for marker in self.detector.detect(image):
            self.markers_seen[marker.id] += 1
            self.daemon.publish(f"{base}/markers", m.ImageMarker(
                msg.stamp_ns, msg.frame_id, "aruco", marker.id, m.POLYGON, marker.centre,
                points=marker.corners))
            if info is not None and info.k[0, 0] > 0:  # calibrated
                pose = marker_pose(marker, info, self.config.marker_size_m)
                self.daemon.publish(f"{base}/marker_poses", m.TFMessage((m.TransformStamped(
                    msg.stamp_ns, msg.frame_id, f"aruco_{marker.id}", pose.translation, pose.quaternion()),)))

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"queue": len(self.queue), "dropped": self.dropped, "skipped_scans": self.skipped_scans,
                               "errors": self.errors, "last_error": self.last_error}
        if self.slam is not None:
            s = self.slam.stats
            out["slam"] = {"scans": s.scans, "keyframes": s.keyframes, "matched": s.matched,
                           "loop_closures": s.loop_closures}
        if self.detector is not None:
            out["markers"] = {str(k): v for k, v in sorted(self.markers_seen.items())}
        return out


class _StatusHandler(socketserver.StreamRequestHandler):
    timeout = STATUS_TIMEOUT_S

    def handle(self) -> None:
        try:
            request = self.rfile.readline(256).decode(errors="replace").strip() or "status"
        except OSError:
            return
        daemon: Daemon = self.server.daemon  # type: ignore[attr-defined]
        if request == "status":
            reply = daemon.status()
        else:
            reply = {"error": f"unknown request {request!r} (send 'status')"}
        with contextlib.suppress(OSError):
            self.wfile.write(json.dumps(reply, default=str).encode() + b"\n")


class _StatusServer(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True


def query_status(path: str | os.PathLike[str], timeout_s: float = STATUS_TIMEOUT_S) -> dict[str, Any]:
    """Ask the daemon at socket ``path`` for its status (a UserError when nobody answers)."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout_s)
            sock.connect(os.fspath(path))
            sock.sendall(b"status\n")
            chunks = []
            while chunk := sock.recv(65536):
                chunks.append(chunk)
    except (FileNotFoundError, ConnectionRefusedError):
        raise UserError(f"no trundle daemon is answering at {path} (is it running? see --socket)") from None
    except OSError as error:
        raise UserError(f"cannot ask the daemon at {path}: {error.strerror or error}") from None
    try:
        return json.loads(b"".join(chunks))
    except json.JSONDecodeError:
        raise UserError(f"the daemon at {path} sent an unreadable answer") from None


class Daemon:
    """The service. ``run()`` blocks until SIGTERM/SIGINT (or ``stop()``); see the module doc."""

    def __init__(self, config: DaemonConfig, *, make_driver: DriverFactory | None = None) -> None:
        self.config = config
        self._make_driver = make_driver or devices.make_driver
        self.supervised: list[Supervised] = []
        self.rates: dict[str, TopicRates] = {}
        self.logger: Logger | None = None
        self.logger_files: list[Path] = []
        self.recording_paused = ""
        self.deleted: list[str] = []
        self.disk: dict[str, Any] = {}
        self.unrecorded = 0
        self.logger_failures = 0
        self.started_ns = wall_ns()
        self.state = "starting"
        self._static_tf: dict[str, m.TransformStamped] = {}
        self._latched: dict[str, m.Message] = {}
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop_requested = False
        self._split_requested = False
        self._server: _StatusServer | None = None
        self._logger_retry_at = 0.0
        self._stop_counts: dict[str, dict[str, int]] = {}
        self.processing: Processing | None = None
        self.odometry: dict[str, OdometrySink] = {}
        self.live: LiveView | None = None
        self.live_errors = 0

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Build drivers, open the log, start everything, tell systemd we are ready."""
        cfg = self.config
        for transform in cfg.transforms:
            self._static_tf[transform.child] = static_transform(wall_ns(), transform.parent, transform.child,
                                                                transform.xyz, transform.rpy)
        if self._static_tf:
            self._latched["/tf_static"] = m.TFMessage(tuple(self._static_tf.values()))
        for device in cfg.devices:
            options = dict(device.options)
            sink: Callable[[str, m.Message, int], object] = self._sink(device.name)
            try:
                odometry = odometry_from_config(options) if device.family == "can" and cfg.processing.odometry else None
                if odometry is not None:  # /odom and odom -> base_link from the wheel states, on the driver's thread
                    sink = self.odometry[device.name] = OdometrySink(sink, odometry, name=f"{cfg.robot}/odometry")
                driver = self._make_driver(device.family, device.url, sink, options)
            except UserError as error:
                raise UserError(f"{device.family} device {device.name!r}: {error}") from None
            self.rates[device.name] = TopicRates()
            self.supervised.append(Supervised(device, driver, cfg.supervision.restart_delay_s,
                                              cfg.supervision.max_restart_delay_s,
                                              on_crash=lambda sup: self.publish("/diagnostics", self._diagnostics())))
            for topic, msg in driver.static_messages():
                self._remember_latched(topic, msg)
        try:
            cfg.logger.folder.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise UserError(f"cannot create the log folder {cfg.logger.folder}: {error.strerror or error}") from None
        if cfg.live.enabled:
            self.live = LiveView(cfg.live.host, cfg.live.port, name=f"trundle {cfg.robot}")
            for topic, msg in list(self._latched.items()):
                self.live(topic, msg, wall_ns())
        processing = Processing(self)
        if processing.active:
            self.processing = processing
            processing.thread.start()
        self._check_disk()
        if cfg.logger.record and not self.recording_paused:
            self._open_logger()
        self._start_status_server()
        for sup in self.supervised:
            sup.start()
        self.state = "running"
        sd_notify("READY=1\nSTATUS=" + self._summary())

    def run(self, *, install_signals: bool = True) -> int:
        """Start, then supervise until a stop is requested; always shuts down cleanly."""
        previous: dict[int, Any] = {}
        if install_signals:
            for sig, handler in ((signal.SIGTERM, self._on_stop_signal), (signal.SIGINT, self._on_stop_signal),
                                 (signal.SIGHUP, self._on_split_signal)):
                previous[sig] = signal.signal(sig, handler)
        try:
            self.start()
            watchdog = watchdog_period_s()
            period = self.config.status.diagnostics_period_s
            next_diag = next_disk = time.monotonic()
            next_watchdog = time.monotonic()
            while not self._stop_requested:
                now = time.monotonic()
                deadlines = [next_diag, next_disk] + ([next_watchdog] if watchdog else [])
                self._wake.wait(max(0.0, min(deadlines) - now))
                self._wake.clear()
                now = time.monotonic()
                if self._split_requested:
                    self._split_requested = False
                    self.split()
                self._supervise(now)
                if now >= next_disk:
                    next_disk = now + self.config.disk.check_period_s
                    self._check_disk()
                self._check_logger(now)
                if now >= next_diag:
                    next_diag = now + period
                    self._publish_diagnostics(now)
                if watchdog and now >= next_watchdog:
                    next_watchdog = now + watchdog
                    sd_notify("WATCHDOG=1")
        finally:
            self.shutdown()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return 0

    def stop(self) -> None:
        """Ask ``run`` to finish (what SIGTERM does); safe from any thread."""
        self._stop_requested = True
        self._wake.set()

    def request_split(self) -> None:
        """Ask ``run`` to start a new log file (what SIGHUP does); safe from any thread."""
        self._split_requested = True
        self._wake.set()

    def _on_stop_signal(self, signum: int, frame: Any) -> None:
        self.stop()

    def _on_split_signal(self, signum: int, frame: Any) -> None:
        self.request_split()

    def shutdown(self) -> None:
        """Stop drivers and processing, write the last diagnostics, close the log, close the socket."""
        if self.state == "stopped":
            return
        self.state = "stopping"
        sd_notify("STOPPING=1")
        timeout = self.config.supervision.stop_timeout_s
        for sup in self.supervised:
            sup.stop(timeout)
        if self.processing is not None:
            self.processing.stop()
        if self.supervised:
            self._publish_diagnostics(time.monotonic())
        self._close_logger()
        if self.live is not None:
            self.live.close()
            self.live = None
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            with contextlib.suppress(FileNotFoundError):
                self.config.status.socket.unlink()
            self._server = None
        self.state = "stopped"

    # ------------------------------------------------------------------ messages
    def _sink(self, device: str) -> Callable[[str, m.Message, int], None]:
        def sink(topic: str, msg: m.Message, log_time_ns: int) -> None:
            self.rates[device].count(topic)
            self._route(topic, msg, log_time_ns)
        return sink

    def publish(self, topic: str, msg: m.Message, log_time_ns: int | None = None) -> None:
        """Log a message the daemon itself produced (diagnostics, SLAM output, detections)."""
        self._route(topic, msg, wall_ns() if log_time_ns is None else log_time_ns, processed=True)

    def _route(self, topic: str, msg: m.Message, log_time_ns: int, processed: bool = False) -> None:
        if topic == "/tf_static" or topic.endswith("camera_info"):
            self._remember_latched(topic, msg)
            msg = self._latched.get(topic, msg)
        logger = self.logger
        if logger is not None:
            logger.write(topic, msg, log_time_ns)  # a full queue is counted by the logger as a drop
        else:
            self.unrecorded += 1
        live = self.live
        if live is not None:
            try:
                live(topic, msg, log_time_ns)
            except Exception:  # noqa: BLE001 -- the live view must never stop the logging
                self.live_errors += 1
        processing = self.processing
        if processing is not None and not processed and processing.wants(topic, msg):
            processing.put(topic, msg)

    def _remember_latched(self, topic: str, msg: m.Message) -> None:
        """Merge every static transform into one /tf_static message (the logger keeps the last one)."""
        with self._lock:
            if topic == "/tf_static" and isinstance(msg, m.TFMessage):
                for transform in msg.transforms:
                    self._static_tf[transform.child_frame_id] = transform
                self._latched[topic] = m.TFMessage(tuple(self._static_tf.values()))
            else:
                self._latched[topic] = msg

    # ------------------------------------------------------------------ logger
    def _open_logger(self) -> None:
        cfg = self.config.logger
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime())
        path = cfg.folder / f"{cfg.prefix}_{stamp}.mcap"
        n = 1
        while any(cfg.folder.glob(f"{path.stem}*")):
            path = cfg.folder / f"{cfg.prefix}_{stamp}-{n}.mcap"
            n += 1
        metadata = {"command": "daemon", "robot": self.config.robot, "config_file": self.config.source,
                    "devices": metadata_json({d.name: {"family": d.family, "url": d.url, **d.options}
                                              for d in self.config.devices})}
        try:
            logger = Logger(path, compression=cfg.compression, chunk_size=cfg.chunk_size_kb * 1024,
                            flush_period_s=cfg.flush_period_s, fsync=cfg.fsync,
                            split_bytes=int(cfg.split_size_mb * 1e6) or NO_SPLIT_BYTES,
                            split_duration_s=cfg.split_duration_s or None, queue_size=cfg.queue_size,
                            metadata=metadata)
        except (OSError, UserError) as error:
            self._logger_failed(f"cannot open a log in {cfg.folder}: {error}")
            return
        with self._lock:
            latched = list(self._latched.items())
        for topic, msg in latched:
            logger.write(topic, msg)
        self.logger = logger
        self.recording_paused = ""

    def _close_logger(self) -> None:
        logger, self.logger = self.logger, None
        if logger is None:
            return
        try:
            logger.close()
        except LoggerError as error:
            print(f"trundle daemon: {error}", file=sys.stderr, flush=True)
        self.logger_files.extend(logger.files)
        self._stop_counts = logger.stats_dict()

    def _logger_failed(self, reason: str) -> None:
        self.logger_failures += 1
        self.recording_paused = reason
        self._logger_retry_at = time.monotonic() + LOGGER_RETRY_S
        print(f"trundle daemon: recording paused: {reason}", file=sys.stderr, flush=True)

    def _check_logger(self, now: float) -> None:
        logger = self.logger
        if logger is not None and logger.error is not None:
            reason = str(logger.error)
            self._close_logger()
            self._logger_failed(reason)
        elif (logger is None and self.config.logger.record and self.recording_paused
              and not self.recording_paused.startswith("disk") and now >= self._logger_retry_at):
            self._open_logger()

    def split(self) -> None:
        """Start a new log file now (latched topics are repeated in it)."""
        if self.logger is not None:
            self.logger.split()

    # ------------------------------------------------------------------ disk guard
    def _check_disk(self) -> None:
        """Below ``min_free_mb``: delete the oldest closed logs (or stop recording); resume above it."""
        cfg, folder = self.config.disk, self.config.logger.folder
        floor = cfg.min_free_mb * 1e6
        try:
            usage = shutil.disk_usage(folder)
        except OSError as error:
            self.disk = {"folder": str(folder), "error": error.strerror or str(error)}
            return
        free = usage.free
        if free < floor and cfg.action == "delete_oldest":
            for path in self._deletable_logs():
                try:
                    path.unlink()
                except OSError:
                    continue
                self.deleted.append(path.name)
                print(f"trundle daemon: disk low, deleted {path}", file=sys.stderr, flush=True)
                usage = shutil.disk_usage(folder)
                free = usage.free
                if free >= floor:
                    break
        if free < floor and not self.recording_paused.startswith("disk"):
            reason = f"disk low: {free / 1e6:.0f} MB free in {folder}, below {cfg.min_free_mb:.0f} MB"
            self._close_logger()
            self.recording_paused = reason
            print(f"trundle daemon: recording stopped: {reason}", file=sys.stderr, flush=True)
        elif (self.recording_paused.startswith("disk") and free >= floor * (1.0 + cfg.resume_margin)
              and self.config.logger.record):
            print("trundle daemon: disk space back, recording again", file=sys.stderr, flush=True)
            self.recording_paused = ""
            if self.state == "running":
                self._open_logger()
        self.disk = {"folder": str(folder), "free_bytes": free, "total_bytes": usage.total,
                     "min_free_bytes": int(floor), "action": cfg.action, "low": free < floor,
                     "deleted": self.deleted[-10:], "deleted_count": len(self.deleted)}

    def _deletable_logs(self) -> list[Path]:
        """Closed ``*.mcap`` files in the log folder, oldest first (never the file being written)."""
        current = self.logger.current_path if self.logger is not None else None
        logs = [p for p in self.config.logger.folder.glob("*.mcap") if p.is_file() and p != current]
        return sorted(logs, key=lambda p: (p.stat().st_mtime, p.name))

    # ------------------------------------------------------------------ supervision and health
    def _supervise(self, now: float) -> None:
        for sup in self.supervised:
            if sup.restart_at is not None and now >= sup.restart_at and not self._stop_requested:
                print(f"trundle daemon: restarting driver {sup.device.name}", file=sys.stderr, flush=True)
                sup.start()

    def _device_status(self, sup: Supervised) -> dict[str, Any]:
        driver, rates = sup.driver, self.rates[sup.device.name]
        state = "crashed" if sup.crashed else driver.state
        return {"name": sup.device.name, "family": sup.device.family, "url": sup.device.url, "state": state,
                "rates_hz": {t: round(r, 2) for t, r in rates.rates.items()},
                "messages": dict(rates.counts), "errors": int(driver.counters.get("errors", 0)),
                "reconnects": int(driver.counters.get("reconnects", 0)), "crashes": sup.crashes,
                "last_error": driver.last_error, "last_crash": sup.last_crash,
                "counters": {k: int(v) for k, v in sorted(driver.counters.items())}}

    def _diagnostics(self) -> m.DiagnosticArray:
        statuses = []
        for sup in self.supervised:
            status = sup.driver.diagnostics()
            rates = self.rates[sup.device.name].rates
            values = (*status.values, *((f"rate {t}", f"{r:.2f} Hz") for t, r in rates.items()),
                      ("crashes", str(sup.crashes)))
            level, message = status.level, status.message
            if sup.crashed:
                level, message = m.ERROR, f"driver crashed: {sup.last_crash}"
                values = (*values, ("last_crash", sup.last_crash))
            statuses.append(m.DiagnosticStatus(level, f"{self.config.robot}/{sup.device.name}", message,
                                               status.hardware_id, values))
        log = self._logger_status()
        level = m.OK if log["recording"] else m.WARN
        if not self.config.logger.record:
            level = m.OK
        message = "recording" if log["recording"] else (self.recording_paused or "not recording")
        statuses.append(m.DiagnosticStatus(level, f"{self.config.robot}/logger", message, "", tuple(
            (k, str(log[k])) for k in ("file", "size_bytes", "written", "dropped", "queue"))))
        disk = self.disk
        disk_level = m.ERROR if disk.get("low") or "error" in disk else m.OK
        statuses.append(m.DiagnosticStatus(disk_level, f"{self.config.robot}/disk",
                                           disk.get("error", f"{disk.get('free_bytes', 0) / 1e9:.2f} GB free"), "",
                                           tuple((k, str(v)) for k, v in disk.items() if k != "deleted")))
        return m.DiagnosticArray(wall_ns(), tuple(statuses))

    def _publish_diagnostics(self, now: float) -> None:
        for rates in self.rates.values():
            rates.update(now)
        self.publish("/diagnostics", self._diagnostics())
        if self.live is not None:
            self.live.repeat_latched()
        sd_notify("STATUS=" + self._summary())

    def _summary(self) -> str:
        parts = [f"{s.device.name} {'crashed' if s.crashed else s.driver.state}" for s in self.supervised]
        log = "recording" if self.logger is not None else (self.recording_paused or "not recording")
        return f"{log}; " + ", ".join(parts)

    def _logger_status(self) -> dict[str, Any]:
        logger = self.logger
        files = [str(p) for p in self.logger_files]
        if logger is None:
            stats = self._stop_counts
            return {"recording": False, "paused": self.recording_paused, "file": None, "size_bytes": 0,
                    "files": files, "written": sum(s["written"] for s in stats.values()),
                    "dropped": sum(s["dropped"] for s in stats.values()), "queue": 0,
                    "unrecorded": self.unrecorded, "failures": self.logger_failures}
        current = logger.current_path
        size = 0
        if current is not None:
            with contextlib.suppress(OSError):
                size = current.stat().st_size
        stats = logger.stats_dict()
        return {"recording": True, "paused": "", "file": str(current) if current else None, "size_bytes": size,
                "files": files + [str(p) for p in logger.files],
                "written": sum(s["written"] for s in stats.values()),
                "dropped": sum(s["dropped"] for s in stats.values()), "queue": logger.queue_length,
                "unrecorded": self.unrecorded, "failures": self.logger_failures,
                "topics": stats}

    def status(self) -> dict[str, Any]:
        """Everything ``trundle status`` shows, as one JSON-able dict."""
        out: dict[str, Any] = {
            "daemon": {"pid": os.getpid(), "robot": self.config.robot, "state": self.state,
                       "config": self.config.source, "started_ns": self.started_ns,
                       "uptime_s": round((wall_ns() - self.started_ns) / 1e9, 1)},
            "devices": [self._device_status(s) for s in self.supervised],
            "logger": self._logger_status(),
            "disk": self.disk,
        }
        if self.processing is not None:
            out["processing"] = self.processing.status()
        if self.live is not None:
            out["live"] = {"url": f"ws://{self.config.live.host}:{self.live.port}", "sent": self.live.sent,
                           "errors": self.live_errors}
        if self.odometry:
            out["odometry"] = {name: {"stale": sink.odometry.stale, "gaps": sink.odometry.gaps,
                                      "distance_m": round(sink.odometry.distance_m, 3)}
                               for name, sink in self.odometry.items()}
        return out

    # ------------------------------------------------------------------ status socket
    def _start_status_server(self) -> None:
        path = self.config.status.socket
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise UserError(f"cannot create {path.parent} for the status socket: {error.strerror or error}") from None
        if path.exists() or path.is_symlink():
            try:
                query_status(path, timeout_s=0.5)
            except UserError:
                path.unlink(missing_ok=True)  # a stale socket left by a killed daemon
            else:
                raise UserError(f"another trundle daemon is answering at {path}")
        try:
            server = _StatusServer(os.fspath(path), _StatusHandler)
        except OSError as error:
            raise UserError(f"cannot open the status socket {path}: {error.strerror or error}") from None
        os.chmod(path, 0o660)
        server.daemon = self  # type: ignore[attr-defined]
        threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, name="status",
                         daemon=True).start()
        self._server = server


def format_status(status: dict[str, Any]) -> str:
    """The human-readable form of a status answer (what ``trundle status`` prints)."""
    d = status["daemon"]
    lines = [f"trundle daemon ({d['robot']}): {d['state']}, pid {d['pid']}, up {_duration(d['uptime_s'])}"]
    lines.append("devices:")
    for dev in status["devices"]:
        rates = ", ".join(f"{t} {r:.1f} Hz" for t, r in dev["rates_hz"].items()) or "no messages"
        lines.append(f"  {dev['name']:<10} {dev['family']:<6} {dev['state']:<10} {rates}")
        lines.append(f"  {'':<10} errors {dev['errors']}, reconnects {dev['reconnects']}, crashes {dev['crashes']}"
                     + (f"; last error: {dev['last_error']}" if dev["last_error"] else "")
                     + (f"; last crash: {dev['last_crash']}" if dev["last_crash"] else ""))
    log = status["logger"]
    if log["recording"]:
        lines.append(f"logger: recording {log['file']} ({_size(log['size_bytes'])}), written {log['written']}, "
                     f"dropped {log['dropped']}, queue {log['queue']}")
    else:
        lines.append(f"logger: not recording ({log['paused'] or 'disabled'}), written {log['written']}, "
                     f"dropped {log['dropped']}")
    disk = status.get("disk", {})
    if "error" in disk:
        lines.append(f"disk: {disk['folder']}: {disk['error']}")
    elif disk:
        lines.append(f"disk: {_size(disk['free_bytes'])} free in {disk['folder']} (floor {_size(disk['min_free_bytes'])}, "
                     f"{disk['action']}; {disk['deleted_count']} logs deleted)")
    for name, odo in status.get("odometry", {}).items():
        lines.append(f"odometry ({name}): {'STALE, ' if odo['stale'] else ''}{odo['distance_m']:.1f} m travelled, "
                     f"{odo['gaps']} gaps")
    if "live" in status:
        lines.append(f"live view: {status['live']['url']} (open it in Foxglove), {status['live']['sent']} messages sent")
    if "processing" in status:
        p = status["processing"]
        extra = "".join(f", {k} {v}" for k, v in p.items() if k in ("slam", "markers"))
        lines.append(f"processing: queue {p['queue']}, dropped {p['dropped']}, errors {p['errors']}{extra}")
    return "\n".join(lines)


def _size(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} TB"


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
