"""The simulator's ground truth of a demo log: each logged scan and camera frame matched to what an
emulator made, so it gets the true time it was made at and the robot's true pose then.

A logged scan is matched by its content to the scan the laser emulator cast, a logged frame by its
JPEG bytes to the frame the camera emulator rendered: a stamp the drivers got wrong cannot hide
behind a time match.
"""

from __future__ import annotations

import collections
import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from trundle.fusion.evaluation.trajectory_errors import Trajectory
from trundle.logs import messages as m
from trundle.logs.reader import LogReader
from trundle.logs.topics import IMAGE_TOPIC, SCAN_TOPIC
from trundle.tools.emulators.sim_devices import SimDevices
from trundle.tools.sim.robot import RobotSim


@dataclass(eq=False)
class Recording:
    """A recorded run: the log and its ground truth (base_link poses in the world frame).

    ``scans`` holds, at each logged scan's stamp, the pose the robot had when the laser emulator
    cast that scan's first beam (the instant a LaserScan's stamp means), and ``scan_true_ns`` that
    true time (host clock); ``frames`` and
    ``frame_true_ns`` the same for each logged camera frame. ``unmatched`` counts logged messages
    no emulator record explained (0 expected). ``cpu_s``: CPU time of the emulators (this
    process) and of the daemon process while recording; ``emulator_late_ms`` how late each
    emulator was at most while the robot drove (a busy machine starves them: timing suffers).
    """

    log: Path
    scans: Trajectory
    frames: Trajectory
    scan_true_ns: np.ndarray
    frame_true_ns: np.ndarray
    unmatched: dict[str, int]
    robot_time_s: float
    cpu_s: dict[str, float]
    emulator_late_ms: dict[str, float | None]


class FrameTimes:
    """When the camera emulator rendered each frame (host ns), by the SHA-1 of the frame's JPEG.

    Wraps the emulator's ``frame_at``: the time is the one ``SimDevices`` rendered at (the last
    entry of its camera activity), the JPEG is encoded as the emulator encodes it (same quality,
    deterministic), so a logged frame's bytes name the instant it shows.
    """

    def __init__(self, devices: SimDevices) -> None:
        """Start noting the frames of ``devices``' camera emulator (started: the emulator exists)."""
        emulator = devices.camera_emulator
        assert emulator is not None, "start the devices first"
        self.activity, self.quality = devices.activity["camera"], emulator.quality
        self.times: dict[bytes, list[int]] = collections.defaultdict(list)
        self._render = emulator.frame_at
        emulator.frame_at = self._frame_at

    def _frame_at(self, t_s: float) -> np.ndarray:
        """The emulator's frame at robot time ``t_s`` (s), its JPEG's digest noted with the host time."""
        image = self._render(t_s)
        ok, jpeg = cv2.imencode(".jpg", image, (cv2.IMWRITE_JPEG_QUALITY, self.quality))
        if ok:
            self.times[hashlib.sha1(jpeg.tobytes()).digest()].append(self.activity[-1])
        return image


def scan_ground_truth(log: Path, sim: RobotSim, devices: SimDevices) -> tuple[Trajectory, np.ndarray, int]:
    """The robot's true pose for every logged scan, found by the scan's content among those the
    laser emulator cast: the trajectory (at the logged stamps), the true host time (ns) of each
    scan, and how many logged scans matched none."""
    assert devices.lrf_device is not None
    dmin = devices.scip_model.params.dmin
    cast: dict[bytes, list[int]] = collections.defaultdict(list)
    for sent in devices.lrf_device.sent:
        cast[np.where(sent.distances >= dmin, sent.distances, -1).astype(np.int64).tobytes()].append(
            devices.first_beam_ns(sent.rear_ns))

    def true_ns(msg: m.LaserScan) -> int | None:
        ranges = msg.ranges.astype(np.float64)
        key = np.where(np.isfinite(ranges), np.round(ranges * 1000.0), -1).astype(np.int64).tobytes()
        return _nearest(cast.get(key), msg.stamp_ns)

    return _ground_truth(log, SCAN_TOPIC, true_ns, sim, devices)


def frame_ground_truth(log: Path, sim: RobotSim, devices: SimDevices, frame_times: FrameTimes
                       ) -> tuple[Trajectory, np.ndarray, int]:
    """The robot's true pose for every logged camera frame, found by its JPEG bytes among the
    frames the camera emulator rendered: the trajectory (at the logged stamps), the true host
    time (ns) of each frame, and how many logged frames matched none."""
    def true_ns(msg: m.CompressedImage) -> int | None:
        return _nearest(frame_times.times.get(hashlib.sha1(bytes(msg.data)).digest()), msg.stamp_ns)

    return _ground_truth(log, IMAGE_TOPIC, true_ns, sim, devices)


def _nearest(times: list[int] | None, stamp_ns: int) -> int | None:
    """Of the times an identical output was made (a robot standing still makes many), the one nearest the stamp."""
    return min(times, key=lambda t: abs(t - stamp_ns)) if times else None


def _ground_truth(log: Path, topic: str, true_ns: Callable[[Any], int | None], sim: RobotSim, devices: SimDevices
                  ) -> tuple[Trajectory, np.ndarray, int]:
    """Poses at the true times ``true_ns(msg)`` of ``topic``'s messages, stamped as logged."""
    stamps: list[int] = []
    times: list[int] = []
    unmatched = 0
    with LogReader(log) as reader:
        for item in reader.messages(topics=[topic]):
            msg = cast(m.LaserScan | m.CompressedImage, item.msg)  # the demo's scan or image topic
            t = true_ns(msg)
            if t is None:
                unmatched += 1
                continue
            stamps.append(msg.stamp_ns)
            times.append(t)
    poses = [sim.pose_at(devices.sim_time(t)) for t in times]
    return (Trajectory(np.array(stamps, np.int64), np.array(poses).reshape(-1, 3)), np.array(times, np.int64),
            unmatched)
