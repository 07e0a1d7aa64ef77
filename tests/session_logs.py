"""Logs for the multi-session tests: sessions of one robot in the polygon room (tests/planar_world.py),
each with odometry that starts at zero wherever the session starts (where it starts is unknown to
trundle), and a drive through another room."""

from __future__ import annotations

import math
from itertools import pairwise
from pathlib import Path

import numpy as np

from tests.planar_world import ROOM, scan
from tests.test_slam import loop_path
from trundle.fusion.geometry import relative, wrap_angle
from trundle.logs import messages as m
from trundle.logs.importers import write_log

START_NS = 1_780_000_000 * 10**9

# Another room: 12 m x 5 m with two stubs and a short wall, nothing like ROOM
OTHER_ROOM = np.array([
    [-6.0, -2.5, 6.0, -2.5], [6.0, -2.5, 6.0, 2.5], [6.0, 2.5, -6.0, 2.5], [-6.0, 2.5, -6.0, -2.5],
    [-2.0, -2.5, -2.0, -1.6], [2.5, 2.5, 2.5, 1.6], [4.5, -0.2, 5.2, -0.2],
]) + np.array([0.0123, 0.0271, 0.0123, 0.0271])
OTHER_WAYPOINTS = np.array([(-4.0, -1.0), (4.0, -1.0), (4.0, 1.0), (-4.0, 1.0), (-4.0, -1.0)])


def room_session(path: Path, truth: np.ndarray, start_ns: int = START_NS, walls: np.ndarray = ROOM,
                 seed: int = 0, beams: int = 181, robot: str = "robot-a") -> Path:
    """An MCAP log of the robot ``robot`` at the ``truth`` poses (the walls' frame), 2 scans a second,
    270-degree scans of ``beams`` beams with 1 cm noise; its odometry is exact but starts at zero."""
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(start_ns, "base_link", "laser", 0.0, 0.0, 0.0),)),
              start_ns)]
    for k, pose in enumerate(truth):
        stamp = start_ns + 10**9 * (k + 1) // 2
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *relative(truth[0], pose)), stamp))
        items.append(("/scan", scan(walls, pose, beams=beams, fov=math.radians(270.0), noise_m=0.01, seed=seed + k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_log(items, path, metadata={"command": "test", "host": robot})
    return path


def room_loop() -> np.ndarray:
    """The room loop's poses, two laps, 0.3 m steps (227 poses, one lap is the first 113)."""
    return loop_path(laps=2, step_m=0.3)


def other_room_drive(step_m: float = 0.3, turn_step_rad: float = math.radians(30.0)) -> np.ndarray:
    """Poses driving once round OTHER_WAYPOINTS: straight steps, turning on the spot at corners."""
    poses, heading = [], 0.0
    for a, b in pairwise(OTHER_WAYPOINTS):
        target = math.atan2(b[1] - a[1], b[0] - a[0])
        turn = float(wrap_angle(target - heading))
        for k in range(1, int(math.ceil(abs(turn) / turn_step_rad)) + 1):
            poses.append((a[0], a[1], heading + turn * min(1.0, k * turn_step_rad / abs(turn))))
        heading = target
        for s in np.arange(0.0, float(np.hypot(*(b - a))), step_m):
            poses.append((a[0] + s * math.cos(heading), a[1] + s * math.sin(heading), heading))
    return np.array(poses)
