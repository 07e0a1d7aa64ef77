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
