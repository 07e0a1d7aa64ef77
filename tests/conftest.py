"""Shared fixtures: where the public evaluation data lives."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from hypothesis import settings

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_file(relative: str) -> Path:
    """A file under ../shared/data, or skip the test saying which file is missing."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"public data not available: {path} (see ../shared/data/README.md)")
    return path


# CI runs the same examples every time (CI=true): a red CI then means a change broke something,
# not that the search happened on a new corner case. Local runs keep exploring.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

# Tests press Ctrl-C on the commands they start (SIGINT). A shell's background job (`make test &`, a CI
# runner) starts with SIGINT ignored, and an ignored signal stays ignored in every child, so those
# commands would never see it: Python's own handler here means the children start with the default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
