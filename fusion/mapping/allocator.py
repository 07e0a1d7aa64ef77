"""The C allocator of a `trundle` process told to keep the memory it frees for reuse (glibc's ``mallopt``).

A scan match makes arrays of a few hundred kilobytes (a reference grid, its fields, a window's index) and
drops them a millisecond later. With glibc's defaults those come from ``mmap`` or from a heap top that is
given back to the system as soon as it is freed, so the next match takes fresh pages, each one a page
fault the kernel zeroes: 38-65 faults a match in the Intel Karto comparison, at 2.6 us each on the
development VM (a tenth of a match). Held in the heap instead, the same memory is reused.

Two settings, both glibc's own (``mallopt(3)``): blocks below :data:`MMAP_THRESHOLD` come from the heap
(glibc's largest threshold on 64 bits), and the heap's free top is given back only beyond
:data:`TRIM_THRESHOLD`, so a process keeps at most that much free memory at the top of its heap (set
the mmap threshold first: if it fails, neither is set). Either one alone is worse
than neither (a fixed trim threshold also fixes the mmap threshold at its 128 KiB default). A user's own
settings (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, ``GLIBC_TUNABLES`` naming malloc) are left
as they are, and another C library (musl) is left alone.
"""

from __future__ import annotations

import ctypes
import os

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3   # mallopt's parameters (malloc.h)
MMAP_THRESHOLD = 32 << 20   # bytes: glibc's largest (half its 64 MiB heap size on 64 bits)
TRIM_THRESHOLD = 64 << 20   # bytes of free heap top a process keeps at most
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Set the two thresholds for this process; returns whether they were set (False: not glibc, or the
    user set the allocator's thresholds)."""
    if any(name in os.environ for name in USER_SETTINGS) or "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    try:
        libc = os.confstr("CS_GNU_LIBC_VERSION") or ""   # "glibc 2.36"; unknown to another C library
    except (ValueError, OSError):
        libc = ""
    if not libc.startswith("glibc"):
        return False
    mallopt = ctypes.CDLL(None).mallopt
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
