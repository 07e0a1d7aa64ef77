"""Salvage a truncated, killed or partly corrupt MCAP log into a complete one.

Equivalent to ``mcap recover``: every intact schema, channel, message, metadata and
attachment record is copied (ids remapped) into a new file with a summary; a chunk with a
bad CRC is skipped and counted, a torn tail ends the copy.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from trundle.logs.errors import DataError, UsageError
from trundle.logs.outputs import writing_file
from trundle.logs.reader import LogDamage, LogReader


@dataclass(frozen=True)
class RecoverResult:
    """The recovered file, the messages copied into it, and what could not be salvaged (``damage``:
    None when the input was intact)."""

    output: Path
    messages: int
    corrupt_chunks: int
    stopped_by: str
    damage: LogDamage | None = None


Replace = Callable[[str, str, int, bytes], "bytes | None"]  # topic, schema name, log time ns, data


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> RecoverResult:
    """Copy every readable record of ``src`` into a complete MCAP at ``dst``.

    A folder ``dst`` gets the file under the input's name (without ``.active``). Raises
    ``DataError`` when ``src`` is not MCAP or nothing at all could be read, ``UsageError`` when
    ``dst`` is ``src`` and the logger's ``UserError`` when ``dst`` exists (a file is never
    overwritten); nothing is left behind then.
    """
    dst = Path(dst)
    if dst.is_dir():
        name = Path(src).name.removesuffix(".active")
        dst = dst / (name if name.endswith(".mcap") else name + ".mcap")
    return copy_log(src, dst)


def copy_log(src: str | os.PathLike[str], dst: str | os.PathLike[str], replace: Replace | None = None,
             metadata: dict[str, dict[str, str]] | None = None) -> RecoverResult:
    """Copy every readable record of ``src`` to the new file ``dst`` (as :func:`recover`), passing each
    message through ``replace(topic, schema_name, log_time_ns, data)``, which returns the data to write
    or None to drop it; ``metadata`` records (name -> key -> value) are added."""
    reader = LogReader(src)
    dst = Path(dst)
    if dst.resolve() == reader.path.resolve():
        raise UsageError("the output must be a different file from the input")
    with writing_file(dst, "output log") as tmp:
        count, channel_ids = _copy(reader, tmp, replace, metadata)
        if count == 0 and not channel_ids:
            raise DataError(f"nothing could be recovered from {src}: {reader.last_scan_error or 'no messages'}")
    return RecoverResult(dst, count, reader.last_scan_corrupt_chunks, reader.last_scan_error, reader.last_damage)


def _copy(reader: LogReader, tmp: Path, replace: Replace | None,
          metadata: dict[str, dict[str, str]] | None) -> tuple[int, dict[int, int]]:
    """Copy every readable record of ``reader``'s file into a complete MCAP at ``tmp`` (messages through
    ``replace``, ``metadata`` added); the messages copied and the channel ids used."""
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    pending_channels: dict[int, Channel] = {}
    schemas: dict[int, Schema] = {}
    count = 0
    header_written = False
    with open(tmp, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        for record in reader.records():
            if not header_written:
                header = getattr(record, "profile", None)
                writer.start(profile=header if header is not None else "ros2",
                             library=getattr(record, "library", "trundle recover"))
                header_written = True
                for name, values in (metadata or {}).items():
                    writer.add_metadata(name, values)
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
                count += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name,
                                      record.media_type, record.data)
        if not header_written:
            writer.start(profile="ros2", library="trundle recover")
        writer.finish()
    return count, channel_ids


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
