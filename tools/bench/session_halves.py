"""A real log cut in two at a place both halves visit, for the multi-session acceptance (tests and
tools/bench/bench_sessions.py).

:func:`split_index` picks the cut from the reference trajectory alone, the same rule for every log:
among the reference poses in the middle fifth of the log (40 % .. 60 % of its poses), the one whose
place the first half visited at least ``min_gap_s`` earlier and the second half visits again at least
``min_gap_s`` later, nearest to both (the larger of the two distances smallest), ties to the middle.
:func:`write_halves` writes the two halves as logs; the second half's odometry (if any) is re-based to
start at zero, so nothing in it tells where it starts.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from trundle.fusion.geometry import relative
from trundle.logs import messages as m
from trundle.logs.importers import write_log
from trundle.logs.reader import LogReader
from trundle.logs.topics import TF_STATIC_TOPIC


def split_index(positions: np.ndarray, stamps_ns: np.ndarray, min_gap_s: float = 60.0) -> int:
    """The index of the reference pose where the log is cut (see the module docstring)."""
    n = len(positions)
    stamps = np.asarray(stamps_ns, np.int64)
    gap = round(min_gap_s * 1e9)
    best, best_key = n // 2, (np.inf, np.inf)
    for k in range(int(0.4 * n), int(0.6 * n) + 1):
        before = np.flatnonzero(stamps < stamps[k] - gap)
        after = np.flatnonzero(stamps > stamps[k] + gap)
        if not len(before) or not len(after):
            continue
        d_before = float(np.min(np.hypot(*(positions[before, :2] - positions[k, :2]).T)))
        d_after = float(np.min(np.hypot(*(positions[after, :2] - positions[k, :2]).T)))
        key = (round(max(d_before, d_after), 1), abs(k - n // 2))
        if key < best_key:
            best, best_key = k, key
    return best


def write_halves(log: Path, split_ns: int, first: Path, second: Path) -> None:
    """``log`` cut at ``split_ns`` (log time) into ``first`` and ``second``; ``/tf_static`` goes into both and
    the second half's Odometry is re-based to start at zero."""
    with LogReader(log) as reader:
        items = [(i.topic, i.msg, i.log_time_ns) for i in reader.messages()]
    statics = [(t, msg) for t, msg, _ in items if t == TF_STATIC_TOPIC]
    head = [i for i in items if i[0] != TF_STATIC_TOPIC and i[2] < split_ns]
    tail = [i for i in items if i[0] != TF_STATIC_TOPIC and i[2] >= split_ns]
    odom0 = next((np.array([msg.x, msg.y, msg.theta]) for _, msg, _ in tail if isinstance(msg, m.Odometry)), None)
    rebased = []
    for topic, msg, t in tail:
        if isinstance(msg, m.Odometry) and odom0 is not None:
            x, y, theta = relative(odom0, np.array([msg.x, msg.y, msg.theta]))
            msg = dataclasses.replace(msg, x=float(x), y=float(y), theta=float(theta))
        rebased.append((topic, msg, t))
    for path, part in ((first, head), (second, rebased)):
        start = part[0][2]
        write_log([(t, msg, start) for t, msg in statics] + part, path, metadata={"command": "test"})
