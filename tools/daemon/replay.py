"""Replay: the daemon on a log. A log's messages are played in log-time order at any rate
(:func:`trundle.logs.replay.play`) into what the daemon feeds from its drivers: the online
processing (:class:`trundle.tools.daemon.processing.Processing`, the same code), the live view
(:class:`trundle.tools.daemon.live_view.LiveView`, advertising the log's time as the server's) and
an output log with the replayed messages and the processing's results, as the daemon logs them.

At rate 0 each wanted message is processed before the next is read (nothing skipped: the result
is that of ``trundle slam``); at a real-time rate the processing runs on its own thread and takes
the newest scan when it falls behind, counting the ones it skipped, as the daemon does. The log's
own copies of the processing's outputs (``/slam/pose``, ``/map``, map -> odom on ``/tf``, ...) are
left out while the processing makes them anew. Ctrl-C ends the replay: the processing finishes and
the output log is closed complete.
"""

from __future__ import annotations

import collections
import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from trundle.logs import messages as m
from trundle.logs import ros2
from trundle.logs.errors import DataError, UsageError
from trundle.logs.frames import links
from trundle.logs.outputs import writing_file
from trundle.logs.reader import LogInfo, LogReader, RawMessage
from trundle.logs.replay import play
from trundle.logs.topics import LANDMARK_TOPIC, MAP_TOPIC, PATH_TOPIC, SLAM_POSE_TOPIC, TF_STATIC_TOPIC, TF_TOPIC
from trundle.logs.writer import Logger, is_latched
from trundle.tools.daemon.live_view import LiveView
from trundle.tools.daemon.processing import INPUT_TYPES, Processing, Publish

ProcessingFactory = Callable[[Publish, Callable[[], int]], Processing]
"""Builds a fresh Processing from its ``publish`` and ``clock`` (ns) (one per pass of a ``--loop``)."""
ProgressUpdate = Callable[[float, str], None]
"""Shows the log seconds played in this pass and a text after them."""
IMAGE_TYPES = ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image")
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry",)


@contextlib.contextmanager
def writing_output(path: str | os.PathLike[str], metadata: Mapping[str, object]) -> Iterator[Logger]:
    """The output log ``path`` (an ``.mcap`` that must not exist: never overwritten), written as the
    daemon writes its logs (``/tf_static`` latched) under the output helper's temporary name
    (:func:`trundle.logs.outputs.writing_file`): it takes its name closed and complete, and a
    failure (a read-only folder, a full disk) leaves nothing. The one place a replay's output is
    opened; the logger is closed when the block ends, Ctrl-C ignored meanwhile."""
    path = Path(path)
    if path.suffix != ".mcap":
        raise UsageError(f"output must be an .mcap file, got {path}")
    with writing_file(path) as tmp:
        logger = Logger(tmp, metadata=metadata, latched_topics=(TF_STATIC_TOPIC,), salvage=False)
        try:
            yield logger
        finally:
            with no_interrupts():
                logger.close()


def replay_window(log: str | os.PathLike[str], info: LogInfo, topics: Iterable[str] | None, start_s: float,
                  end_s: float | None) -> tuple[list[str] | None, int, int | None]:
    """The topics (None: all) and log-time window ``[start_ns, end_ns)`` for ``--topics``, ``--start``
    and ``--end`` (s after the log's first message); a filter matching no topic, a start not before
    the end, or a window without a message of those topics is a UserError."""
    wanted = None if topics is None else list(dict.fromkeys(topics))
    if wanted is not None and not set(wanted) & set(info.topics):
        raise UsageError(f"--topics {' '.join(wanted)}: no such topic in {log} "
                         f"(it has {', '.join(sorted(info.topics))})")
    if end_s is not None and start_s >= end_s:
        raise UsageError(f"--start {start_s:g} is not before --end {end_s:g}")
    t0 = info.start_ns or 0
    start_ns = t0 + round(start_s * 1e9)
    end_ns = None if end_s is None else t0 + round(end_s * 1e9)
    if next(LogReader(log).raw_messages(wanted, start_ns, end_ns), None) is None:
        window = f"{start_s:g}-{end_s:g} s" if end_s is not None else f"after {start_s:g} s"
        raise DataError(f"{log} has no message{' of those topics' if wanted else ''} {window} into the log "
                        f"(it is {info.duration_s:.1f} s long)")
    return wanted, start_ns, end_ns


def missing_inputs(info: LogInfo, processing: Processing, topics: Iterable[str] | None = None) -> list[str]:
    """What the processing needs and the log's ``topics`` (None: all) lack, in words (empty: nothing)."""
    played = {t: i for t, i in info.topics.items() if topics is None or t in set(topics)}
    types = {i.ros_type for i in played.values()}
    missing = []
    slam = processing.slam
    if slam is not None:
        scan = played.get(processing.scan_topic)
        if scan is None or scan.ros_type != "sensor_msgs/msg/LaserScan":
            missing.append(f"no scans on {processing.scan_topic} (SLAM maps nothing)")
        if not types & set(ODOMETRY_TYPES) and not (slam.wheels is not None and "sensor_msgs/msg/JointState" in types):
            missing.append("no odometry (SLAM matches the scans alone)")
    if processing.detector is not None and not types & set(IMAGE_TYPES):
        missing.append("no camera images (no markers to detect)")
    return missing


def output_topics(info: LogInfo, processing: Processing) -> list[str]:
    """The log's topics the processing makes anew (left out of the replay)."""
    made = set()
    if processing.slam is not None:
        made |= {SLAM_POSE_TOPIC, MAP_TOPIC, PATH_TOPIC}
    if processing.detector is not None:
        made |= {LANDMARK_TOPIC} | {t for t in info.topics if t.endswith(("/markers", "/marker_poses"))}
    return sorted(made & set(info.topics))


def live_channels(info: LogInfo, topics: Iterable[str] | None, processing: Processing | None) -> dict[str, str]:
    """Every topic a replay streams, with its ROS type: the log's ``topics`` (None: all) that trundle
    decodes and the ``processing``'s outputs (the live view advertises them before clients come)."""
    played = {t: i.ros_type for t, i in info.topics.items()
              if ros2.is_supported(i.ros_type) and (topics is None or t in set(topics))}
    if processing is not None:
        images = [t for t, ros_type in played.items() if ros_type in IMAGE_TYPES]
        played |= {t: ros2.ros_type(kind) for t, kind in processing.outputs(images).items()}
    return played


@dataclass
class ReplayResult:
    """What a replay did: messages per topic, seconds of log played and of wall time playing them (the
    processing's final optimisation comes after), passes, and the processing's counts (scans taken and
    skipped to keep up, messages dropped or failed)."""

    counts: collections.Counter[str] = field(default_factory=collections.Counter)
    log_s: float = 0.0
    wall_s: float = 0.0
    passes: int = 0
    interrupted: bool = False
    scans: int = 0
    skipped_scans: int = 0
    dropped: int = 0
    errors: int = 0
    last_error: str = ""
    published: collections.Counter[str] = field(default_factory=collections.Counter)

    @property
    def messages(self) -> int:
        return sum(self.counts.values())

    @property
    def rate(self) -> float:
        """The rate achieved: log seconds per wall second."""
        return self.log_s / self.wall_s if self.wall_s > 0 else 0.0


class LogReplay:
    """Play ``log`` (``topics``, ``[start_ns, end_ns)``; see :func:`replay_window`) at ``rate`` (0: as
    fast as possible), ``loop`` for ever, into a Processing from ``make_processing`` (None: none), the
    ``live`` view and the ``output`` log; ``run`` returns what it did."""

    def __init__(self, log: str | os.PathLike[str], *, rate: float = 1.0, topics: list[str] | None = None,
                 start_ns: int | None = None, end_ns: int | None = None, loop: bool = False,
                 make_processing: ProcessingFactory | None = None, live: LiveView | None = None,
                 output: Logger | None = None, map_frames: tuple[str, str] = ("map", "odom"),
                 progress: ProgressUpdate | None = None) -> None:
        self.log, self.rate, self.topics, self.loop = log, rate, topics, loop
        self.start_ns, self.end_ns = start_ns, end_ns
        self.make_processing, self.live, self.output, self.progress = make_processing, live, output, progress
        self.map_frames = map_frames
        self.processing: Processing | None = None
        self.excluded: set[str] = set()
        self.now_ns = 0  # the log time of the last message played: the processing's clock and outputs' log time
        self.result = ReplayResult()
        self._pass_start_ns: int | None = None
        self._played_s = 0.0  # log seconds played in this pass
        self._latched_before: list[RawMessage] = []  # latched topics' last messages before the window
        self._done_s = 0.0  # in the passes before
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._inputs = {ros2.ros_type(kind) for kind in INPUT_TYPES}  # the ROS types worth decoding

    def run(self) -> ReplayResult:
        """Play until the window's end (or, with ``loop``, until Ctrl-C); always finishes the processing
        and leaves the output complete."""
        result = self.result
        started = self._started = time.monotonic()
        try:
            play(self.log, self._deliver, self.rate, self.topics, self.start_ns, self.end_ns, self.loop,
                 on_pass=self._next_pass)
        except KeyboardInterrupt:
            result.interrupted = True
        finally:
            result.wall_s = time.monotonic() - started  # the playing; the processing's final work after it
            with no_interrupts():
                self._end_processing()
        return result

    def _next_pass(self, n: int) -> None:
        """Before pass ``n``: a fresh processing (the log's time starts again), then the latched topics'
        last messages before the window (the laser's mount, calibrations), as a latched publisher's
        subscriber would have them."""
        self.result.passes = n + 1
        self._done_s += self._played_s
        self._played_s = 0.0
        self._end_processing()
        if self.make_processing is not None:
            processing = self.processing = self.make_processing(self.publish, lambda: self.now_ns)
            self.excluded = set(output_topics(LogReader(self.log).info(), processing))
            if self.rate > 0:
                processing.thread.start()
        if n == 0 and self.start_ns is not None:
            latched = [t for t in LogReader(self.log).info().topics if is_latched(t)
                       and (self.topics is None or t in self.topics)]
            before = {raw.topic: raw for raw in LogReader(self.log).raw_messages(latched, None, self.start_ns)}
            self._latched_before = sorted(before.values(), key=lambda raw: raw.log_time_ns)
        for raw in self._latched_before:
            self._deliver(raw)
        self._pass_start_ns = None

    def _end_processing(self) -> None:
        processing, self.processing = self.processing, None
        if processing is None:
            return
        if self.rate > 0:
            processing.stop()
        processing.finish()
        result = self.result
        result.skipped_scans += processing.skipped_scans
        result.dropped += processing.dropped
        result.errors += processing.errors
        result.last_error = processing.last_error or result.last_error
        if processing.slam is not None:
            result.scans += processing.slam.stats.scans

    def publish(self, topic: str, msg: m.Message) -> None:
        """The processing's results: to the output and the live view, at the log time played."""
        log_time_ns = self.now_ns
        with self._lock:
            self.result.published[topic] += 1
        if self.output is not None:
            _wait_for_room(self.output)
            self.output.write(topic, msg, log_time_ns)
        if self.live is not None:
            self.live(topic, msg, log_time_ns)

    def _deliver(self, raw: RawMessage) -> None:
        t = self.now_ns = raw.log_time_ns
        if self._pass_start_ns is None:
            self._pass_start_ns = t
        processing = self.processing
        msg: m.Message | None = None
        if processing is not None:
            if raw.topic in self.excluded:
                return
            if raw.ros_type in self._inputs:
                msg = ros2.decode(raw.ros_type, raw.data)
                if self._is_map_to_odom(raw.topic, msg):
                    return
        result = self.result
        result.counts[raw.topic] += 1
        if self.output is not None:
            _wait_for_room(self.output)
            self.output.write_encoded(raw.topic, raw.ros_type, raw.data, t, raw.publish_time_ns)
        if self.live is not None:
            self.live.send(raw.topic, raw.ros_type, raw.data, t)
            self.live.set_time(t)
        if processing is not None and msg is not None and processing.wants(raw.topic, msg):
            if self.rate > 0:
                processing.put(raw.topic, msg)
            else:
                processing.handle(raw.topic, msg)
        self._played_s = (t - self._pass_start_ns) * 1e-9
        result.log_s = self._done_s + self._played_s
        if self.progress is not None:
            wall = time.monotonic() - self._started
            rate = f"{result.log_s / wall:.2f}x" if wall > 0 else "-"
            self.progress(self._played_s, f"log {self._played_s:.1f} s, wall {wall:.1f} s, rate {rate}")

    def _is_map_to_odom(self, topic: str, msg: m.Message) -> bool:
        """A map -> odom transform on /tf: the log's own SLAM output."""
        return (topic == TF_TOPIC and isinstance(msg, m.TFMessage) and self.processing is not None
                and self.processing.slam is not None and links(msg) == {self.map_frames})


def _wait_for_room(logger: Logger) -> None:
    """Wait while the logger's queue is half full: a replay's output is complete, never dropped."""
    while logger.queue_length >= logger.queue_size // 2 and logger.error is None:
        time.sleep(0.001)


@contextlib.contextmanager
def no_interrupts() -> Iterator[None]:
    """Ctrl-C ignored while a replay finishes and its output is closed (a second Ctrl-C must not leave it
    half written); main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)

