"""Salvage a truncated, killed or partly corrupt MCAP log into a complete one.

Equivalent to ``mcap recover``: every intact schema, channel, message, metadata and
attachment record is copied (ids remapped) into a new file with a summary; a chunk with a
bad CRC is skipped and counted, a torn tail ends the copy.

A crash file is recovered once. The recovered log records where it came from
(``recovered_from`` in its ``trundle`` metadata: the crash file's name, size and mtime), and a
crash file trundle's logger left (``NAME.mcap.active`` whose MCAP header names trundle) is then
removed: everything readable in it is in the recovered log, and a second recovery (by the next
daemon or record start, :func:`salvage_folder`) would only write a duplicate. Any other input is
left as it is. A file a live process still writes (it holds the logger's lock) is refused.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from trundle.logs import metadata as log_metadata
from trundle.logs.errors import DataError, OutputError, UsageError, UserError
from trundle.logs.locks import writer_of
from trundle.logs.outputs import writing_file
from trundle.logs.paths import input_file
from trundle.logs.reader import LogDamage, LogReader, log_origin
from trundle.logs.writer import ACTIVE_SUFFIX, LIBRARY_PREFIX

RECOVERED_FROM = "recovered_from"  # the key in the recovered log's ``trundle`` metadata


@dataclass(frozen=True)
class RecoverResult:
    """What a copy of ``source`` salvaged: ``messages`` over ``duration_s`` (first to last log time, s),
    the chunks skipped as corrupt and what ended the copy early; ``library`` is the input's MCAP
    writer; ``removed`` the crash file removed after a recovery (None: the input is left as it was);
    ``damage`` what could not be salvaged (None: the input was intact)."""

    source: Path
    output: Path
    messages: int
    corrupt_chunks: int
    stopped_by: str
    duration_s: float = 0.0
    library: str = ""
    removed: Path | None = None
    damage: LogDamage | None = None

    def line(self) -> str:
        """One line saying what was recovered, where it went and what ended the copy."""
        corrupt = f"; skipped {self.corrupt_chunks} corrupt chunks" if self.corrupt_chunks else ""
        lost = self.damage
        if corrupt and lost is not None and lost.messages is not None and lost.seconds is not None:
            corrupt += f" ({lost.messages} messages, {lost.seconds:.2f} s of log)"
        stopped = f"; stopped by {self.stopped_by}" if self.stopped_by else ""
        removed = f"; removed the crash file {self.removed.name}" if self.removed else ""
        return (f"recovered {self.messages} messages ({self.duration_s:.1f} s) from {self.source.name} "
                f"into {self.output}{corrupt}{stopped}{removed}")


Replace = Callable[[str, str, int, bytes], "bytes | None"]  # topic, schema name, log time ns, data


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> RecoverResult:
    """Copy every readable record of ``src`` into a complete MCAP at ``dst``, which records
    ``recovered_from``; then remove ``src`` if it is trundle's crash file (see the module doc).

    A folder ``dst`` gets the file under the input's name (without ``.active``). Raises
    ``UserError`` when a live process still writes ``src`` (nothing is written then),
    ``DataError`` when ``src`` is not MCAP or nothing at all could be read, ``UsageError`` when
    ``dst`` is ``src`` and ``UserError`` when ``dst`` exists (a file is never overwritten);
    nothing is left behind then.
    """
    src, dst = input_file(src, "MCAP log"), Path(dst)
    live = writer_of(src)
    if live is not None:
        final = src.name.removesuffix(ACTIVE_SUFFIX) if is_crash_file(src) else src.name
        raise UserError(f"{src} is still being written by {live}: it becomes {final} when that process "
                        "closes it, there is nothing to recover (nothing written)")
    if dst.is_dir():
        name = src.name.removesuffix(ACTIVE_SUFFIX)
        dst = dst / (name if name.endswith(".mcap") else name + ".mcap")
    origin = _identity(src)
    result = copy_log(src, dst, metadata={log_metadata.RECORD: {RECOVERED_FROM: json.dumps(origin, sort_keys=True)}})
    if is_crash_file(src) and result.library.startswith(LIBRARY_PREFIX) and _identity(src) == origin:
        src.unlink()
        result = dataclasses.replace(result, removed=src)
    return result


def is_crash_file(path: Path) -> bool:
    """True for the name the logger gives a file while writing it (``NAME.mcap.active``)."""
    return path.name.endswith(".mcap" + ACTIVE_SUFFIX)


def _identity(path: Path) -> dict[str, object]:
    """What ``recovered_from`` records of a crash file: its name, size (bytes) and mtime (ns)."""
    st = path.stat()
    return {"name": path.name, "size_bytes": st.st_size, "mtime_ns": st.st_mtime_ns}


def _output_names(src: Path) -> tuple[Path, ...]:
    """Where a recovery of ``src`` goes by default, in order of preference: ``X.mcap`` for the crash
    file ``X.mcap.active``, then ``X.recovered.mcap``."""
    recovered = src.with_name(f"{src.name.split('.mcap')[0]}.recovered.mcap")
    return (src.with_name(src.name.removesuffix(ACTIVE_SUFFIX)), recovered) if is_crash_file(src) else (recovered,)


def default_output(src: Path) -> Path:
    """The first of :func:`_output_names` that does not exist yet (else the last: refused as taken)."""
    names = _output_names(src)
    return next((name for name in names if not name.exists()), names[-1])


def recovered_into(active: Path) -> Path | None:
    """The log that already holds ``active``'s content (a recovery whose removal of the crash file
    did not happen), looked for under the names a recovery gives it; None if there is none."""
    origin = _identity(active)
    for candidate in _output_names(active):
        if not candidate.is_file():
            continue
        try:
            _, meta = log_origin(candidate)
        except DataError:
            continue
        if meta.fields.get(RECOVERED_FROM) == origin:
            return candidate
    return None


def _logger_started(path: Path) -> bool:
    """True when the MCAP header of ``path`` names trundle's logger (a crash file trundle wrote)."""
    try:
        with open(path, "rb") as f:
            header = next(StreamReader(f).records, None)
    except Exception:  # noqa: BLE001 -- OSError, mcap, struct, each its own kind: not a log trundle started
        return False
    return isinstance(header, Header) and header.library.startswith(LIBRARY_PREFIX)


def salvage_folder(folder: Path) -> list[RecoverResult]:
    """Recover every crash file trundle's logger left in ``folder`` (``*.mcap.active`` that no live
    process holds) to its :func:`default_output` and remove it; a crash file already recovered, one
    another program wrote and one nothing can be read from are left alone. Returns what was
    recovered, one result per crash file."""
    recovered = []
    for active in sorted(folder.glob("*.mcap" + ACTIVE_SUFFIX)):
        if writer_of(active) is not None or recovered_into(active) is not None or not _logger_started(active):
            continue
        try:
            result = recover(active, default_output(active))
        except (DataError, UserError, OutputError):  # nothing readable, the target appeared, or a full disk
            continue
        recovered.append(result)
    return recovered


def copy_log(src: str | os.PathLike[str], dst: str | os.PathLike[str], replace: Replace | None = None,
             metadata: dict[str, dict[str, str]] | None = None) -> RecoverResult:
    """Copy every readable record of ``src`` to the new file ``dst`` (as :func:`recover`), passing each
    message through ``replace(topic, schema_name, log_time_ns, data)``, which returns the data to write
    or None to drop it; ``metadata`` records (name -> key -> value) are added, their keys merged into
    ``src``'s record of the same name when it has one."""
    reader = LogReader(src)
    dst = Path(dst)
    if dst.resolve() == reader.path.resolve():
        raise UsageError("the output must be a different file from the input")
    with writing_file(dst, "output log") as tmp:
        copied = _copy(reader, tmp, replace, metadata)
        if copied.messages == 0 and not copied.channels:
            raise DataError(f"nothing could be recovered from {src}: {reader.last_scan_error or 'no messages'}")
    span = (copied.last_ns - copied.first_ns) * 1e-9 if copied.messages else 0.0
    return RecoverResult(reader.path, dst, copied.messages, reader.last_scan_corrupt_chunks, reader.last_scan_error,
                         span, copied.library, damage=reader.last_damage)


@dataclass
class _Copied:
    """What :func:`_copy` wrote: messages, the channel ids used, the input's MCAP library and the
    first and last message log times (ns)."""

    messages: int = 0
    channels: int = 0
    library: str = ""
    first_ns: int = 0
    last_ns: int = 0


def _copy(reader: LogReader, tmp: Path, replace: Replace | None,
          metadata: dict[str, dict[str, str]] | None) -> _Copied:
    """Copy every readable record of ``reader``'s file into a complete MCAP at ``tmp`` (messages through
    ``replace``, ``metadata`` merged or added)."""
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    pending_channels: dict[int, Channel] = {}
    schemas: dict[int, Schema] = {}
    extra = dict(metadata or {})
    copied = _Copied()
    first_ns, last_ns = 1 << 64, -1
    header_written = False
    with open(tmp, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        for record in reader.records():
            if not header_written:
                header = getattr(record, "profile", None)
                copied.library = getattr(record, "library", "")
                writer.start(profile=header if header is not None else "ros2",
                             library=copied.library or "trundle recover")
                header_written = True
                if header is not None:
                    continue
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                pending_channels[record.id] = record
            elif isinstance(record, Message):
                channel = pending_channels.get(record.channel_id)
                new_id = channel_ids.get(record.channel_id)
                if new_id is None:
                    if channel is None:
                        continue
                    new_id = channel_ids[record.channel_id] = _register(writer, channel, schemas, schema_ids)
                data = record.data
                if replace is not None and channel is not None:
                    schema = schemas.get(channel.schema_id)
                    replaced = replace(channel.topic, schema.name if schema else "", record.log_time, record.data)
                    if replaced is None:
                        continue
                    data = replaced
                writer.add_message(new_id, record.log_time, data, record.publish_time, record.sequence)
                copied.messages += 1
                first_ns, last_ns = min(first_ns, record.log_time), max(last_ns, record.log_time)
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, {**record.metadata, **extra.pop(record.name, {})})
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name,
                                      record.media_type, record.data)
        if not header_written:
            writer.start(profile="ros2", library="trundle recover")
        for name, values in extra.items():
            writer.add_metadata(name, values)
        writer.finish()
    copied.channels = len(channel_ids)
    if copied.messages:
        copied.first_ns, copied.last_ns = first_ns, last_ns
    return copied


def _register(writer: Writer, channel: Channel, schemas: dict[int, Schema], schema_ids: dict[int, int]) -> int:
    schema_id = 0
    if channel.schema_id:
        schema_id = schema_ids.get(channel.schema_id, 0)
        schema = schemas.get(channel.schema_id)
        if not schema_id and schema is not None:
            schema_id = schema_ids[channel.schema_id] = writer.register_schema(
                schema.name, schema.encoding, schema.data
            )
    return writer.register_channel(channel.topic, channel.message_encoding, schema_id, dict(channel.metadata))
