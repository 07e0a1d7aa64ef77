"""The map self-check: each keyframe against the submaps it played no part in; a stretch that contradicts
the rest of the map fails it, a good map passes."""

from __future__ import annotations

import math

import numpy as np

from tests.planar_world import ROOM, scan
from tests.test_slam import loop_path
from trundle.fusion.geometry import compose, relative
from trundle.fusion.mapping.map_check import _stretches
from trundle.fusion.odometry.drift import drifting_odometry
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.grid_slam import Slam
from trundle.logs import messages as m


def mapped_room() -> Slam:
    """Two laps of the polygon room, drifting odometry, 2 Hz scans: a good map."""
    truth = loop_path(laps=2)
    odometry = drifting_odometry(truth, seed=5)
    slam = Slam(SlamConfig())
    for k, (pose, odo) in enumerate(zip(truth, odometry, strict=True)):
        stamp = 1_000_000_000 + k * 500_000_000
        slam.process("/odom", m.Odometry(stamp, "odom", "base_link", *odo))
        slam.process("/scan", scan(ROOM, pose, beams=271, fov=math.radians(270.0), noise_m=0.01, seed=k,
                                   stamp_ns=stamp, max_range=10.0))
    slam.finish()
    return slam


def test_a_good_map_passes_and_a_turned_stretch_fails_where_it_is() -> None:
    slam = mapped_room()
    good = slam.check_map()
    assert good.passed and good.consistency > 0.8 and good.compared_keyframes > 0.5 * slam.stats.keyframes
    # the keyframes of a stretch of the second lap put 15 degrees off, as a heading glitch the graph kept would
    poses = slam.graph.poses
    first, last = len(poses) // 2 + 10, len(poses) // 2 + 30
    pivot = poses[first]
    turn = np.array([0.0, 0.0, math.radians(15.0)])
    poses[first:last + 1] = compose(compose(pivot, turn), relative(pivot, poses[first:last + 1]))
    slam.graph.poses = poses
    broken = slam.check_map()
    assert not broken.passed and broken.consistency < good.consistency
    flagged = [(a, b) for a, b in broken.stretches if b - a + 1 >= broken.min_stretch]
    assert flagged and all(first - 2 <= a and b <= last + 2 for a, b in flagged)


def test_stretches_ignore_lone_keyframes_and_keep_a_broken_run_whole() -> None:
    values = np.full(40, 0.9)
    values[5] = 0.1  # one keyframe: a person walked by
    values[20:30] = 0.2
    values[24] = 0.7  # a keyframe inside the broken run that happens to agree
    values[33] = np.nan  # not compared
    assert _stretches(values) == [(20, 29)]
