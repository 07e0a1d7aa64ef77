"""A killed or starved recorder leaves a log that recovers with at most a second lost."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import trundle
from trundle.logs.errors import DataError
from trundle.logs.reader import LogReader
from trundle.logs.recover import recover

CHILD = Path(__file__).with_name("recorder_child.py")
KILLS = 20
PARALLEL = 5


def start_child(out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(Path(trundle.__file__).parents[1]))  # this test's trundle
    proc = subprocess.Popen([sys.executable, str(CHILD), str(out), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    if proc.stdout.readline().strip() != "ready":
        proc.kill()
        raise AssertionError(f"recorder did not start: {proc.communicate()[1]}")
    return proc


def check_recovered(active: Path, ready_ns: int, killed_at_ns: int, tmp: Path) -> float:
    """Seconds of data lost: from the newest recovered message (or the start) to the kill."""
    assert active.exists(), "a killed recorder must leave its .active file"
    try:
        out = recover(active, tmp / (active.name + ".recovered.mcap"))
    except DataError:  # killed before the first flush: everything since the start is lost
        assert LogReader(active).info().message_count == 0
        return (killed_at_ns - ready_ns) * 1e-9
    seqs: dict[str, list[int]] = {}
    last = ready_ns
    for raw in LogReader(out.output).raw_messages():
        seqs.setdefault(raw.topic, []).append(raw.sequence)
        last = max(last, raw.log_time_ns)
    for topic, s in seqs.items():  # nothing missing in the middle, nothing duplicated
        assert s == list(range(len(s))), topic
    assert set(seqs) <= {"/scan", "/wheels"}
    return (killed_at_ns - last) * 1e-9


def test_sigkill_at_20_random_moments_loses_at_most_one_second(tmp_path: Path) -> None:
    rng = random.Random(20261122)
    losses = []
    for batch in range(KILLS // PARALLEL):
        children = []
        for i in range(PARALLEL):
            out = tmp_path / f"kill{batch}_{i}.mcap"
            proc = start_child(out)
            children.append((out, proc, time.time_ns(), rng.uniform(0.2, 3.0)))
        started = time.monotonic()
        try:
            for out, proc, ready_ns, after in sorted(children, key=lambda c: c[3]):
                time.sleep(max(0.0, started + after - time.monotonic()))
                killed_at = time.time_ns()
                proc.send_signal(signal.SIGKILL)
                proc.wait()
                losses.append(check_recovered(out.with_name(out.name + ".active"), ready_ns, killed_at, tmp_path))
        finally:  # a failed check must not leave recorders running
            for _, proc, _, _ in children:
                proc.kill()
                proc.wait()
    assert len(losses) == KILLS
    assert max(losses) <= 1.0, f"lost {max(losses):.3f} s (all: {np.round(losses, 3).tolist()})"


def test_file_size_limit_stops_logger_with_clear_error_and_readable_file(tmp_path: Path) -> None:
    out = tmp_path / "limited.mcap"
    proc = start_child(out, "--fsize-limit", "1000000")
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 3
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "File too large" in lines[0] and "trundle recover" in lines[0], err
    active = out.with_name(out.name + ".active")
    assert 0 < active.stat().st_size <= 1000000
    assert sum(1 for _ in LogReader(active).messages()) > 0
    assert recover(active, tmp_path / "fixed.mcap").messages > 0
