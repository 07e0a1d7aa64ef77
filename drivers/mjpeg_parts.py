"""The codec of an MJPEG-over-HTTP stream: the body of a ``multipart/x-mixed-replace`` response
cut into its parts (RFC 2046 section 5.1.1), with no I/O, so it can be fed any split of the bytes.

A part is a delimiter line (``--BOUNDARY``, transport padding, CRLF or LF), header lines up to an
empty line, then the body: ``Content-Length`` bytes when the part says its length (mjpg-streamer,
IP cameras, ``trundle emulate camera``), else everything up to the CRLF before the next delimiter.
Bodies are kept byte for byte; whether a body is a whole JPEG is not the codec's business (the
camera driver checks each frame). Bytes outside any part (preamble, padding) are skipped, and a
part whose headers or body overrun the limits is skipped as a whole (counted in ``skipped_parts``),
so garbage cannot make the parser hold unbounded memory. ``X-Timestamp`` (the capture time
mjpg-streamer's output_http plugin sends per part) is read by ``x_timestamp_ns``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

MAX_HEADER_BYTES = 16 * 1024  # a part's header block, delimiter line excluded
MAX_BODY_BYTES = 64 * 1024 * 1024  # one frame
MAX_PADDING = 256  # spaces and tabs allowed after a delimiter before its line ends
_HEADER_END = re.compile(rb"\n\r?\n")
_X_TIMESTAMP = re.compile(r"\s*(\d{1,12})(?:\.(\d{1,9}))?\s*")


@dataclass(frozen=True, slots=True)
class Part:
    """One part of the stream: its headers (names lower-cased, values stripped) and body bytes."""

    headers: dict[str, str]
    body: bytes


def x_timestamp_ns(value: str) -> int | None:
    """``X-Timestamp: <sec>.<usec>`` (mjpg-streamer writes ``%d.%06d``) as integer nanoseconds of
    the camera's clock; None when the value is not a non-negative decimal number of seconds."""
    match = _X_TIMESTAMP.fullmatch(value)
    if match is None:
        return None
    seconds, fraction = match.group(1), match.group(2) or ""
    return int(seconds) * 1_000_000_000 + int(fraction.ljust(9, "0"))


def _headers(block: bytes) -> dict[str, str]:
    """``Name: value`` lines of a header block (latin-1, as HTTP is); lines without a colon are ignored."""
    headers: dict[str, str] = {}
    for line in block.decode("latin-1").splitlines():
        name, colon, value = line.partition(":")
        if colon and name.strip():
            headers[name.strip().lower()] = value.strip()
    return headers


def _content_length(headers: dict[str, str]) -> int | None:
    """The part's Content-Length when it is a plain decimal number, else None (read to the delimiter);
    a number too long to be a frame's length counts as one over ``MAX_BODY_BYTES``."""
    value = headers.get("content-length", "")
    if not (value.isascii() and value.isdigit()):
        return None
    return int(value) if len(value) <= 12 else MAX_BODY_BYTES + 1


class MultipartParser:
    """Cuts a multipart body with ``boundary`` into ``Part``s: ``feed`` bytes as they come, get the
    parts completed so far; ``finish`` at the end of the stream gives the part it cut off, if any.

    The parts produced never depend on how the bytes were split between ``feed`` calls.
    """

    def __init__(self, boundary: str | bytes) -> None:
        raw = boundary.encode("latin-1") if isinstance(boundary, str) else boundary
        if not raw:
            raise ValueError("a multipart boundary cannot be empty")
        self.delimiter = b"--" + raw
        self.skipped_parts = 0
        self._buf = bytearray()
        self._state = "delimiter"  # delimiter | headers | body (Content-Length) | until (the next delimiter) | done
        self._headers: dict[str, str] = {}
        self._length: int | None = None
        self._scan = 0  # where the delimiter search resumes in _buf

    def feed(self, data: bytes) -> list[Part]:
        """Add ``data``; the parts it completed, in order."""
        if self._state == "done":
            return []
        self._buf += data
        parts: list[Part] = []
        while self._step(parts):
            pass
        if self._state == "delimiter":  # nothing before _scan can begin a delimiter
            del self._buf[: self._scan]
            self._scan = 0
        return parts

    def finish(self) -> Part | None:
        """The stream ended: the part whose body it cut off (its bytes so far), or None."""
        part = None
        if self._state == "body" and self._buf:
            part = Part(self._headers, bytes(self._buf))
        self._state, self._buf, self._scan = "done", bytearray(), 0
        return part

    # --- states -------------------------------------------------------------------------------

    def _find_delimiter(self) -> tuple[int, int] | None:
        """``(start, end)`` of the next whole delimiter line in ``_buf`` (``end`` past its LF) from
        ``_scan``; ``(start, -1)`` for the closing delimiter; None when it has not come (yet)."""
        while True:
            start = self._buf.find(self.delimiter, self._scan)
            if start < 0:
                self._scan = max(self._scan, len(self._buf) - len(self.delimiter) + 1)
                return None
            pos = start + len(self.delimiter)
            if self._buf[pos:pos + 2] == b"--":
                return start, -1
            end = pos
            while end < len(self._buf) and end - pos <= MAX_PADDING and self._buf[end] in b" \t":
                end += 1
            tail = self._buf[end:end + 2]
            if end - pos <= MAX_PADDING and tail in (b"", b"\r", b"-"):  # undecided: wait for more bytes
                self._scan = start
                return None
            if tail[:1] == b"\n":
                return start, end + 1
            if tail == b"\r\n":
                return start, end + 2
            self._scan = start + 1  # the boundary text inside something else: not a delimiter

    def _step(self, parts: list[Part]) -> bool:
        """Advance one state; False when more bytes are needed."""
        if self._state in ("delimiter", "until"):
            found = self._find_delimiter()
            if found is None:
                if self._state == "until" and len(self._buf) > MAX_BODY_BYTES + len(self.delimiter) + MAX_PADDING + 2:
                    self._skip_part()  # any delimiter still to come starts past the limit
                    return True
                return False
            start, end = found
            if self._state == "until" and start > MAX_BODY_BYTES:
                self.skipped_parts += 1
            elif self._state == "until":
                parts.append(Part(self._headers, bytes(self._body_before(start))))
            if end < 0:
                self._state = "done"
                self._buf = bytearray()
                return False
            del self._buf[:end]
            self._state, self._scan = "headers", 0
            return True
        if self._state == "headers":
            if self._buf[:1] == b"\n" or self._buf[:2] == b"\r\n":
                block_end, body_start = 0, self._buf.index(b"\n") + 1
            else:
                match = _HEADER_END.search(self._buf)
                if match is None:
                    if len(self._buf) > MAX_HEADER_BYTES + 2:  # an end still to come is past the limit
                        self._skip_part()
                        return True
                    return False
                block_end, body_start = match.start() + 1, match.end()
            if block_end > MAX_HEADER_BYTES:
                self._skip_part()
                return True
            self._headers = _headers(bytes(self._buf[:block_end]))
            self._length = _content_length(self._headers)
            del self._buf[:body_start]
            if self._length is None:
                self._state, self._scan = "until", 0  # the body runs to the next delimiter
            elif self._length > MAX_BODY_BYTES:
                self._skip_part()
            else:
                self._state = "body"
            return True
        if self._state == "body":
            assert self._length is not None
            if len(self._buf) < self._length:
                return False
            parts.append(Part(self._headers, bytes(self._buf[: self._length])))
            del self._buf[: self._length]
            self._state, self._scan = "delimiter", 0
            return True
        return False

    def _skip_part(self) -> None:
        """Drop the current part: everything up to the next delimiter is discarded."""
        self.skipped_parts += 1
        self._state, self._scan, self._headers = "delimiter", 0, {}

    def _body_before(self, start: int) -> bytearray:
        """A delimited body: the bytes before the delimiter at ``start`` without the line break it owns."""
        end = start
        if self._buf[end - 1:end] == b"\n":
            end -= 1
            if self._buf[end - 1:end] == b"\r":
                end -= 1
        return self._buf[:end]
