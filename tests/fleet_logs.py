"""Small robot logs for the fleet tests: odometry and 270-degree scans of a drive through the
polygon room (tests/planar_world.py), stamped at a chosen start time and named for a robot."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tests.planar_world import ROOM, scan
from tests.test_slam import loop_path
from trundle.logs import messages as m
from trundle.logs.importers import write_log

START_NS = 1_780_000_000 * 10**9   # 2026-05-28 UTC: robots' logs are in epoch time


def robot_log(path: Path, robot: str, start_ns: int = START_NS, scans: int = 20, offset: int = 0,
              noise_m: float = 0.01, still: bool = False) -> Path:
    """An MCAP log of ``scans`` poses of the room loop from pose ``offset`` on (all at that pose
    if ``still``), 2 scans a second, with exact odometry, the recording ``host`` named ``robot``
    (as `trundle record` on the robot writes it) and laser range noise ``noise_m`` (m)."""
    loop = loop_path(laps=2, step_m=0.3)
    poses = np.repeat(loop[offset:offset + 1], scans, axis=0) if still else loop[offset:offset + scans]
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(start_ns, "base_link", "laser", 0.0, 0.0, 0.0),)),
              start_ns)]
    for k, pose in enumerate(poses):
        stamp = start_ns + 10**9 * (k + 1) // 2
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *pose), stamp))
        items.append(("/scan", scan(ROOM, pose, beams=181, fov=math.radians(270.0), noise_m=noise_m, seed=k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_log(items, path, metadata={"command": "test", "host": robot})
    return path


def corrupt_log(path: Path, source: Path, keep: int = 300) -> Path:
    """``source`` cut after ``keep`` bytes with the rest garbled: the MCAP magic and header survive,
    no message does."""
    data = bytearray(source.read_bytes()[:keep])
    data[40:] = np.random.default_rng(7).integers(0, 256, len(data) - 40, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    return path
