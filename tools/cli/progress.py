"""A one-line progress bar on stderr for long work (silent when stderr is not a terminal)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``update(done)`` redraws ``label [#####     ] 42% done/total`` at most 10 times a second."""

    def __init__(self, label: str, total: float, stream: TextIO | None = None, force: bool = False) -> None:
        self.label, self.total = label, max(total, 1e-12)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = force or self.stream.isatty()
        self._last = 0.0

    def update(self, done: float, suffix: str = "") -> None:
        now = time.monotonic()
        if not self.enabled or (now - self._last < 0.1 and done < self.total):
            return
        self._last = now
        fraction = min(max(done / self.total, 0.0), 1.0)
        bar = "#" * int(30 * fraction)
        self.stream.write(f"\r{self.label} [{bar:<30}] {fraction:4.0%} {suffix}")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


class StatusLine:
    """Progress of work without an end known in advance (a recording until Ctrl-C): on a terminal,
    ``update(text)`` redraws one line in place at most once a second; otherwise (a log file,
    journald) it prints the text as a line of its own every ``every_s`` seconds."""

    def __init__(self, stream: TextIO | None = None, every_s: float = 10.0, terminal: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = self.stream.isatty() if terminal is None else terminal
        self.every_s = every_s if not self.terminal else 1.0
        self._next = time.monotonic() + self.every_s
        self._width = 0

    def update(self, text: str) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.every_s
        if self.terminal:
            self.stream.write(f"\r{text:<{self._width}}")   # spaces over a longer line before it
            self._width = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.terminal and self._width:
            self.stream.write("\n")
            self.stream.flush()
