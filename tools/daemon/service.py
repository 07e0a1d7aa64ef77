"""The onboard service: life cycle, message routing, the logger, signals, health and status.

``Daemon(config).run()`` (what ``trundle daemon --config robot.toml`` does):

- builds every configured driver (``trundle.drivers.lrf``, ``trundle.drivers.wheels``, ``trundle.drivers.camera``
  through ``driver_from_url``) and runs each on its own supervised thread (``supervisor``): a driver
  thread that dies of an unexpected exception is reported (stderr, ``/diagnostics``, status) and
  restarted after a back-off; device faults are the drivers' own business (they reconnect themselves);
- logs everything to MCAP in the configured folder (``trundle.logs.writer.Logger``: ``.active`` files,
  flush timer, splits repeating ``/tf_static`` and camera info), with a disk guard (``disk_guard``)
  that deletes the oldest logs it wrote (never another file) or stops recording below a free-space floor,
  and resumes above it;
- runs wheel odometry on the wheels driver's messages (``trundle.fusion.odometry.diff_drive.OdometrySink``, when the
  ``[can]`` table has ``wheel_radius_m`` and ``track_m``) and online processing off the drivers'
  threads (``processing``: SLAM on ``/scan`` + ``/odom``, ArUco markers on camera images);
- streams the same topics to Foxglove over a WebSocket when ``[live] enabled`` (``live_view``);
- publishes ``/diagnostics`` every period, answers ``trundle status`` on a UNIX socket with one
  JSON object (``status``), and speaks systemd's notify protocol (``systemd``: READY=1, WATCHDOG=1,
  STATUS=, STOPPING=1);
- SIGTERM/SIGINT stop it cleanly (every file closed and renamed), SIGHUP starts a new split.

Those modules get what they need from the daemon as callbacks (``publish``, ``status``, the disk
guard's stop and resume), so they never import this one.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from trundle.drivers import devices
from trundle.drivers.health import HealthReporter
from trundle.drivers.lifecycle import Driver, wall_ns
from trundle.fusion.odometry.diff_drive import OdometrySink, odometry_from_config
from trundle.logs import messages as m
from trundle.logs.errors import UserError
from trundle.logs.frames import FrameTree
from trundle.logs.topics import DIAGNOSTICS_TOPIC, TF_STATIC_TOPIC
from trundle.logs.writer import Logger, LoggerError, is_latched
from trundle.tools.config.robot import RobotConfig, check_daemon_config
from trundle.tools.daemon.disk_guard import DAEMON_COMMAND, DiskGuard
from trundle.tools.daemon.live_view import LiveView
from trundle.tools.daemon.processing import Processing, online_estimator
from trundle.tools.daemon.status import StatusServer
from trundle.tools.daemon.supervisor import Supervised, TopicRates
from trundle.tools.daemon.systemd import sd_notify, watchdog_period_s

DriverFactory = Callable[[str, str, Any, dict[str, Any]], Driver]  # (family, url, sink, options) -> driver
NO_SPLIT_BYTES = 1 << 62  # split only on request: the logger then numbers its files
LOGGER_RETRY_S = 5.0  # after a logger failure, try a new log this much later
SIGNAL_POLL_S = 0.1  # the supervision loop's longest sleep: how soon a signal's request is acted on


class Daemon:
    """The service. ``run()`` blocks until SIGTERM/SIGINT (or ``stop()``); see the module doc."""

    def __init__(self, config: RobotConfig, *, make_driver: DriverFactory | None = None) -> None:
        self.config = config
        self._make_driver = make_driver or devices.make_driver
        self.supervised: list[Supervised] = []
        self.logger: Logger | None = None
        self.logger_files: list[Path] = []
        self.recording_paused = ""
        self.disk_guard = DiskGuard(config.disk, config.logger, config.robot, current_log=self._current_log,
                                    stop_recording=self._stop_recording, resume_recording=self._resume_recording)
        self.unrecorded = 0
        self.logger_failures = 0
        self.started_ns = wall_ns()
        self.state = "starting"
        self.static_frames = FrameTree()  # the config's [[transforms]] and the drivers' mounts, merged
        self._latched: dict[str, m.Message] = {}
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stop_requested = False
        self._split_requested = False
        self._server: StatusServer | None = None
        self._logger_retry_at = 0.0
        self._stop_counts: dict[str, dict[str, int]] = {}
        self.processing: Processing | None = None
        self.odometry: dict[str, OdometrySink] = {}
        self.live: LiveView | None = None
        self.live_errors = 0
        self.health = HealthReporter(self.say)
        self.started_at: float | None = None   # monotonic time the daemon said it started
    @staticmethod
    def say(text: str) -> None:
        """One line on stderr (journald, the daemon's log file), ``trundle daemon: ...``."""
        print(f"trundle daemon: {text}", file=sys.stderr, flush=True)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Check the config, build drivers, take the status socket (one daemon per config), open the
        log, start everything, tell systemd we are ready."""
        cfg = self.config
        check_daemon_config(cfg)
        self.static_frames = FrameTree.configured(cfg.transforms, wall_ns())
        if cfg.transforms:
            self._latched[TF_STATIC_TOPIC] = self.static_frames.static_message()
        for device in cfg.devices:
            options = dict(device.options)
            rates = TopicRates()
            sink: Callable[[str, m.Message, int], object] = self._sink(rates)
            try:
                odometry = odometry_from_config(options) if device.family == "can" and cfg.processing.odometry else None
                if odometry is not None:  # /odom and odom -> base_link from the wheel states, on the driver's thread
                    sink = self.odometry[device.name] = OdometrySink(sink, odometry, name=f"{cfg.robot}/odometry")
                driver = self._make_driver(device.family, device.url, sink, options)
            except UserError as error:
                raise UserError(f"{device.family} device {device.name!r}: {error}") from None
            self.supervised.append(Supervised(device, driver, rates, cfg.supervision.restart_delay_s,
                                              cfg.supervision.max_restart_delay_s,
                                              on_crash=lambda sup: self.publish(DIAGNOSTICS_TOPIC,
                                                                                self._diagnostics())))
            for topic, msg in driver.static_messages():
                self._remember_latched(topic, msg)
        self._server = StatusServer(cfg.status.socket, self.status)  # refuses a second daemon before it logs
        folder = cfg.logger.folder
        assert folder is not None  # check_daemon_config
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise UserError(f"cannot create the log folder {folder}: {error.strerror or error}") from None
        if cfg.live.enabled:
            self.live = LiveView(cfg.live.host, cfg.live.port, name=f"trundle {cfg.robot}")
            for topic, msg in list(self._latched.items()):
                self.live(topic, msg, wall_ns())
        processing = Processing(cfg.processing, cfg.frames, self.publish, online_estimator(cfg.processing, cfg.slam))
        if processing.active:
            self.processing = processing
            for topic, msg in list(self._latched.items()):  # the drivers' static transforms and calibrations
                if processing.wants(topic, msg):
                    processing.put(topic, msg)
            processing.thread.start()
        self.disk_guard.check()
        if cfg.logger.record and not self.recording_paused:
            self._open_logger()
        self._server.start()
        for sup in self.supervised:
            sup.start()
        self.state = "running"
        sd_notify("READY=1\nSTATUS=" + self._summary())
        devices = ", ".join(f"{s.device.name} ({s.device.url})" for s in self.supervised) or "no devices"
        log = (f"recording to {self.logger.current_path}" if self.logger is not None and self.logger.current_path
               else self.recording_paused or "not recording")
        self.say(f"started (pid {os.getpid()}, robot {cfg.robot}): {devices}; {log}; "
                 f"status socket {cfg.status.socket}")
        self.started_at = time.monotonic()

    def run(self, *, install_signals: bool = True) -> int:
        """Start, then supervise until a stop is requested; always shuts down cleanly."""
        previous: dict[signal.Signals, Any] = {}
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
                # short waits: a signal handler only sets a flag (see _on_stop_signal), seen here at once
                self._wake.wait(min(SIGNAL_POLL_S, max(0.0, min(deadlines) - now)))
                self._wake.clear()
                now = time.monotonic()
                if self._split_requested:
                    self._split_requested = False
                    self.split()
                for sup in self.supervised:
                    if self._stop_requested:
                        break
                    sup.restart_if_due(now)
                if now >= next_disk:
                    next_disk = now + self.config.disk.check_period_s
                    self.disk_guard.check()
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
        """SIGTERM, SIGINT: stop. Only a flag: a handler that took the wake event's lock deadlocked
        when a second signal came while it held it (SIGTERM twice froze the daemon)."""
        self._stop_requested = True

    def _on_split_signal(self, signum: int, frame: Any) -> None:
        """SIGHUP: a new log file (a flag, as for stop)."""
        self._split_requested = True

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
            self._server.close()
            self._server = None
        if self.state == "stopping" and self.started_at is not None:   # a start that failed said why instead
            written = sum(c["written"] for c in self._stop_counts.values())
            files = ", ".join(str(p) for p in self.logger_files) or "no log"
            self.say(f"stopped after {time.monotonic() - self.started_at:.0f} s: {written} messages in {files}")
        self.state = "stopped"

    # ------------------------------------------------------------------ messages
    def _sink(self, rates: TopicRates) -> Callable[[str, m.Message, int], None]:
        """A driver's sink: count the message in the driver's ``rates``, then route it."""
        def sink(topic: str, msg: m.Message, log_time_ns: int) -> None:
            rates.count(topic)
            self._route(topic, msg, log_time_ns)
        return sink

    def publish(self, topic: str, msg: m.Message, log_time_ns: int | None = None) -> None:
        """Log a message the daemon itself produced (diagnostics, SLAM output, detections)."""
        self._route(topic, msg, wall_ns() if log_time_ns is None else log_time_ns, processed=True)

    def _route(self, topic: str, msg: m.Message, log_time_ns: int, processed: bool = False) -> None:
        """To the logger, the live view and (unless the daemon ``processed`` it) online processing;
        latched topics are merged first (runs on the drivers' threads)."""
        if is_latched(topic):
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
        """Merge every static transform into one /tf_static message (the logger keeps the last one); a
        driver's mount of a child frame the config's [[transforms]] places is left out (the config wins)."""
        with self._lock:
            if topic == TF_STATIC_TOPIC and isinstance(msg, m.TFMessage):
                self.static_frames.add_static(msg)
                self._latched[topic] = self.static_frames.static_message()
            else:
                self._latched[topic] = msg

    # ------------------------------------------------------------------ logger
    def _open_logger(self) -> None:
        """A new log named ``prefix_YYYYmmdd-HHMMSS.mcap``, starting with the latched topics."""
        cfg, folder = self.config.logger, self.config.logger.folder
        assert folder is not None  # check_daemon_config
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime())
        path = folder / f"{cfg.prefix}_{stamp}.mcap"
        n = 1
        while any(folder.glob(f"{path.stem}*")):
            path = folder / f"{cfg.prefix}_{stamp}-{n}.mcap"
            n += 1
        metadata = {"command": DAEMON_COMMAND, "robot": {"name": self.config.robot}, "config_file": self.config.source,
                    "devices": {d.name: {"family": d.family, "url": d.url, **d.options} for d in self.config.devices}}
        try:
            logger = Logger(path, compression=cfg.compression, chunk_size=cfg.chunk_size_kb * 1024,
                            flush_period_s=cfg.flush_period_s, fsync=cfg.fsync,
                            split_bytes=int(cfg.split_size_mb * 1e6) or NO_SPLIT_BYTES,
                            split_duration_s=cfg.split_duration_s or None, queue_size=cfg.queue_size,
                            metadata=metadata)
        except (OSError, UserError) as error:
            self._logger_failed(f"cannot open a log in {cfg.folder}: {error}")
            return
        for salvaged in logger.salvaged:  # crash files of a daemon or recorder that died (kill -9, power)
            print(f"trundle daemon: {salvaged.line()}", file=sys.stderr, flush=True)
        with self._lock:
            latched = list(self._latched.items())
        for topic, msg in latched:
            logger.write(topic, msg)
        self.logger = logger
        self.recording_paused = ""

    def _close_logger(self) -> None:
        """Close (and rename) the log, keeping its files and counts for the status."""
        logger, self.logger = self.logger, None
        if logger is None:
            return
        try:
            logger.close()
        except LoggerError as error:
            self.say(str(error))
        self.logger_files.extend(logger.files)
        self._stop_counts = logger.stats_dict()

    def _logger_failed(self, reason: str) -> None:
        """Pause recording for ``reason``; ``_check_logger`` retries after ``LOGGER_RETRY_S``."""
        self.logger_failures += 1
        self.recording_paused = reason
        self._logger_retry_at = time.monotonic() + LOGGER_RETRY_S
        self.say(f"recording paused: {reason}")

    def _check_logger(self, now: float) -> None:
        """Close a log that failed to write; retry a paused one when due (``now``: monotonic, s)."""
        logger = self.logger
        if logger is not None and logger.error is not None:
            reason = str(logger.error)
            self._close_logger()
            self._logger_failed(reason)
        elif (logger is None and self.config.logger.record and self.recording_paused
              and not self.disk_guard.stopped and now >= self._logger_retry_at):
            self._open_logger()

    def split(self) -> None:
        """Start a new log file now (latched topics are repeated in it)."""
        if self.logger is not None:
            self.logger.split()

    # ------------------------------------------------------------------ disk guard callbacks
    def _current_log(self) -> Path | None:
        """The file being written (the disk guard never deletes it)."""
        logger = self.logger
        return logger.current_path if logger is not None else None

    def _stop_recording(self, reason: str) -> None:
        """The disk guard's stop: close the log and say why (the reason first: a status asked while the log
        closes says why it is not recording)."""
        self.recording_paused = reason
        self._close_logger()

    def _resume_recording(self) -> None:
        """The disk guard's resume: a new log, unless starting or stopping."""
        self.recording_paused = ""
        if self.state == "running":
            self._open_logger()

    # ------------------------------------------------------------------ health and status
    def _diagnostics(self) -> m.DiagnosticArray:
        """One ``/diagnostics`` message: every device, the logger, the disk."""
        statuses = [sup.diagnostics(self.config.robot) for sup in self.supervised]
        if self.processing is not None:
            statuses.append(self.processing.diagnostics(self.config.robot))
        log = self._logger_status()
        level = m.OK if log["recording"] else m.WARN
        if not self.config.logger.record:
            level = m.OK
        message = "recording" if log["recording"] else (self.recording_paused or "not recording")
        statuses.append(m.DiagnosticStatus(level, f"{self.config.robot}/logger", message, "", tuple(
            (k, str(log[k])) for k in ("file", "size_bytes", "written", "dropped", "queue"))))
        statuses.append(self.disk_guard.diagnostics(self.config.robot))
        return m.DiagnosticArray(wall_ns(), tuple(statuses))

    def _publish_diagnostics(self, now: float) -> None:
        """Update the rates (``now``: monotonic, s), publish diagnostics, repeat latched topics to the
        live view, tell systemd the summary."""
        for sup in self.supervised:
            sup.rates.update(now)
        diagnostics = self._diagnostics()
        self.publish(DIAGNOSTICS_TOPIC, diagnostics)
        if self.state == "running":  # devices going bad or well again, one line each on stderr (the journal)
            self.health.update([s for s in diagnostics.status if not s.name.endswith(("/logger", "/disk"))], now)
        if self.live is not None:
            self.live.repeat_latched()
        sd_notify("STATUS=" + self._summary())

    def _summary(self) -> str:
        """One line for systemd's STATUS=: the logger, then each device's state."""
        parts = [f"{s.device.name} {s.state}" for s in self.supervised]
        log = "recording" if self.logger is not None else (self.recording_paused or "not recording")
        return f"{log}; " + ", ".join(parts)

    def _logger_status(self) -> dict[str, Any]:
        """The ``logger`` entry of the status answer (sizes in bytes)."""
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
        """Everything ``trundle status`` shows, as one JSON-able dict (the status server's provider)."""
        out: dict[str, Any] = {
            "daemon": {"pid": os.getpid(), "robot": self.config.robot, "state": self.state,
                       "config": self.config.source, "started_ns": self.started_ns,
                       "uptime_s": round((wall_ns() - self.started_ns) / 1e9, 1)},
            "devices": [s.status() for s in self.supervised],
            "logger": self._logger_status(),
            "disk": self.disk_guard.status,
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
