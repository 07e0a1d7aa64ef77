"""Hokuyo SCIP 2.0 codec: commands, replies, line checksums and the 2/3/4-character encodings.

Pure functions over bytes and numpy arrays (no I/O), shared by the driver and the emulator.
A reply is ``echo LF status sum LF [data-line sum LF]* LF``; data are split into lines of at
most 64 characters, and an encoded value may straddle two lines, so lines are verified and
stripped of their sums before the payload is decoded (Hokuyo SCIP 2.0 specification C-42-03320B).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from trundle.logs.errors import ProtocolError

LF = 0x0A
CHAR_BASE = 0x30  # '0': every encoded character carries 6 bits above this
CHAR_TOP = 0x6F  # 'o' = 0x30 + 63
LINE_CHARS = 64  # payload characters per data line
TIMESTAMP_CHARS = 4
STRING_CHARS = re.compile(rb"[A-Za-z0-9 ._+@]{0,16}")
MEASURE_COMMANDS = ("GD", "GS", "GE", "MD", "MS", "ME")


class ScipError(ProtocolError):
    """A reply that cannot be used; ``kind`` is checksum, truncated, format or status (the driver
    counts bad scans and drops them; a bad reply during the handshake reconnects)."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def checksum(data: bytes) -> int:
    """SCIP sum character of ``data``: low 6 bits of the byte sum, plus 0x30."""
    return (sum(data) & 0x3F) + CHAR_BASE


def with_checksum(data: bytes) -> bytes:
    """``data`` followed by its sum character (a reply line without its LF)."""
    return data + bytes((checksum(data),))


def verify_line(line: bytes, tolerant: bool = False) -> bytes:
    """The payload of ``line`` (sum character stripped), or ScipError("checksum").

    ``tolerant`` also accepts a sum over all but the last payload character, as urg_c does:
    that covers the key:value lines (``KEY:VALUE;S`` sums ``KEY:VALUE``, not the ``;``) and
    firmware that sums one character too many or too few on the VV lines.
    """
    if len(line) < 2:
        raise ScipError("truncated", f"line too short: {line!r}")
    payload, got = line[:-1], line[-1]
    if checksum(payload) == got or (tolerant and len(payload) >= 1 and checksum(payload[:-1]) == got):
        return payload
    raise ScipError("checksum", f"bad sum in line {line!r}")


def encode_command(command: str, params: str = "", string: str = "") -> bytes:
    """A request line: ``<command><params>[;<string>]`` and LF.

    ``string`` (at most 16 of ``A-Za-z0-9 ._+@``) is echoed back by the sensor, which lets a
    host tell its own replies from those of an earlier session.
    """
    if not (len(command) == 2 or (len(command) == 3 and command[0] == "%") or command == "SCIP2.0"):
        raise ValueError(f"not a SCIP command name: {command!r}")
    if not STRING_CHARS.fullmatch(string.encode("ascii", "replace")):
        raise ValueError(f"SCIP string must be at most 16 of A-Za-z0-9 ._+@: {string!r}")
    text = command + params + (";" + string if string else "")
    return text.encode("ascii") + b"\n"


def encode_values(values: np.ndarray | Sequence[int], width: int) -> bytes:
    """Encode non-negative integers as ``width`` characters of 6 bits each, big-endian."""
    v = np.asarray(values, dtype=np.int64).reshape(-1)
    if v.size and (v.min() < 0 or v.max() >= 1 << (6 * width)):
        raise ValueError(f"values must be in [0, {1 << (6 * width)}) for {width}-character encoding")
    shifts = 6 * np.arange(width - 1, -1, -1, dtype=np.int64)
    chars = ((v[:, None] >> shifts) & 0x3F) + CHAR_BASE
    return chars.astype(np.uint8).tobytes()


def decode_values(chars: bytes | np.ndarray, width: int) -> np.ndarray:
    """Decode ``width``-character groups into uint32 values (ScipError on bad length or characters)."""
    c = np.frombuffer(chars, dtype=np.uint8) if isinstance(chars, (bytes, bytearray, memoryview)) else chars
    if c.size % width:
        raise ScipError("truncated", f"{c.size} characters is not a multiple of {width}")
    d = c - np.uint8(CHAR_BASE)  # wraps below 0x30, so one test catches both ends of the range
    if d.size and d.max() > 0x3F:
        raise ScipError("format", "character outside the SCIP encoding range 0x30-0x6F")
    return d.reshape(-1, width) @ _WEIGHTS[width]  # one pass: sum of 6-bit digits times 64^k


_WEIGHTS = {width: (1 << (6 * np.arange(width - 1, -1, -1))).astype(np.uint32) for width in range(1, 6)}


def decode_value(chars: bytes) -> int:
    """Decode one short value (a timestamp) without numpy; ScipError on bad characters."""
    value = 0
    for c in chars:
        if not CHAR_BASE <= c <= CHAR_TOP:
            raise ScipError("format", "character outside the SCIP encoding range 0x30-0x6F")
        value = (value << 6) | (c - CHAR_BASE)
    return value


def encode_data(payload: bytes) -> bytes:
    """Split encoded data into lines of at most 64 characters, each with sum and LF."""
    n = len(payload)
    full = n // LINE_CHARS
    out = bytearray()
    if full:
        body = np.frombuffer(payload, np.uint8, full * LINE_CHARS).reshape(full, LINE_CHARS)
        lines = np.empty((full, LINE_CHARS + 2), np.uint8)
        lines[:, :LINE_CHARS] = body
        lines[:, LINE_CHARS] = (body.sum(axis=1, dtype=np.uint32) & 0x3F) + CHAR_BASE
        lines[:, LINE_CHARS + 1] = LF
        out += lines.tobytes()
    rest = payload[full * LINE_CHARS:]
    if rest:
        out += with_checksum(rest) + b"\n"
    return bytes(out)


def decode_data(region: bytes, n_chars: int) -> np.ndarray:
    """Verify and join the data lines in ``region`` holding ``n_chars`` encoded characters.

    ``region`` is the lines as received, each ``payload sum LF``. Returns the payload characters
    as uint8 (lines concatenated, so values straddling two lines come out whole). Raises
    ScipError("truncated") when the line layout does not match ``n_chars`` and
    ScipError("checksum") when a line's sum is wrong.
    """
    full, rest = divmod(n_chars, LINE_CHARS)
    expected = full * (LINE_CHARS + 2) + (rest + 2 if rest else 0)
    if len(region) != expected:
        raise ScipError("truncated", f"data of {len(region)} bytes where {expected} were expected")
    arr = np.frombuffer(region, dtype=np.uint8)
    body = arr[: full * (LINE_CHARS + 2)].reshape(full, LINE_CHARS + 2)
    last = arr[full * (LINE_CHARS + 2):]
    if (body[:, -1] != LF).any() or (rest and last[-1] != LF):
        raise ScipError("truncated", "data line boundaries out of place")
    # uint8 sums wrap modulo 256, which keeps the low 6 bits the checksum uses
    sums = (np.add.reduce(body[:, :LINE_CHARS], axis=1, dtype=np.uint8) & 0x3F) + CHAR_BASE
    if (sums != body[:, LINE_CHARS]).any() or (rest and checksum(last[:rest].tobytes()) != last[rest]):
        raise ScipError("checksum", "bad sum in a data line")
    if not rest:
        return body[:, :LINE_CHARS].reshape(-1)
    return np.concatenate((body[:, :LINE_CHARS].reshape(-1), last[:rest]))


@dataclass(frozen=True)
class Reply:
    """One reply: the ``echo`` line (without LF) and the ``body`` lines that follow it.

    ``body`` keeps each line's LF and leaves out the empty line that ends the reply.
    """

    echo: bytes
    body: bytes

    @property
    def status(self) -> str:
        """The two status characters (one for a SCIP 1.1 answer); ScipError if the line is bad."""
        end = self.body.find(b"\n")
        if end < 0:
            raise ScipError("truncated", "reply without a status line")
        line = self.body[:end]
        if len(line) == 1:
            return line.decode("latin-1")
        if len(line) != 3:
            raise ScipError("truncated", f"status line {line!r}")
        return verify_line(line).decode("latin-1")

    def lines(self) -> list[bytes]:
        """The lines after the status line, without their LF."""
        return self.body.split(b"\n")[1:-1]


def encode_reply(echo: bytes, status: str, lines: Iterable[bytes] = (), data: bytes = b"") -> bytes:
    """A whole reply: echo, status with sum, ``lines`` (sums added), raw ``data`` lines, empty line."""
    out = [echo, b"\n", with_checksum(status.encode("ascii")), b"\n"]
    for line in lines:
        out += [with_checksum(line), b"\n"]
    out += [data, b"\n"]
    return b"".join(out)


def parse_info(reply: Reply) -> dict[str, str]:
    """The ``KEY:VALUE;S`` lines of a VV, PP or II reply as a dict (tolerant sums, see ``verify_line``)."""
    info: dict[str, str] = {}
    for line in reply.lines():
        payload = verify_line(line, tolerant=True)
        key, sep, value = payload.partition(b":")
        if not sep:
            raise ScipError("format", f"not a key:value line: {line!r}")
        info[key.decode("latin-1")] = value.rstrip(b";").decode("latin-1")
    return info


def encode_info(items: Mapping[str, str]) -> bytes:
    """The data lines of a VV/PP/II reply: ``KEY:VALUE;`` and the sum of ``KEY:VALUE``."""
    out = []
    for key, value in items.items():
        text = f"{key}:{value}".encode("latin-1")
        out.append(text + b";" + bytes((checksum(text),)) + b"\n")
    return b"".join(out)


@dataclass(frozen=True)
class SensorParams:
    """The PP parameters: distances in mm, steps of the angular grid, scan speed in rpm."""

    model: str
    dmin: int
    dmax: int
    ares: int
    amin: int
    amax: int
    afrt: int
    rpm: int

    @classmethod
    def from_info(cls, info: Mapping[str, str]) -> SensorParams:
        """Parse a PP reply; ScipError("format") if a key is missing or not a number."""
        try:
            numbers = {k: int(info[k.upper()].strip()) for k in ("dmin", "dmax", "ares", "amin", "amax", "afrt")}
            rpm = int(info["SCAN"].strip())
        except (KeyError, ValueError) as error:
            raise ScipError("format", f"PP reply lacks a numeric {error}") from None
        if numbers["ares"] <= 0 or rpm <= 0 or numbers["amin"] > numbers["amax"]:
            raise ScipError("format", "PP reply with impossible ARES/SCAN/AMIN/AMAX")
        return cls(info.get("MODL", ""), rpm=rpm, **numbers)

    def info(self) -> dict[str, str]:
        """The PP key/value pairs in the sensor's order."""
        return {"MODL": self.model, "DMIN": str(self.dmin), "DMAX": str(self.dmax), "ARES": str(self.ares),
                "AMIN": str(self.amin), "AMAX": str(self.amax), "AFRT": str(self.afrt), "SCAN": str(self.rpm)}

    @property
    def scan_period_s(self) -> float:
        return 60.0 / self.rpm

    def step_angle(self, step: float | np.ndarray) -> float | np.ndarray:
        """Angle (rad, counter-clockwise, 0 ahead) of step ``step``."""
        return 2.0 * np.pi * (np.asarray(step, dtype=np.float64) - self.afrt) / self.ares

    def angle_step(self, angle: float) -> int:
        """The step nearest to ``angle`` (rad), clamped to [AMIN, AMAX]."""
        step = round(angle * self.ares / (2.0 * np.pi) + self.afrt)
        return int(min(max(step, self.amin), self.amax))


@dataclass(frozen=True)
class Measure:
    """A distance request (GD/GS/GE single scan, MD/MS/ME continuous).

    ``start``..``end`` steps inclusive, ``cluster`` steps merged per value (0 and 1 both mean
    one), ``skip`` scans left out between two sent (MD only), ``scans`` to send (0 = until QT),
    ``string`` echoed back.
    """

    command: str
    start: int
    end: int
    cluster: int = 1
    skip: int = 0
    scans: int = 0
    string: str = ""

    def __post_init__(self) -> None:
        if self.command not in MEASURE_COMMANDS:
            raise ValueError(f"not a measurement command: {self.command!r}")
        if not (0 <= self.start <= self.end <= 9999 and 0 <= self.cluster <= 99 and 0 <= self.skip <= 9
                and 0 <= self.scans <= 99):
            raise ValueError(f"measurement parameters out of range: {self}")

    @property
    def continuous(self) -> bool:
        return self.command[0] == "M"

    @property
    def width(self) -> int:
        """Characters per value: 2 for GS/MS, 3 otherwise."""
        return 2 if self.command[1] == "S" else 3

    @property
    def intensity(self) -> bool:
        return self.command[1] == "E"

    @property
    def beams(self) -> int:
        cluster = max(self.cluster, 1)
        return (self.end - self.start + cluster) // cluster

    @property
    def data_chars(self) -> int:
        return self.beams * self.width * (2 if self.intensity else 1)

    def params(self, scans: int | None = None) -> str:
        text = f"{self.start:04d}{self.end:04d}{self.cluster:02d}"
        if self.continuous:
            text += f"{self.skip:01d}{self.scans if scans is None else scans:02d}"
        return text

    def encode(self) -> bytes:
        return encode_command(self.command, self.params(), self.string)

    def echo(self, remaining: int | None = None) -> bytes:
        """The echo line of a reply; for MD/MS/ME scans ``remaining`` replaces the scan count."""
        return encode_command(self.command, self.params(remaining), self.string)[:-1]

    @classmethod
    def from_echo(cls, line: bytes) -> Measure:
        """Parse a request or echo line (without LF); ScipError("format") if it is not one."""
        text, _, string = line.decode("latin-1").partition(";")
        command = text[:2]
        size = 15 if command[:1] == "M" else 12
        if command not in MEASURE_COMMANDS or len(text) != size or not text[2:].isdigit():
            raise ScipError("format", f"not a measurement request: {line!r}")
        try:
            skip, scans = (int(text[12]), int(text[13:15])) if size == 15 else (0, 0)
            return cls(command, int(text[2:6]), int(text[6:10]), int(text[10:12]), skip, scans, string)
        except ValueError as error:
            raise ScipError("format", str(error)) from None


@dataclass(frozen=True)
class Scan:
    """A decoded scan: raw 24-bit ``timestamp`` (ms), ``distances`` (mm or error codes below DMIN),
    ``intensities`` (None unless GE/ME) and, for MD/MS/ME, the ``remaining`` scan count."""

    timestamp: int
    distances: np.ndarray
    intensities: np.ndarray | None
    remaining: int = 0


def decode_scan(reply: Reply, measure: Measure) -> Scan:
    """Decode a measurement reply with status 00 or 99 (ScipError on any defect)."""
    status = reply.status
    if status not in ("00", "99"):
        raise ScipError("status", f"status {status}")
    body = reply.body
    stamp_line = body[4:4 + TIMESTAMP_CHARS + 2]
    if len(stamp_line) != TIMESTAMP_CHARS + 2 or stamp_line[-1] != LF:
        raise ScipError("truncated", "timestamp line")
    timestamp = decode_value(verify_line(stamp_line[:-1]))
    distances, intensities = decode_measurement(body, measure)
    remaining = int(reply.echo[13:15]) if measure.continuous and reply.echo[13:15].isdigit() else 0
    return Scan(timestamp, distances, intensities, remaining)


def decode_measurement(body: bytes, measure: Measure) -> tuple[np.ndarray, np.ndarray | None]:
    """Distances and (GE/ME) intensities of a reply ``body`` whose status and timestamp lines
    the caller has checked (ScipError on any defect in the data lines)."""
    values = decode_values(decode_data(body[4 + TIMESTAMP_CHARS + 2:], measure.data_chars), measure.width)
    if measure.intensity:
        pairs = values.reshape(-1, 2)
        return pairs[:, 0], pairs[:, 1]
    return values, None


def encode_scan(measure: Measure, timestamp: int, distances: np.ndarray, intensities: np.ndarray | None = None,
                remaining: int | None = None, status: str = "99") -> bytes:
    """A measurement reply (the emulator's side of ``decode_scan``)."""
    values = np.asarray(distances, dtype=np.int64)
    if measure.intensity:
        values = np.column_stack((values, np.asarray(intensities, dtype=np.int64))).reshape(-1)
    echo = measure.echo(remaining) if measure.continuous else measure.echo()
    stamp = encode_values([timestamp & 0xFFFFFF], TIMESTAMP_CHARS)
    return encode_reply(echo, status, [stamp], encode_data(encode_values(values, measure.width)))


class ScipFramer:
    """Cuts a byte stream into replies to the commands the host is waiting for.

    A reply starts at an expected echo line and ends at the empty line (or where the next
    expected echo starts, when a truncated reply lost its end). Anything else is skipped and
    counted: ``resyncs`` runs of skipped bytes, ``garbage_bytes`` in total, ``overflows`` replies
    dropped for growing past ``max_reply`` bytes. Never raises on any input.
    """

    def __init__(self, max_reply: int = 1 << 16) -> None:
        self.max_reply = max_reply
        self.resyncs = 0
        self.garbage_bytes = 0
        self.overflows = 0
        self._buf = bytearray()
        self._echoes: tuple[bytes, ...] = ()
        self._heads: dict[bytes, list[bytes]] = {b"": [], b"\n": []}
        self._in_garbage = False

    def expect(self, *echoes: bytes) -> None:
        """Set the echo lines (without LF) that start the replies wanted from now on."""
        self._echoes = tuple(echoes)
        self._heads = {b"": [e + b"\n" for e in echoes], b"\n": [b"\n" + e + b"\n" for e in echoes]}

    def clear(self) -> int:
        """Drop buffered bytes; returns how many."""
        n = len(self._buf)
        self._buf.clear()
        return n

    def _skip(self, n: int) -> None:
        if n <= 0:
            return
        if not self._in_garbage:
            self.resyncs += 1
            self._in_garbage = True
        self.garbage_bytes += n
        del self._buf[:n]

    def _find(self, prefix: bytes, start: int) -> tuple[int, bytes]:
        best, which = -1, b""
        for echo, head in zip(self._echoes, self._heads[prefix], strict=True):
            pos = self._buf.find(head, start)
            if pos >= 0 and (best < 0 or pos < best):
                best, which = pos, echo
        return best, which

    def feed(self, data: bytes) -> list[Reply]:
        """Add received bytes; return the complete replies they finish."""
        self._buf += data
        replies: list[Reply] = []
        while self._echoes:
            pos, echo = self._find(b"", 0)
            if pos < 0:
                keep = max(len(e) for e in self._echoes)
                self._skip(len(self._buf) - keep)
                break
            self._skip(pos)
            self._in_garbage = False
            head = len(echo) + 1
            end = self._buf.find(b"\n\n", head - 1)
            cut, _ = self._find(b"\n", head)
            if cut >= 0 and (end < 0 or cut < end):
                end = cut
            if end < 0:
                if len(self._buf) > self.max_reply:
                    self.overflows += 1
                    self._skip(len(self._buf))
                break
            replies.append(Reply(bytes(echo), bytes(self._buf[head:end + 1])))
            del self._buf[:end + 2 if self._buf[end + 1:end + 2] == b"\n" else end + 1]
        if not self._echoes:
            self._skip(len(self._buf))
        return replies
