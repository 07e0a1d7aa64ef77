"""Read trundle (and any ROS 2) MCAP logs, salvaging what a crash or corruption left.

Reading is one linear pass over the records, chunk by chunk, so a file with no summary (a
killed recorder's ``.active`` file), a truncated tail or a chunk with a bad CRC still yields
every intact message: the bad chunk is counted and skipped, the truncated tail ends the pass.
Messages come out in log-time order (merged across chunks). What a pass skipped is a
:class:`LogDamage` (``LogReader.last_damage``, ``LogInfo.damage``): the one owner of how damage is
counted, said (one line) and recorded (``log_damage`` in reports).
"""

from __future__ import annotations

import heapq
import io
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary

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


def _plural(count: int, word: str) -> str:
    return f"{count} {word}{'' if count == 1 else 's'}"


@dataclass(frozen=True)
class LogDamage:
    """What one pass over a damaged log could not read (the log is intact when there is none).

    ``corrupt_chunks`` chunks failed their CRC or decompression and were skipped; ``torn_after_byte``
    is where the readable file ends when its records stop before the footer (None: read to the
    footer), and ``chunks_after_tear`` how many chunks the summary lists beyond it (0 when the tear
    is after the data section, None when no summary says). ``messages`` and ``seconds`` are what the
    skipped chunks held, counted where the file says it (each chunk's MessageIndex records, the
    summary's chunk index, else its statistics less the messages read: message count, and log-time
    span of the chunks in s, overlapping spans counted once), plus messages whose channel record
    was in a skipped chunk; None when nothing in the file tells. Chunks a time window leaves out on
    purpose are not damage.
    """

    path: Path
    size_bytes: int
    corrupt_chunks: int
    torn_after_byte: int | None
    chunks_after_tear: int | None
    messages: int | None
    seconds: float | None
    cause: str

    def line(self, name: str | None = None) -> str:
        """The damage in one line for a person, e.g. ``run.mcap is damaged: skipped 1 corrupt chunk
        (37 messages, 1.20 s of log)``; ``name`` is the log as the user gave it (default: its path)."""
        said = [f"skipped {_plural(self.corrupt_chunks, 'corrupt chunk')}"] if self.corrupt_chunks else []
        torn = self.torn_after_byte
        if torn is not None:
            where = f"byte {torn} of {self.size_bytes}"
            if self.chunks_after_tear is None and torn >= self.size_bytes:
                said.append(f"it stops at byte {torn} without its summary (an unfinished recording)")
            elif self.chunks_after_tear is None:
                said.append(f"skipped the unreadable rest after {where}")
            elif self.chunks_after_tear:
                said.append(f"skipped {_plural(self.chunks_after_tear, 'unreadable chunk')} after {where}")
            else:
                said.append(f"its index after {where} is unreadable (every chunk was read)")
        messages = "messages unknown" if self.messages is None else _plural(self.messages, "message")
        seconds = "seconds of log unknown" if self.seconds is None else f"{self.seconds:.2f} s of log"
        return f"{name or self.path} is damaged: {'; '.join(said)} ({messages}, {seconds})"

    def as_dict(self) -> dict[str, Any]:
        """The damage for a report's ``log_damage`` (JSON-able; unknown counts are null)."""
        return {"file": str(self.path), "size_bytes": self.size_bytes, "corrupt_chunks": self.corrupt_chunks,
                "torn_after_byte": self.torn_after_byte, "chunks_after_tear": self.chunks_after_tear,
                "messages_lost": self.messages, "seconds_lost": self.seconds, "cause": self.cause,
                "said": self.line()}


def damage_dict(damage: LogDamage | None) -> dict[str, Any] | None:
    """A report's ``log_damage``: the damage as a dict, None for an intact log."""
    return None if damage is None else damage.as_dict()


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
    damage: LogDamage | None = None

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
class _Lost:
    """A corrupt chunk: where it starts (byte), its log-time span (ns) and the message counts of the
    MessageIndex records that followed it in the file."""

    offset: int
    start_ns: int
    end_ns: int
    indexed: list[int] = field(default_factory=list)


@dataclass
class _Scan:
    """State of one linear pass: ids seen, counters, what was skipped, the error that ended it."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    header: Header | None = None
    statistics: Statistics | None = None
    summary: Summary | None = None
    chunks: int = 0
    corrupt_chunks: int = 0
    compression: set[str] = field(default_factory=set)
    footer_seen: bool = False
    data_end_seen: bool = False
    error: str = ""
    lost: list[_Lost] = field(default_factory=list)
    read: int = 0      # message records read intact
    orphans: int = 0   # of them, those whose channel record was lost
    torn_after: int | None = None
    chunk_offsets: set[int] = field(default_factory=set)   # every Chunk record the pass met (byte)
    record_ends: list[int] = field(default_factory=list)   # where each top-level record ends (byte)
    finished: bool = False
    damage: LogDamage | None = None


def _span_s(spans: list[tuple[int, int]]) -> float:
    """Seconds covered by the union of the ``(start_ns, end_ns)`` spans."""
    total, reach = 0, None
    for start, end in sorted(spans):
        if reach is None or start > reach:
            total += end - start
            reach = end
        elif end > reach:
            total += end - reach
            reach = end
    return total * 1e-9


def _index_count(f: BinaryIO, index: ChunkIndex) -> int | None:
    """The messages of the chunk ``index`` describes, from its MessageIndex records (None when they
    cannot be read as the index says they are)."""
    total, size = 0, 0
    try:
        for channel_id, offset in index.message_index_offsets.items():
            f.seek(offset)
            head = f.read(9)
            if len(head) != 9 or head[0] != Opcode.MESSAGE_INDEX:
                return None
            length = int.from_bytes(head[1:], "little")
            body = f.read(min(length, index.message_index_length))
            if len(body) != length:
                return None
            record = MessageIndex.read(ReadDataStream(io.BytesIO(body)))
            if record.channel_id != channel_id:
                return None
            total, size = total + len(record.records), size + 9 + length
    except Exception:  # mcap's own EndOfFile and struct errors on a garbled record
        return None
    return total if size == index.message_index_length else None


_CHUNK_HEAD = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 8   # a Chunk record's bytes besides its compression name and data


def _chunk_at(f: BinaryIO, index: ChunkIndex) -> bool:
    """Whether the file holds, where ``index`` says, a record of the length and times it says (its
    opcode may be overwritten; not so when the index itself was)."""
    try:
        f.seek(index.chunk_start_offset)
    except (OSError, OverflowError, ValueError):  # an offset beyond what a file can have
        return False
    head = f.read(25)
    return (len(head) == 25
            and int.from_bytes(head[1:9], "little") == index.chunk_length - 9
            and int.from_bytes(head[9:17], "little") == index.message_start_time
            and int.from_bytes(head[17:25], "little") == index.message_end_time)


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
        chunks outside ``window`` are skipped without decompression. At the end ``scan.damage``
        says what the pass could not read.
        """
        start_ns, end_ns = window
        with open(self.path, "rb") as f:
            # The summary names every channel (a corrupt chunk may hold the only Channel record) and
            # every chunk (what a torn tail held); chunks are skipped by time only when it is there.
            self._load_summary(f, scan)
            can_skip = (start_ns is not None or end_ns is not None) and scan.summary is not None
            f.seek(0)
            stream = StreamReader(f, emit_chunks=True, record_size_limit=1 << 32)
            end = len(MAGIC)   # where the last intact record ends (byte)
            lost: _Lost | None = None   # the corrupt chunk whose MessageIndex records may follow
            try:
                for record in stream.records:
                    start, end = end, f.tell()
                    scan.record_ends.append(end)
                    if isinstance(record, MessageIndex):
                        if lost is not None:
                            lost.indexed.append(len(record.records))
                        yield record
                        continue
                    lost = None
                    if isinstance(record, Chunk):
                        # where it starts, also when the reader skipped a record of unknown opcode before it
                        start = end - _CHUNK_HEAD - len(record.compression.encode()) - len(record.data)
                        scan.chunks += 1
                        scan.chunk_offsets.add(start)
                        scan.compression.add(record.compression or "none")
                        if can_skip and ((start_ns is not None and record.message_end_time < start_ns) or (
                                end_ns is not None and record.message_start_time >= end_ns)):
                            continue
                        try:
                            inner = breakup_chunk(record, validate_crc=True)
                        except Exception as error:  # zstd, lz4 and mcap each raise their own kinds
                            scan.corrupt_chunks += 1
                            scan.error = scan.error or f"corrupt chunk skipped: {type(error).__name__}"
                            lost = _Lost(start, record.message_start_time, record.message_end_time)
                            scan.lost.append(lost)
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
                scan.torn_after = end
                scan.error = f"{type(error).__name__} after {scan.chunks} chunks" + (
                    f" ({error})" if str(error) else "")
            scan.damage = self._damage(f, scan, window if can_skip else (None, None))
            scan.finished = True

    @staticmethod
    def _load_summary(f: BinaryIO, scan: _Scan) -> None:
        """Keep the summary in ``scan`` and take its schemas and channels (nothing when there is none)."""
        try:
            summary = SeekingReader(f).get_summary()
        except Exception:  # no or damaged footer: a linear pass must see every chunk
            return
        if summary is None:
            return
        scan.summary = summary
        scan.schemas.update(summary.schemas)
        scan.channels.update(summary.channels)

    def _damage(self, f: BinaryIO, scan: _Scan, window: tuple[int | None, int | None]) -> LogDamage | None:
        """What the finished pass ``scan`` skipped (None when nothing): counted from each skipped chunk's
        MessageIndex records and the summary's chunk index where they are readable.

        With a summary, a chunk it lists (in ``window``) that the pass never met is lost too: beyond a
        tear, and also a chunk that is where the summary says but was jumped over (an overwritten record
        length). The tear is then where the last intact record before the first such chunk ends."""
        indexes = scan.summary.chunk_indexes if scan.summary is not None else []
        start_ns, end_ns = window
        missed = [index for index in indexes if index.chunk_start_offset not in scan.chunk_offsets
                  and not (start_ns is not None and index.message_end_time < start_ns)
                  and not (end_ns is not None and index.message_start_time >= end_ns)
                  and ((scan.torn_after is not None
                        and index.chunk_start_offset + index.chunk_length > scan.torn_after)
                       or _chunk_at(f, index))]
        if scan.footer_seen and not scan.lost and not scan.orphans and not missed:
            return None
        by_offset = {index.chunk_start_offset: index for index in indexes}
        spans: list[tuple[int, int]] = []
        messages: int | None = scan.orphans
        seconds_known = True
        for lost in scan.lost:
            index = by_offset.get(lost.offset)
            if index is not None:
                spans.append((index.message_start_time, index.message_end_time))
                count = _index_count(f, index)
            else:
                if lost.start_ns <= lost.end_ns:
                    spans.append((lost.start_ns, lost.end_ns))
                else:
                    seconds_known = False
                count = sum(lost.indexed) if lost.indexed else None
            messages = None if messages is None or count is None else messages + count
        torn_after, after = scan.torn_after, None
        if missed:
            first = min(index.chunk_start_offset for index in missed)
            lost_at = max((end for end in scan.record_ends if end <= first), default=len(MAGIC))
            torn_after = lost_at if torn_after is None else min(torn_after, lost_at)
            after = len(missed)
            for index in missed:
                spans.append((index.message_start_time, index.message_end_time))
                count = _index_count(f, index)
                messages = None if messages is None or count is None else messages + count
        elif torn_after is not None and (scan.data_end_seen or scan.summary is not None):
            after = 0
        elif torn_after is not None:
            messages, seconds_known = None, False
        statistics = scan.summary.statistics if scan.summary is not None else None
        if messages is None and statistics is not None and window == (None, None):
            messages = statistics.message_count - (scan.read - scan.orphans)  # the whole file was read
        return LogDamage(self.path, self.size_bytes, scan.corrupt_chunks, torn_after, after, messages,
                         _span_s(spans) if seconds_known else None, scan.error)

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
        elif isinstance(record, DataEnd):
            scan.data_end_seen = True
        elif isinstance(record, Message):
            scan.read += 1
            scan.orphans += record.channel_id not in scan.channels

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

    @property
    def last_damage(self) -> LogDamage | None:
        """What the last pass skipped (None: the log is intact); only once that pass has ended."""
        if self._last_scan is None or not self._last_scan.finished:
            raise RuntimeError("last_damage is known only after a pass over the log has ended")
        return self._last_scan.damage

    def info(self) -> LogInfo:
        """Counts, times and topics from one pass over the file (exact even for damaged files)."""
        scan = _Scan()
        self._last_scan = scan
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
        info.damage = scan.damage
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
