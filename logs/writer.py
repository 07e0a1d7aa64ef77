"""Crash-safe MCAP logger: one writer thread behind a bounded queue.

Files are MCAP with the ``ros2`` profile, ``ros2msg`` schemas (full definition text) and CDR
messages, so ``ros2 bag`` and Foxglove open them. While open a file is ``NAME.mcap.active``;
a clean close renames it to ``NAME.mcap``. The open chunk is flushed at least every
``flush_period_s`` (optionally fsynced), so a killed process loses at most that much. The writer
thread wakes once per ``batch_s`` at most while messages flow (a message wakes it, it lets the
batch gather, then writes them all), not once per message. Files split
by size and/or duration; latched topics (``/tf_static``, ``*/camera_info`` and any named) are
repeated at the start of every split. Each topic counts messages written and dropped.
An ``.active`` file is ``flock``ed while written, so a live writer is known for sure
(:mod:`trundle.logs.locks`); a new logger recovers the crash files dead ones left in its folder
(:func:`trundle.logs.recover.salvage_folder`, ``Logger.salvaged``).
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import glob
import os
import platform
import struct
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, NamedTuple

from mcap.writer import CompressionType, Writer

from trundle import __version__
from trundle.logs import messages as m
from trundle.logs import metadata as log_metadata
from trundle.logs import ros2
from trundle.logs.errors import OutputError, UserError
from trundle.logs.outputs import PARTIAL_SUFFIX
from trundle.logs.topics import TF_STATIC_TOPIC

if TYPE_CHECKING:
    from trundle.logs.recover import RecoverResult

ACTIVE_SUFFIX = ".active"
LIBRARY_PREFIX = "trundle/"  # the MCAP header's library, before the version: marks a log this logger wrote
_SPLIT = object()  # queued by Logger.split: the writer starts a new file at the next message
COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

_QOS_LATCHED = (
    "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
    "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n"
    "  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  avoid_ros_namespace_conventions: false\n")
_QOS_VOLATILE = _QOS_LATCHED.replace("durability: 1", "durability: 2").replace("depth: 1", "depth: 10")
# MCAP record sizes (MCAP spec, records section), for keeping split files under their size limit:
MESSAGE_RECORD_BYTES = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel id, sequence, log and publish time
MESSAGE_INDEX_ENTRY_BYTES = 8 + 8  # each message's (log time, offset) in its chunk's message index
MESSAGE_INDEX_BYTES = 1 + 8 + 2 + 4  # a message index record (one per channel and chunk), entries aside
CHUNK_RECORD_BYTES = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 8 + 4 + 8  # chunk header with a compression name
CHUNK_INDEX_BYTES = 1 + 8 + 8 + 8 + 8 + 8 + 4 + 8 + 4 + 4 + 8 + 8  # + 10 per channel
SUMMARY_FIXED_BYTES = 1024  # statistics, data end, summary offsets, metadata index, footer, magic


class LoggerError(OutputError):
    """The logger could not write (disk full, file size limit, permissions): it has stopped."""


def is_latched(topic: str, extra: Iterable[str] = ()) -> bool:
    """Topics whose last message must be present in every file (ROS transient-local)."""
    return topic == TF_STATIC_TOPIC or topic.endswith("camera_info") or topic in extra


@dataclass
class TopicStats:
    written: int = 0
    dropped: int = 0


class _Item(NamedTuple):
    """One queued message (a tuple: cheap to build on the producer's thread)."""

    topic: str
    ros_type: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    latch_key: str = ""


@dataclass
class _OpenFile:
    path: Path
    stream: IO[bytes]
    writer: Writer
    channels: dict[str, int] = field(default_factory=dict)
    schemas: dict[str, int] = field(default_factory=dict)
    sequence: dict[str, int] = field(default_factory=dict)
    first_log_time_ns: int | None = None
    open_chunk_bytes: int = 0  # records in the chunk not yet written to the stream (uncompressed)
    chunks: int = 0
    summary_bytes: int = SUMMARY_FIXED_BYTES  # what finishing the file adds: summary, footer

    @property
    def active_path(self) -> Path:
        return self.path.with_name(self.path.name + ACTIVE_SUFFIX)

    def finished_size(self, extra: int = 0) -> int:
        """An upper bound on the file's size if it were finished after ``extra`` more bytes of records
        (the open chunk counted uncompressed, with its record, message indexes and chunk index)."""
        pending = self.open_chunk_bytes + extra
        if pending:
            pending += CHUNK_RECORD_BYTES + CHUNK_INDEX_BYTES + (MESSAGE_INDEX_BYTES + 10) * len(self.channels)
        return self.stream.tell() + pending + self.summary_bytes


class Logger:
    """Write messages to MCAP from any thread; never blocks the caller.

    ``write`` returns False (and counts a drop for that topic) when the queue is full or the
    logger has failed. ``error`` holds the first write failure; ``close`` raises it.
    ``metadata`` is the log's description, stored in every file (:mod:`trundle.logs.metadata`).
    With ``salvage``, leftover ``.active`` files of the folder are recovered first: ``salvaged``
    lists the files written, ``salvage_damage`` what could not be salvaged from each damaged one.
    """

    def __init__(self, path: str | os.PathLike[str], *, compression: str = "zstd",
                 chunk_size: int = 1 << 20, flush_period_s: float = 0.5, fsync: bool = False,
                 split_bytes: int | None = None, split_duration_s: float | None = None,
                 queue_size: int = 10000, metadata: Mapping[str, object] | None = None,
                 latched_topics: Iterable[str] = (), salvage: bool = True, batch_s: float = 0.1) -> None:
        if compression not in COMPRESSION:
            raise UserError(f"unknown compression {compression!r} (choose zstd, lz4 or none)")
        self.base_path = Path(path)
        if self.base_path.suffix not in (".mcap", PARTIAL_SUFFIX):  # a .partial is an output's temporary name
            self.base_path = self.base_path.with_name(self.base_path.name + ".mcap")
        if not self.base_path.parent.is_dir():
            raise UserError(f"output folder does not exist: {self.base_path.parent}")
        self.compression = compression
        self.chunk_size = chunk_size
        self.flush_period_s = flush_period_s
        self.fsync = fsync
        self.split_bytes = split_bytes
        self.split_duration_ns = int(split_duration_s * 1e9) if split_duration_s else None
        self._splitting = bool(split_bytes or split_duration_s)
        self.queue_size = queue_size
        self.batch_s = batch_s
        self._urgent_at = max(1, min(queue_size // 4, 256))  # a batch this long is written at once
        self.metadata = log_metadata.encode(
            {"trundle_version": __version__, "host": platform.node(), **(metadata or {})}
        )
        self.latched_topics = frozenset(latched_topics)
        from trundle.logs.recover import salvage_folder  # recover reads this module's names

        self.stats: dict[str, TopicStats] = collections.defaultdict(TopicStats)
        self.files: list[Path] = []
        # crash files other (dead) loggers left here, each recovered once (trundle.logs.recover)
        self.salvaged: list[RecoverResult] = salvage_folder(self.base_path.parent) if salvage else []
        taken = self._taken()
        if taken:
            raise UserError(f"{taken[0]} exists: give another name, or move it away (a log is never overwritten)")
        self.error: LoggerError | None = None
        self.bad_messages = 0  # messages MCAP could not hold (counted as drops of their topic too)
        self.last_bad_message = ""
        self._latched: dict[str, _Item] = {}
        self._topic_latched: dict[str, bool] = {}
        self._queue: collections.deque = collections.deque()  # _Item, _SPLIT, or None to close
        self._wake = threading.Event()
        self._urgent = threading.Event()
        self._split_requested = False
        self._closed = False
        self._split_index = 0
        self._file: _OpenFile | None = None
        self._lock = threading.Lock()
        self._open_next()
        self._thread = threading.Thread(target=self._run, name="mcap-logger", daemon=True)
        self._thread.start()

    def _taken(self) -> list[Path]:
        """Files this logger would write that exist already (the base name, or any split part)."""
        base = self.base_path
        names = [base, base.with_name(base.name + ACTIVE_SUFFIX)]
        taken = [p for p in names if p.exists() or p.is_symlink()]
        if self._splitting:
            taken += sorted(base.parent.glob(glob.escape(base.stem) + "_[0-9]*.mcap*"))
        return taken

    # --- producer side -------------------------------------------------------------------------

    def write(self, topic: str, msg: m.Message, log_time_ns: int | None = None) -> bool:
        """Queue a message; ``log_time_ns`` is the receive time (default: now)."""
        ros_type, data = ros2.encode(msg)
        stamp = getattr(msg, "stamp_ns", None)
        log_time = time.time_ns() if log_time_ns is None else int(log_time_ns)
        if not 0 <= log_time < 1 << 64:
            raise ValueError(f"log time {log_time} ns of a {topic} message is outside MCAP's unsigned 64-bit range")
        if stamp is not None and not 0 <= stamp < 1 << 64:  # e.g. a device clock near zero minus a sweep time
            stamp = None  # the publish time is then the log time (the message keeps its own stamp)
        # Static transforms from several publishers are all kept for the next split, one per
        # set of child frames, as tf2's transient-local subscribers would see them.
        key = topic + "|" + ",".join(sorted(t.child_frame_id for t in msg.transforms)) \
            if isinstance(msg, m.TFMessage) else topic
        return self._put(_Item(topic, ros_type, data, log_time, log_time if stamp is None else int(stamp), key))

    __call__ = write

    def write_encoded(self, topic: str, ros_type: str, data: bytes, log_time_ns: int,
                      publish_time_ns: int | None = None) -> bool:
        """Queue CDR bytes of ``ros_type`` already encoded (e.g. copied from another log)."""
        return self._put(_Item(topic, ros_type, data if isinstance(data, bytes) else bytes(data), int(log_time_ns),
                               int(log_time_ns if publish_time_ns is None else publish_time_ns)))

    def _put(self, item: _Item) -> bool:
        if self._closed or self.error is not None or len(self._queue) >= self.queue_size:
            self.stats[item.topic].dropped += 1
            return False
        self._queue.append(item)
        if not self._wake.is_set():
            self._wake.set()
        elif len(self._queue) >= self._urgent_at and not self._urgent.is_set():
            self._urgent.set()
        return True

    def split(self) -> None:
        """Start a new file at the next message (as SIGHUP does in the daemon); the messages
        queued before the request still go to the current file."""
        self._queue.append(_SPLIT)
        self._wake.set()
        self._urgent.set()

    def close(self) -> None:
        """Write everything queued, finish the file and rename it; raises the first write error."""
        if not self._closed:
            self._closed = True
            self._queue.append(None)
            self._wake.set()
            self._urgent.set()
            self._thread.join()
        if self.error is not None:
            raise self.error

    @property
    def current_path(self) -> Path | None:
        file = self._file
        return file.active_path if file else None

    @property
    def queue_length(self) -> int:
        return len(self._queue)

    def __enter__(self) -> Logger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- writer thread -------------------------------------------------------------------------

    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_period_s
        running = True
        while running:
            self._wake.wait(max(0.0, next_flush - time.monotonic()))
            if self._wake.is_set():  # let the batch gather: producers do not wake a woken writer
                self._urgent.wait(max(0.0, min(self.batch_s, next_flush - time.monotonic())))
            self._urgent.clear()
            self._wake.clear()
            running = self._drain()
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_period_s
                self._guard(self._flush)
        self._guard(self._finish_file)

    def _drain(self) -> bool:
        """Write everything queued; False once the close sentinel is reached."""
        queue = self._queue
        while queue:
            item = queue.popleft()
            if item is None:
                return False
            if item is _SPLIT:
                self._split_requested = True
                continue
            if self.error is None:
                try:
                    self._write_item(item)
                    continue
                except OSError as error:
                    self._fail(error)
                except (ValueError, struct.error) as error:  # one message MCAP cannot hold: dropped, counted
                    self.bad_messages += 1
                    self.last_bad_message = f"{item.topic}: {error}"
            self.stats[item.topic].dropped += 1
        return True

    def _guard(self, action) -> None:
        """Run a flush or finish step unless failed; an OSError stops the logger."""
        if self.error is None:
            try:
                action()
            except OSError as error:
                self._fail(error)

    def _fail(self, error: OSError) -> None:
        where = self._file.active_path if self._file else self.base_path
        self.error = LoggerError(f"cannot write {where}: {error.strerror or error}; "
                                 f"the file keeps what was flushed (trundle recover {where})", str(where), error)
        self._file = None

    def _write_item(self, item: _Item) -> None:
        file = self._file
        assert file is not None
        if self._split_requested or (self._splitting and self._needs_split(file, item)):
            self._split_requested = False
            self._finish_file()
            self._open_next()
            file = self._file
            assert file is not None
            file.first_log_time_ns = item.log_time_ns
            for key, latched in list(self._latched.items()):
                if key != (item.latch_key or item.topic):  # re-logged at the split time, publish time kept
                    self._add(file, latched._replace(log_time_ns=item.log_time_ns))
        latched_topic = self._topic_latched.get(item.topic)
        if latched_topic is None:
            latched_topic = self._topic_latched[item.topic] = is_latched(item.topic, self.latched_topics)
        if latched_topic:
            self._latched[item.latch_key or item.topic] = item
        self._add(file, item)
        self.stats[item.topic].written += 1

    def _needs_split(self, file: _OpenFile, item: _Item) -> bool:
        if file.first_log_time_ns is None:
            return False
        if self.split_duration_ns and item.log_time_ns - file.first_log_time_ns >= self.split_duration_ns:
            return True
        # the file as it would be finished with this message in it: split before it would pass the limit
        extra = MESSAGE_RECORD_BYTES + MESSAGE_INDEX_ENTRY_BYTES + len(item.data)
        if not self.split_bytes:
            return False
        return file.finished_size(extra) > self.split_bytes

    def _add(self, file: _OpenFile, item: _Item) -> None:
        channel = file.channels.get(item.topic)
        if channel is None:
            schema = file.schemas.get(item.ros_type)
            if schema is None:
                text = ros2.schema_text(item.ros_type).encode()
                schema = file.writer.register_schema(item.ros_type, "ros2msg", text)
                file.schemas[item.ros_type] = schema
                file.summary_bytes += 2 * (len(text) + len(item.ros_type) + 32)  # in the data and the summary
            qos = _QOS_LATCHED if is_latched(item.topic, self.latched_topics) else _QOS_VOLATILE
            channel = file.writer.register_channel(item.topic, "cdr", schema, {"offered_qos_profiles": qos})
            file.channels[item.topic] = channel
            file.summary_bytes += 2 * (len(item.topic) + len(qos) + 64)
        sequence = file.sequence.get(item.topic, 0)
        file.sequence[item.topic] = sequence + 1
        file.writer.add_message(channel, item.log_time_ns, item.data, item.publish_time_ns, sequence)
        file.open_chunk_bytes += MESSAGE_RECORD_BYTES + MESSAGE_INDEX_ENTRY_BYTES + len(item.data)
        if file.open_chunk_bytes > self.chunk_size:  # the writer closed the chunk (it does past chunk_size)
            self._chunk_written(file)
        if file.first_log_time_ns is None:
            file.first_log_time_ns = item.log_time_ns

    def _chunk_written(self, file: _OpenFile) -> None:
        """The open chunk went to the stream: its index joins the summary."""
        file.open_chunk_bytes = 0
        file.chunks += 1
        file.summary_bytes += CHUNK_INDEX_BYTES + 10 * len(file.channels)

    def _flush(self) -> None:
        file = self._file
        if file is None:
            return
        if file.open_chunk_bytes:
            self._chunk_written(file)
        file.writer.flush()
        if self.fsync:
            os.fsync(file.stream.fileno())

    def _open_next(self) -> None:
        if self._splitting or self._split_index > 0:  # numbered parts; a first unsplit file keeps NAME
            path = self.base_path.with_name(f"{self.base_path.stem}_{self._split_index}.mcap")
        else:
            path = self.base_path
        self._split_index += 1
        active = path.with_name(path.name + ACTIVE_SUFFIX)
        # exclusive: never truncates another writer's file; closed by _finish_file, not here
        stream = open(active, "xb")  # noqa: SIM115  the file outlives this method
        try:
            # marks the file live (trundle.logs.locks) until closed; blocking: a reader checking the lock
            # holds it for a moment
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX)
            writer = Writer(stream, chunk_size=self.chunk_size, compression=COMPRESSION[self.compression])
            writer.start(profile="ros2", library=f"{LIBRARY_PREFIX}{__version__}")
            writer.add_metadata(log_metadata.RECORD, self.metadata)
            stream.flush()  # the header is on disk from the start: even an early kill leaves MCAP
        except BaseException:  # e.g. a full disk: no header, so nothing to recover; the empty file goes
            with contextlib.suppress(OSError):
                stream.close()
            active.unlink(missing_ok=True)
            raise
        self._file = _OpenFile(path, stream, writer)

    def _finish_file(self) -> None:
        file = self._file
        if file is None:
            return
        self._file = None
        file.writer.finish()
        if self.fsync:
            file.stream.flush()
            os.fsync(file.stream.fileno())
        file.stream.close()
        os.replace(file.active_path, file.path)
        self.files.append(file.path)

    def stats_dict(self) -> dict[str, dict[str, int]]:
        """Per-topic ``{"written": n, "dropped": n}`` (for status and diagnostics)."""
        return {topic: {"written": s.written, "dropped": s.dropped} for topic, s in sorted(self.stats.items())}
