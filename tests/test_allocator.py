"""A `trundle` process keeps the memory it frees for reuse (glibc's mallopt), unless the user set the allocator."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import trundle
from trundle.fusion.mapping import allocator
from trundle.tools.cli import main as cli

PACKAGE_PARENT = Path(trundle.__file__).parent.parent  # where `import trundle` found the code under test
GLIBC = (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")

# Page faults of six rounds of four 1 MB arrays made, written and dropped together (a match's arrays): with
# glibc's defaults the freed heap top is given back every round and the next round faults its pages in again.
FAULTS = """
import resource, sys
import numpy as np
from trundle.fusion.mapping.allocator import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "kept" else None
counts = []
for _ in range(6):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    blocks = [np.ones(125_000) for _ in range(4)]
    del blocks
    counts.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(kept, *counts)
"""


def faults(how: str, **env: str) -> tuple[str, list[int]]:
    """What keep_freed_memory returned ("None": not called) and the faults of each round, in a fresh process."""
    clean = {k: v for k, v in os.environ.items() if k not in allocator.USER_SETTINGS and k != "GLIBC_TUNABLES"}
    done = subprocess.run([sys.executable, "-c", FAULTS, how], capture_output=True, text=True, check=True,
                          env={**clean, "PYTHONPATH": str(PACKAGE_PARENT), **env})
    kept, *counts = done.stdout.split()
    return kept, [int(c) for c in counts]


@pytest.mark.skipif(not GLIBC, reason="the allocator's thresholds are glibc's (this C library is another)")
def test_freed_memory_is_reused_without_page_faults():
    pages = 4 * 1_000_000 // os.sysconf("SC_PAGE_SIZE")
    kept, counts = faults("kept")
    assert kept == "True" and counts[0] > pages // 2 and max(counts[1:]) < pages // 20   # the first round's, reused
    default, counts = faults("default")
    assert default == "None" and min(counts[1:]) > pages // 2   # glibc's defaults: faulted in again every round


@pytest.mark.parametrize("setting", [{"MALLOC_TRIM_THRESHOLD_": "1048576"}, {"MALLOC_MMAP_THRESHOLD_": "65536"},
                                     {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=1048576"}])
def test_the_users_allocator_settings_are_left_as_they_are(setting):
    assert faults("kept", **setting)[0] == "False"


def test_a_command_sets_the_allocator_and_help_does_not(monkeypatch):
    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(True) or True)
    for argv, code in ((["trundle", "--help"], 0), (["trundle", "info", "/nonexistent.mcap"], 2)):
        monkeypatch.setattr(sys, "argv", argv)
        with pytest.raises(SystemExit) as done:
            cli.entry()
        assert done.value.code == code
    assert calls == [True]   # once: for the command, not for --help
