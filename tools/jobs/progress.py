"""How long work shows how far it is: a progress factory its caller passes in, silent by default.

``trundle`` passes its terminal progress bar, the fleet passes nothing (or its own), so the jobs
and the demo depend on no command-line code.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol


class ProgressBar(Protocol):
    """The display of one job's progress; ``enabled`` says whether it shows anything (if not, a
    caller may print a line now and then instead)."""

    enabled: bool

    def update(self, done: float, suffix: str = "") -> None:
        """Show ``done`` of the total the display was made with, and ``suffix`` after it."""

    def close(self) -> None:
        """End the display: the job is done."""


ProgressFactory = Callable[[str, float], ProgressBar]
"""Makes a job's progress display from a label and the total (in the unit of ``update``'s ``done``)."""


class NoProgress:
    """A progress display that shows nothing (the default)."""

    enabled = False

    def __init__(self, label: str, total: float) -> None:
        """Take the label and total a progress factory is called with, and ignore them."""

    def update(self, done: float, suffix: str = "") -> None:
        """Show nothing."""

    def close(self) -> None:
        """Nothing to end."""
