"""Readers of public dataset formats (CARMEN logs, BreezySLAM ``.dat``) that write trundle MCAP logs.

An importer turns a file into the messages our own drivers publish (LaserScan, JointState,
Odometry, static transforms), so public data runs through exactly the code path of our logs.
"""

from __future__ import annotations

import gzip
import os
import time
import zlib
from collections.abc import Iterable
from pathlib import Path

from trundle.logs import messages as m
from trundle.logs.errors import DataError, UsageError, UserError
from trundle.logs.outputs import PARTIAL_SUFFIX
from trundle.logs.paths import input_file
from trundle.logs.topics import TF_STATIC_TOPIC
from trundle.logs.writer import Logger

Item = tuple[str, m.Message, int]  # topic, message, log time (ns)


def write_log(items: Iterable[Item], out: str | os.PathLike[str], *, metadata: dict[str, object],
              compression: str = "zstd") -> dict[str, int]:
    """Write ``(topic, message, log_time_ns)`` items to the MCAP file ``out``; returns messages per topic.

    Waits for the logger's queue instead of dropping, so an import is always complete.
    ``metadata`` is the log's description (:mod:`trundle.logs.metadata`). ``out`` is written as
    given: a command writes it through :func:`trundle.logs.outputs.writing_file` (whose temporary
    name it may be), so a failure leaves nothing under the name the user gave.
    """
    out = Path(out)
    if out.suffix != PARTIAL_SUFFIX:
        mcap_output(out)
    counts: dict[str, int] = {}
    logger = Logger(out, compression=compression, metadata=metadata, latched_topics=(TF_STATIC_TOPIC,), salvage=False)
    try:
        for topic, msg, log_time_ns in items:
            while logger.queue_length >= logger.queue_size // 2:
                if logger.error is not None:
                    break
                time.sleep(0.001)
            if not logger.write(topic, msg, log_time_ns):
                break
            counts[topic] = counts.get(topic, 0) + 1
    finally:
        logger.close()
    return counts


def mcap_output(out: str | os.PathLike[str]) -> Path:
    """``out`` as the name of an MCAP log to write; any other extension is a UsageError."""
    out = Path(out)
    if out.suffix != ".mcap":
        raise UsageError(f"output must be an .mcap file, got {out}")
    return out


def open_text(path: str | os.PathLike[str]) -> list[str]:
    """Lines of a text dataset file (``.gz`` transparently); a missing or non-regular file (a device
    such as /dev/zero would be read forever) is a UserError and a binary one a DataError, said before
    it is read whole."""
    path = input_file(path, "log file")
    with open(path, "rb") as f:
        gzipped = f.read(2) == b"\x1f\x8b"
    try:
        with (gzip.open(path, "rb") if gzipped else open(path, "rb")) as f:
            head = f.read(65536)
            if b"\x00" in head:
                raise DataError(f"{path} is not a text log (binary data)")
            raw = head + f.read()
    except (OSError, EOFError, zlib.error) as error:
        raise UserError(f"cannot read {path}: {error}") from None
    return raw.decode("utf-8", errors="replace").splitlines()
