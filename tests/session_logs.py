"""Logs for the multi-session tests: sessions of one robot in the polygon room (tests/planar_world.py),
each with odometry starting at zero wherever the session starts (its start is unknown to trundle), and
a log of another room; plus the real logs cut in two at a place both halves visit (:func:`split_time`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tests.planar_world import ROOM, scan
from tests.test_slam import loop_path
from trundle.fusion.geometry import relative
from trundle.logs import messages as m
from trundle.logs.importers import write_log

START_NS = 1_780_000_000 * 10**9

# Another room: 12 m x 5 m with two stubs, nothing like ROOM
OTHER_ROOM = np.array([
    [-6.0, -2.5, 6.0, -2.5], [6.0, -2.5, 6.0, 2.5], [6.0, 2.5, -6.0, 2.5], [-6.0, 2.5, -6.0, -2.5],
    [-2.0, -2.5, -2.0, -0.7], [2.5, 2.5, 2.5, 0.9], [4.0, -1.0, 4.6, -1.0],
]) + np.array([0.0123, 0.0271, 0.0123, 0.0271])


def room_session(path: Path, truth: np.ndarray, start_ns: int = START_NS, walls: np.ndarray = ROOM,
                 seed: int = 0) -> Path:
    """An MCAP log of the robot at the ``truth`` poses (ROOM frame), 2 scans a second, 270-degree scans with
    1 cm noise; its odometry is exact but starts at zero (the odom frame is where the session starts)."""
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(start_ns, "base_link", "laser", 0.0, 0.0, 0.0),)),
              start_ns)]
    for k, pose in enumerate(truth):
        stamp = start_ns + 10**9 * (k + 1) // 2
        odom = relative(truth[0], pose)
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *odom), stamp))
        items.append(("/scan", scan(walls, pose, beams=181, fov=math.radians(270.0), noise_m=0.01, seed=seed + k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_log(items, path, metadata={"command": "test"})
    return path


def room_loop() -> np.ndarray:
    """The room loop's poses, two laps, 0.3 m steps."""
    return loop_path(laps=2, step_m=0.3)
