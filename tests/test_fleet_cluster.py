"""`trundle fleet` on a real two-node Ray cluster on loopback addresses (tests/ray_cluster.py):
a corrupt log fails alone, a rerun skips what is done, a worker node killed mid-run loses no log."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.fleet_logs import START_NS, corrupt_log, robot_log
from tests.ray_cluster import ENV, HEAD_IP, LoopbackCluster, NamespaceUnavailable, cmdline

TRUNDLE = str(Path(sys.executable).with_name("trundle"))
HOUR_NS = 3600 * 10**9


@pytest.fixture(scope="module")
def cluster():
    """Head 127.0.0.2 and worker 127.0.0.3, one CPU each; torn down whatever the tests do."""
    try:
        c = LoopbackCluster()
    except NamespaceUnavailable as error:
        pytest.skip(str(error))
    try:
        c.start()
        c.add_node("127.0.0.3")
        yield c
    finally:
        c.stop()


def fleet(cluster: LoopbackCluster, *args: str) -> subprocess.CompletedProcess:
    """`trundle fleet ARGS --address <head>` run as a user runs it (inside the cluster's namespace)."""
    return subprocess.run(cluster.command([TRUNDLE, "fleet", *args, "--address", cluster.address]),
                          capture_output=True, text=True, timeout=600, env=ENV)


def rows(folder: Path) -> dict[str, dict[str, str]]:
    with open(folder / "results.csv", newline="") as f:
        return {Path(r["log"]).name: r for r in csv.DictReader(f)}


def test_slam_over_five_logs_one_corrupt_then_a_rerun_skips_the_done(cluster, tmp_path) -> None:
    logs = tmp_path / "logs"
    good = [robot_log(logs / f"robot-{r}" / f"run{i}.mcap", f"robot-{r}", START_NS + i * HOUR_NS, offset=5 * i)
            for i, r in enumerate("aabb")]
    bad = corrupt_log(logs / "robot-b" / "broken.mcap", good[0])
    out = tmp_path / "out"
    first = fleet(cluster, "slam", str(logs / "robot-*" / "*.mcap"), "-o", str(out))
    assert first.returncode == 1, first.stderr        # a failed log is said by the exit code, the others ran
    table = rows(out)
    assert sorted(table) == sorted(p.name for p in good + [bad])
    assert [table[p.name]["status"] for p in good] == ["ok"] * 4
    failed = table["broken.mcap"]
    assert failed["status"] == "failed" and "broken.mcap" in failed["error"] and "has no topic /scan" in failed["error"]
    assert f"failed {bad}: " in first.stdout
    assert {table[p.name]["node"] for p in good} == {HEAD_IP, "127.0.0.3"}   # both nodes did work
    for p in good:
        folder = out / table[p.name]["name"]
        assert table[p.name]["name"] == p.stem
        for name in ("map.yaml", "map.pgm", "trajectory.csv", "report.json", "slam.mcap", "fleet.json"):
            assert (folder / name).is_file(), folder / name
        report = json.loads((folder / "report.json").read_text())
        assert int(table[p.name]["scans"]) == report["scans"] == 20
        assert table[p.name]["robot"] == p.parent.name
    assert not (out / "broken").exists()                 # a failed log installs nothing ...
    assert "Traceback" in (out / ".fleet" / "errors" / "broken.txt").read_text() or \
        "no LaserScan" in (out / ".fleet" / "errors" / "broken.txt").read_text()   # ... and keeps its error text

    stamps = {p.name: (out / p.stem / "fleet.json").stat().st_mtime_ns for p in good}
    second = fleet(cluster, "slam", str(logs / "robot-*" / "*.mcap"), "-o", str(out))
    assert second.returncode == 1
    again = rows(out)
    assert [again[p.name]["status"] for p in good] == ["skipped"] * 4
    assert again["broken.mcap"]["status"] == "failed"
    assert {p.name: (out / p.stem / "fleet.json").stat().st_mtime_ns for p in good} == stamps  # not recomputed
    assert [again[p.name]["scans"] for p in good] == [table[p.name]["scans"] for p in good]

    host = subprocess.run(["ss", "-Hltnp"], capture_output=True, text=True).stdout   # the machine's own namespace
    assert not [pid for pid in cluster.processes() if f"pid={pid}," in host]
    listening = cluster.listeners()
    assert listening and all(a.startswith(("127.", "*:", "0.0.0.0:", "[::]:", "[::ffff:127.")) for a in listening)
    assert not [a for a in listening if a.startswith("127.") and not a.startswith(("127.0.0.2:", "127.0.0.3:",
                                                                                   "127.0.0.1:"))]


def _task_on(cluster: LoopbackCluster, raylet: int) -> str | None:
    """The name of the fleet task a worker of that raylet runs now (Ray titles it ``ray::<task name>``)."""
    for pid in cluster.processes():
        title = cmdline(pid)
        if title.startswith("ray::trundle-fleet") and _parent(pid) == raylet:
            return title.split()[-1]
    return None


def _parent(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return -1


def test_a_worker_node_killed_mid_run_loses_no_log(cluster, tmp_path) -> None:
    node = cluster.add_node("127.0.0.4")
    raylet = cluster.raylet(node)
    logs = [robot_log(tmp_path / "logs" / f"long{i}.mcap", "robot-c", START_NS + i * HOUR_NS, scans=120, offset=3 * i)
            for i in range(6)]
    out = tmp_path / "out"
    run = subprocess.Popen(cluster.command([TRUNDLE, "fleet", "slam", *map(str, logs), "-o", str(out),
                                            "--address", cluster.address, "--retries", "2"]),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    killed = None
    deadline = time.monotonic() + 300
    while killed is None and run.poll() is None and time.monotonic() < deadline:
        killed = _task_on(cluster, raylet)
        time.sleep(0.05)
    assert killed is not None, "no fleet task ever ran on the third node"
    os.kill(raylet, signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=600)
    assert run.returncode == 0, stderr
    table = rows(out)
    assert [table[p.name]["status"] for p in logs] == ["ok"] * 6, stderr
    assert table[f"{killed}.mcap"]["node"] != "127.0.0.4"       # the lost task was run again elsewhere
    for p in logs:
        assert json.loads((out / p.stem / "report.json").read_text())["scans"] == 120
    assert not list((out / ".fleet" / "work").glob("*")) if (out / ".fleet" / "work").exists() else True
