"""Read trundle (and any ROS 2) MCAP logs, salvaging what a crash or corruption left.

Reading is one linear pass over the records, chunk by chunk, so a file with no summary (a
killed recorder's ``.active`` file), a truncated tail or a chunk with a bad CRC still yields
every intact message: the bad chunk is counted and skipped, the truncated tail ends the pass.
Messages come out in log-time order (merged across chunks).
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk

from trundle.logs.errors import DataError
from trundle.logs.metadata import LogMetadata, read_metadata
from trundle.logs.paths import input_file

if TYPE_CHECKING:
    from trundle.logs import messages as m

MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class RawMessage:
    """A message as stored: CDR bytes of ``ros_type`` on ``topic``."""

    topic: str
    ros_type: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


@dataclass(frozen=True)
class LogMessage:
    """A decoded message with its topic and receive (log) time."""

    topic: str
    log_time_ns: int
    msg: m.Message


@dataclass
class TopicInfo:
    """One topic of a log: its schema name, message encoding (``cdr``, ``json``, ...), counts and times."""

    ros_type: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    latched: bool = False
    encoding: str = "cdr"

    @property
    def rate_hz(self) -> float:
        """Mean message rate between the first and last message (0 for fewer than two)."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return 0.0
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass
class LogInfo:
    """What ``trundle info`` shows: like ``ros2 bag info`` plus salvage details."""

    path: Path
    size_bytes: int
    profile: str = ""
    library: str = ""
    compression: set[str] = field(default_factory=set)
    message_count: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    chunks: int = 0
    corrupt_chunks: int = 0
    complete: bool = True
    error: str = ""
    topics: dict[str, TopicInfo] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) * 1e-9

    def topic_list(self) -> str:
        """The log's topics for a message naming them: ``"/odom, /scan"`` (``"none"`` for none)."""
        return ", ".join(sorted(self.topics)) or "none"

    def require(self, topic: str, ros_type: str) -> TopicInfo:
        """The topic a job needs, of ``ros_type``; a DataError saying whether it is missing or of another type."""
        found = self.topics.get(topic)
        if found is None:
            raise DataError(f"{self.path} has no topic {topic} ({ros_type}; topics: {self.topic_list()})")
        if found.ros_type != ros_type:
            raise DataError(f"{self.path}: {topic} carries {found.ros_type or 'messages without a schema'}, "
                            f"not {ros_type}")
        return found


@dataclass
class _Scan:
    """State of one linear pass: ids seen, counters, the error that ended it."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    header: Header | None = None
    statistics: Statistics | None = None
    chunks: int = 0
    corrupt_chunks: int = 0
    compression: set[str] = field(default_factory=set)
    footer_seen: bool = False
    error: str = ""


class LogReader:
    """Typed, time-windowed iteration over an MCAP log; salvages damaged files."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = input_file(path, "MCAP log")
        self.size_bytes = self.path.stat().st_size
        if self.size_bytes == 0:
            raise DataError(f"{self.path} is empty (0 bytes): no log was written into it")
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise DataError(f"{self.path} is not an MCAP file (bad magic bytes)")
        self._last_scan: _Scan | None = None

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    # --- the linear pass -------------------------------------------------------------------

    def _records(self, scan: _Scan, window: tuple[int | None, int | None] = (None, None)) -> Iterator[object]:
        """Schema/Channel/Message/Metadata/Attachment records in file order, chunks opened.

        A Chunk record is yielded (before its contents) so callers can order by its start time;
        chunks outside ``window`` are skipped without decompression.
        """
        start_ns, end_ns = window
        with open(self.path, "rb") as f:
            # Chunks hold the Schema/Channel records too: skipping one by time is safe only when
            # the summary already told us every channel.
            can_skip = (start_ns is not None or end_ns is not None) and self._load_summary_channels(f, scan)
            f.seek(0)
            stream = StreamReader(f, emit_chunks=True, record_size_limit=1 << 32)
            try:
                for record in stream.records:
                    if isinstance(record, Chunk):
                        scan.chunks += 1
                        scan.compression.add(record.compression or "none")
                        if can_skip and ((start_ns is not None and record.message_end_time < start_ns) or (
                                end_ns is not None and record.message_start_time >= end_ns)):
                            continue
                        try:
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception as error:  # zstd, lz4 and mcap each raise their own kinds
                            scan.corrupt_chunks += 1
                            scan.error = scan.error or f"corrupt chunk skipped: {type(error).__name__}"
                            continue
                        yield record
                        for item in inner:
                            self._note(scan, item)
                            yield item
                    else:
                        self._note(scan, record)
                        yield record
                scan.footer_seen = True
            except Exception as error:  # a torn or garbage tail: keep what came before it
                scan.error = f"{type(error).__name__} after {scan.chunks} chunks" + (
                    f" ({error})" if str(error) else "")

    @staticmethod
    def _load_summary_channels(f: BinaryIO, scan: _Scan) -> bool:
        """Fill ``scan`` with the summary's schemas and channels; False when there is no summary."""
        try:
            summary = SeekingReader(f).get_summary()
        except Exception:  # no or damaged footer: a linear pass must see every chunk
            return False
        if summary is None:
            return False
        scan.schemas.update(summary.schemas)
        scan.channels.update(summary.channels)
        return True

    @staticmethod
    def _note(scan: _Scan, record: object) -> None:
        if isinstance(record, Schema):
            scan.schemas[record.id] = record
        elif isinstance(record, Channel):
            scan.channels[record.id] = record
        elif isinstance(record, Header):
            scan.header = record
        elif isinstance(record, Statistics):
            scan.statistics = record

    # --- public API --------------------------------------------------------------------------

    def raw_messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                     end_ns: int | None = None) -> Iterator[RawMessage]:
        """Stored messages in log-time order, filtered by topic and ``start_ns <= t < end_ns``."""
        wanted = set(topics) if topics is not None else None
        scan = _Scan()
        self._last_scan = scan
        heap: list[tuple[int, int, RawMessage]] = []
        order = 0
        for record in self._records(scan, (start_ns, end_ns)):
            if isinstance(record, Chunk):
                while heap and heap[0][0] < record.message_start_time:
                    yield heapq.heappop(heap)[2]
            elif isinstance(record, Message):
                channel = scan.channels.get(record.channel_id)
                if channel is None or (wanted is not None and channel.topic not in wanted):
                    continue
                t = record.log_time
                if (start_ns is not None and t < start_ns) or (end_ns is not None and t >= end_ns):
                    continue
                schema = scan.schemas.get(channel.schema_id)
                raw = RawMessage(channel.topic, schema.name if schema else "", t, record.publish_time,
                                 record.sequence, record.data)
                order += 1
                heapq.heappush(heap, (t, order, raw))
        while heap:
            yield heapq.heappop(heap)[2]

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[LogMessage]:
        """Decoded messages of the types trundle maps, in log-time order; others are skipped."""
        from trundle.logs import ros2  # numpy and the rosbags typestore: only to decode (not for info)

        for raw in self.raw_messages(topics, start_ns, end_ns):
            if ros2.is_supported(raw.ros_type):
                yield LogMessage(raw.topic, raw.log_time_ns, ros2.decode(raw.ros_type, raw.data))

    def records(self) -> Iterator[object]:
        """Every readable record in file order (for recovery); see ``last_scan`` afterwards."""
        scan = _Scan()
        self._last_scan = scan
        for record in self._records(scan):
            if not isinstance(record, Chunk):
                yield record

    @property
    def last_scan_error(self) -> str:
        return self._last_scan.error if self._last_scan else ""

    @property
    def last_scan_corrupt_chunks(self) -> int:
        return self._last_scan.corrupt_chunks if self._last_scan else 0

    def info(self) -> LogInfo:
        """Counts, times and topics from one pass over the file (exact even for damaged files)."""
        scan = _Scan()
        info = LogInfo(self.path, self.size_bytes)
        for record in self._records(scan):
            if isinstance(record, Message):
                channel = scan.channels.get(record.channel_id)
                if channel is None:
                    continue
                topic = info.topics.get(channel.topic)
                if topic is None:
                    schema = scan.schemas.get(channel.schema_id)
                    qos = channel.metadata.get("offered_qos_profiles", "")
                    topic = info.topics[channel.topic] = TopicInfo(schema.name if schema else "",
                                                                   latched="durability: 1" in qos,
                                                                   encoding=channel.message_encoding)
                t = record.log_time
                topic.count += 1
                topic.first_ns = t if topic.first_ns is None else min(topic.first_ns, t)
                topic.last_ns = t if topic.last_ns is None else max(topic.last_ns, t)
                info.message_count += 1
                info.start_ns = t if info.start_ns is None else min(info.start_ns, t)
                info.end_ns = t if info.end_ns is None else max(info.end_ns, t)
            elif isinstance(record, Metadata):
                info.metadata[record.name] = dict(record.metadata)
        if scan.header is not None:
            info.profile, info.library = scan.header.profile, scan.header.library
        info.compression = scan.compression
        info.chunks, info.corrupt_chunks = scan.chunks, scan.corrupt_chunks
        info.complete = scan.footer_seen and not scan.corrupt_chunks
        info.error = scan.error
        return info


def log_origin(path: str | os.PathLike[str]) -> tuple[str, LogMetadata]:
    """Who wrote a closed log: its MCAP header's library and its ``trundle`` metadata, read from the
    header and the summary's metadata index only (no chunk is opened, cheap enough for a whole folder).
    A DataError when they cannot be read (not MCAP, no summary: torn or still being written)."""
    try:
        with open(path, "rb") as f:
            reader = SeekingReader(f)
            header = reader.get_header()
            if reader.get_summary() is None:
                raise DataError(f"{path} has no summary (torn or unfinished)")
            records = {record.name: dict(record.metadata) for record in reader.iter_metadata()}
    except DataError:
        raise
    except Exception as error:  # OSError, mcap, struct: each its own kind
        raise DataError(f"cannot read the header and summary of {path} ({type(error).__name__})") from None
    return header.library, read_metadata(records)


def read_messages(path: str | os.PathLike[str], topics: Iterable[str] | None = None) -> list[LogMessage]:
    """All decoded messages of ``topics`` (all mapped topics if None), in log-time order."""
    return list(LogReader(path).messages(topics))
