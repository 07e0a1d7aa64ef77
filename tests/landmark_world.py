"""A simulated landmark world for EKF-SLAM and graph tests: a robot drives a loop among point
landmarks; its odometry and sightings carry noise drawn from exactly the models the estimators
assume (so NEES must come out right), as Odometry and LandmarkList messages."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from trundle.fusion.geometry import compose, relative, wrap_angle
from trundle.fusion.odometry.increments import MotionNoise
from trundle.logs import messages as m

SIGMA_RANGE_M = 0.05
SIGMA_BEARING_RAD = math.radians(1.0)


@dataclass
class LandmarkRun:
    """True poses at every odometry reading, the messages (topic, msg) in time order and the landmarks."""

    stamps_ns: np.ndarray
    truth: np.ndarray
    messages: list[tuple[str, m.Message]]
    landmarks: np.ndarray
    ids: list[str]
    seen: dict[int, list[int]]  # stamp -> the true landmark of each sighting of that LandmarkList


def ring_of_landmarks(count: int, radius: float, rng: np.random.Generator, jitter: float = 1.0) -> np.ndarray:
    """Landmarks around a circle of ``radius`` m (the robot drives near it), jittered."""
    angles = np.linspace(0, 2 * math.pi, count, endpoint=False)
    ring = radius + rng.uniform(-jitter, jitter, count) + np.where(np.arange(count) % 2, 1.5, -1.5)
    return np.column_stack([ring * np.cos(angles), ring * np.sin(angles)])


def simulate(rng: np.random.Generator, landmarks: np.ndarray, *, laps: float = 1.0, radius: float = 6.0,
             speed: float = 0.5, rate_hz: float = 20.0, sight_every: int = 4, max_range: float = 5.0,
             noise: MotionNoise | None = None, known_ids: bool = True, start_pose=(6.0, 0.0, math.pi / 2),
             sigma_range: float = SIGMA_RANGE_M, sigma_bearing: float = SIGMA_BEARING_RAD) -> LandmarkRun:
    """Drive ``laps`` circles of ``radius`` m at ``speed`` m/s; odometry at ``rate_hz`` with noise drawn
    from ``noise`` (the estimators' own model), sightings every ``sight_every`` readings of the
    landmarks within ``max_range`` (ids when ``known_ids``, else anonymous)."""
    noise = noise or MotionNoise()
    dt = 1.0 / rate_hz
    steps = int(laps * 2 * math.pi * radius / speed / dt)
    true_step = np.array([speed * dt, 0.0, speed / radius * dt])
    pose = np.asarray(start_pose, np.float64)
    odom = np.zeros(3)
    stamps, truth, messages = [], [], []
    seen_by_stamp: dict[int, list[int]] = {}
    ids = [str(k) for k in range(len(landmarks))]
    for k in range(steps + 1):
        stamp = 1_000_000_000 + int(round(k * dt * 1e9))
        if k:
            pose = compose(pose, true_step)
            q = noise.step_covariance(true_step, dt)
            odom = compose(odom, true_step + rng.multivariate_normal(np.zeros(3), q))
        stamps.append(stamp)
        truth.append(pose.copy())
        messages.append(("/odom", m.Odometry(stamp, "odom", "base_link", *odom, vx=speed, wz=speed / radius)))
        if k % sight_every == 0:
            local = relative(
                np.broadcast_to(pose, (len(landmarks), 3)), np.column_stack([landmarks, np.zeros(len(landmarks))])
            )
            seen, which = [], []
            for j in np.flatnonzero(np.hypot(local[:, 0], local[:, 1]) <= max_range):
                which.append(int(j))
                r = float(np.hypot(*local[j, :2])) + rng.normal(0, sigma_range)
                b = float(wrap_angle(math.atan2(local[j, 1], local[j, 0]) + rng.normal(0, sigma_bearing)))
                seen.append(m.LandmarkObservation(ids[j] if known_ids else "", r, b,
                                                  np.diag([sigma_range ** 2, sigma_bearing ** 2])))
            if seen:
                order = rng.permutation(len(seen))
                messages.append(("/landmarks", m.LandmarkList(stamp, "base_link", tuple(seen[i] for i in order))))
                seen_by_stamp[stamp] = [which[i] for i in order]
    return LandmarkRun(np.array(stamps, np.int64), np.array(truth), messages, landmarks, ids, seen_by_stamp)


def in_map_frame(run: LandmarkRun) -> tuple[np.ndarray, np.ndarray]:
    """True poses and landmarks expressed in the map frame of the estimators (the first pose at the origin)."""
    origin = run.truth[0]
    poses = relative(np.broadcast_to(origin, run.truth.shape), run.truth)
    points = relative(np.broadcast_to(origin, (len(run.landmarks), 3)),
                      np.column_stack([run.landmarks, np.zeros(len(run.landmarks))]))[:, :2]
    return poses, points
