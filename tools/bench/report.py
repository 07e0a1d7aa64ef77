"""Shared output for benchmarks: print a figure table and write it as JSON."""

from __future__ import annotations

import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from trundle.logs.outputs import write_json

RESULTS = Path("bench-results")


def best_of(fn: Callable[[], object], repeat: int = 5, number: int = 1,
            clock: Callable[[], float] = time.perf_counter) -> float:
    """Smallest mean seconds per call of ``fn`` over ``repeat`` rounds of ``number`` calls.

    ``clock=time.process_time`` measures CPU time, which a loaded machine disturbs less.
    """
    best = float("inf")
    for _ in range(repeat):
        start = clock()
        for _ in range(number):
            fn()
        best = min(best, (clock() - start) / number)
    return best


def write(name: str, figures: dict[str, Any]) -> Path:
    """Print ``figures`` and save them with the machine description to bench-results/NAME.json."""
    RESULTS.mkdir(exist_ok=True)
    payload = {"benchmark": name, "machine": {"python": platform.python_version(), "cpu": platform.processor()
                                              or platform.machine()}, "figures": figures}
    path = RESULTS / f"{name}.json"
    write_json(path, payload, replace=True)
    width = max(map(len, figures), default=0)
    for key, value in figures.items():
        print(f"{key:<{width}}  {value:.4g}" if isinstance(value, float) else f"{key:<{width}}  {value}")
    print(f"wrote {path}")
    return path
