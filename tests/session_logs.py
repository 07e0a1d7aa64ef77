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


# Point landmarks (marker ids) on ROOM's walls, seen within MARKER_RANGE_M
ROOM_MARKERS = {"3": (-4.9, 0.5), "17": (0.9, -2.0), "42": (4.9, 2.0), "71": (-1.0, 3.9)}
MARKER_RANGE_M = 4.0
MARKER_SIGMA_M = 0.01


def room_session(path: Path, truth: np.ndarray, start_ns: int = START_NS, walls: np.ndarray = ROOM,
                 seed: int = 0, beams: int = 181, robot: str = "robot-a",
                 markers: dict[str, tuple[float, float]] | None = None) -> Path:
    """An MCAP log of the robot ``robot`` at the ``truth`` poses (the walls' frame), 2 scans a second,
    270-degree scans of ``beams`` beams with 1 cm noise; its odometry is exact but starts at zero. With
    ``markers`` (id -> position in the walls' frame) each scan comes with a LandmarkList of those within
    MARKER_RANGE_M (positions with MARKER_SIGMA_M noise)."""
    items = [("/tf_static", m.TFMessage((m.TransformStamped.planar(start_ns, "base_link", "laser", 0.0, 0.0, 0.0),)),
              start_ns)]
    rng = np.random.default_rng(seed)
    for k, pose in enumerate(truth):
        stamp = start_ns + 10**9 * (k + 1) // 2
        items.append(("/odom", m.Odometry(stamp, "odom", "base_link", *relative(truth[0], pose)), stamp))
        items.append(("/scan", scan(walls, pose, beams=beams, fov=math.radians(270.0), noise_m=0.01, seed=seed + k,
                                    stamp_ns=stamp, max_range=10.0), stamp))
        seen = []
        for name, where in (markers or {}).items():
            local = relative(pose, np.array([*where, 0.0]))[:2]
            if np.hypot(*local) <= MARKER_RANGE_M:
                seen.append(m.LandmarkObservation.from_position(name, local + rng.normal(0.0, MARKER_SIGMA_M, 2),
                                                                np.eye(2) * MARKER_SIGMA_M ** 2))
        if seen:
            items.append(("/landmarks", m.LandmarkList(stamp, "base_link", tuple(seen)), stamp))
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
