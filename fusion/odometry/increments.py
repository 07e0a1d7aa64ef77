"""Odometry increments and their covariance, composed over many odometry readings.

Landmark SLAM predicts between sightings, which arrive far less often than odometry; the motion in
between is the composition of every reading's increment, and its covariance is propagated step by
step (``Sigma <- J_a Sigma J_a^T + J_b Q J_b^T`` for ``a (+) b``), so a curved path's heading error
shows as the lateral error it causes. The per-step noise ``Q`` is a random walk: its variances
grow linearly with the distance driven, the angle turned and the time taken, so the accumulated
covariance does not depend on how often the odometry reports (a floor per reading would).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from trundle.fusion.geometry import compose, relative, wrap_angle


@dataclass(frozen=True)
class MotionNoise:
    """Random-walk odometry noise: standard deviation after one metre, one radian or one second.

    ``xy_per_m`` (m/sqrt(m)) along and across the motion per distance driven; ``theta_per_m``
    (rad/sqrt(m)) heading per distance; ``theta_per_rad`` (rad/sqrt(rad)) heading per angle
    turned; ``xy_per_s`` (m/sqrt(s)) and ``theta_per_s`` (rad/sqrt(s)) per second whatever the
    motion (wheel slip, a robot pushed while standing). Defaults suit a small differential-drive
    robot on a hard floor, on the generous side: an estimator trusting its odometry too much
    becomes inconsistent, one trusting it too little only leans more on its landmarks.
    """

    xy_per_m: float = 0.1
    theta_per_m: float = 0.1
    theta_per_rad: float = 0.1
    xy_per_s: float = 0.005
    theta_per_s: float = 0.01

    def step_covariance(self, step_xyt, dt_s: float) -> np.ndarray:
        """3x3 covariance (robot frame at the step's start) of one odometry increment taking ``dt_s``."""
        distance, turn = math.hypot(float(step_xyt[0]), float(step_xyt[1])), abs(float(step_xyt[2]))
        dt = max(float(dt_s), 0.0)
        vxy = self.xy_per_m ** 2 * distance + self.xy_per_s ** 2 * dt
        vth = self.theta_per_m ** 2 * distance + self.theta_per_rad ** 2 * turn + self.theta_per_s ** 2 * dt
        return np.diag([vxy, vxy, vth])


def compose_jacobians(a_xyt, b_xyt) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of ``a (+) b`` by ``a`` and by ``b`` (3x3 each)."""
    c, s = math.cos(float(a_xyt[2])), math.sin(float(a_xyt[2]))
    bx, by = float(b_xyt[0]), float(b_xyt[1])
    ja = np.array([[1.0, 0.0, -s * bx - c * by], [0.0, 1.0, c * bx - s * by], [0.0, 0.0, 1.0]])
    jb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ja, jb


class IncrementAccumulator:
    """The composed increment since the last :meth:`reset` (robot frame at that instant), its
    covariance and the distance (m), turn (rad) and time (s) it took.

    Called once per odometry reading (tens of thousands a log), so :meth:`add` works on Python
    floats: ``J_a Sigma J_a^T`` and ``J_b Q J_b^T`` written out for the diagonal ``Q`` of
    :meth:`MotionNoise.step_covariance`.
    """

    def __init__(self, noise: MotionNoise | None = None) -> None:
        self.noise = noise or MotionNoise()
        self.reset()

    def reset(self) -> None:
        self._x = self._y = self._theta = 0.0
        self._s = [0.0] * 6  # xx, xy, xt, yy, yt, tt
        self.distance_m = 0.0
        self.turn_rad = 0.0
        self.duration_s = 0.0

    @property
    def delta(self) -> np.ndarray:
        return np.array([self._x, self._y, self._theta])

    @property
    def covariance(self) -> np.ndarray:
        xx, xy, xt, yy, yt, tt = self._s
        return np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])

    def add(self, step_xyt, dt_s: float) -> None:
        """Append one odometry increment (robot frame at its start) that took ``dt_s`` seconds."""
        bx, by, bt = float(step_xyt[0]), float(step_xyt[1]), float(step_xyt[2])
        dt = max(float(dt_s), 0.0)
        c, s = math.cos(self._theta), math.sin(self._theta)
        noise = self.noise
        distance, turn = math.hypot(bx, by), abs(bt)
        vxy = noise.xy_per_m ** 2 * distance + noise.xy_per_s ** 2 * dt
        vth = noise.theta_per_m ** 2 * distance + noise.theta_per_rad ** 2 * turn + noise.theta_per_s ** 2 * dt
        # J_a = [[1, 0, a], [0, 1, b], [0, 0, 1]] with a = -s bx - c by, b = c bx - s by
        a, b = -s * bx - c * by, c * bx - s * by
        xx, xy, xt, yy, yt, tt = self._s
        nxt, nyt = xt + a * tt, yt + b * tt
        nxx = xx + 2 * a * xt + a * a * tt
        nxy = xy + a * yt + b * xt + a * b * tt
        nyy = yy + 2 * b * yt + b * b * tt
        # J_b Q J_b^T with J_b = blockdiag(R(theta), 1) and Q = diag(vxy, vxy, vth): isotropic in x-y
        self._s = [nxx + vxy, nxy, nxt, nyy + vxy, nyt, tt + vth]
        self._x += c * bx - s * by
        self._y += s * bx + c * by
        self._theta = float(wrap_angle(self._theta + bt))
        self.distance_m += distance
        self.turn_rad += turn
        self.duration_s += dt


@dataclass(frozen=True)
class Increment:
    """The motion between two :meth:`OdometryIncrements.take` calls: ``delta`` (robot frame at the
    first) and its covariance, and the odometry readings on the way: their ``stamps_ns`` (k,) and
    ``partial`` (k, 3) poses in that same frame (for a trajectory at every reading)."""

    delta: np.ndarray
    covariance: np.ndarray
    stamps_ns: np.ndarray
    partial: np.ndarray


class OdometryIncrements:
    """Odometry messages in, the increment since the last :meth:`take` out, at any instant.

    Readings are kept until the next :meth:`take`, which turns those up to its stamp into
    increments in one vectorised step and composes them with their covariance
    (:class:`IncrementAccumulator`). A sighting's stamp falls between readings: the last reading's
    twist carries the pose on to it, for at most ``timeout_s`` (farther, the odometry counts as
    stale and the increment stops at the reading).
    """

    def __init__(self, noise: MotionNoise | None = None, timeout_s: float = 0.5) -> None:
        self.accumulator = IncrementAccumulator(noise)
        self.timeout_s = timeout_s
        self.readings = 0
        self.stale = 0
        self._pending: list[tuple[int, float, float, float, float, float]] = []  # stamp, x, y, theta, v, w
        self._ref: np.ndarray | None = None     # odometry pose at the last take
        self._ref_ns = 0
        self._last: tuple[int, float, float, float, float, float] | None = None  # last reading taken

    def add(self, odom) -> None:
        """One nav_msgs/Odometry-like reading (``stamp_ns``, ``x``, ``y``, ``theta``, ``vx``, ``wz``)."""
        self._pending.append((int(odom.stamp_ns), float(odom.x), float(odom.y), float(odom.theta), float(odom.vx),
                              float(odom.wz)))
        self.readings += 1

    @property
    def started(self) -> bool:
        return self._ref is not None or bool(self._pending)

    @property
    def pending_until(self) -> int | None:
        """Stamp of the last reading not yet taken (None if none)."""
        return self._pending[-1][0] if self._pending else None

    def take(self, stamp_ns: int) -> Increment:
        """The increment from the previous take to ``stamp_ns`` (robot frame at the previous take); restarts there."""
        due = [r for r in self._pending if r[0] <= stamp_ns]
        self._pending = [r for r in self._pending if r[0] > stamp_ns]
        origin = self._ref is None and bool(due)
        if origin:  # the first reading is the origin of the increments (its partial pose is zero)
            first = due.pop(0)
            self._ref, self._ref_ns, self._last = np.array(first[1:4]), first[0], first
        acc = self.accumulator
        acc.reset()
        if self._ref is None:
            return Increment(np.zeros(3), np.zeros((3, 3)), np.zeros(0, np.int64), np.zeros((0, 3)))
        stamps = np.array([self._ref_ns] + [r[0] for r in due], np.int64)
        chain = np.vstack([self._ref, np.array([r[1:4] for r in due]).reshape(-1, 3)])
        steps = relative(chain[:-1], chain[1:])
        partial = np.zeros((len(due), 3))
        for k, (step, dt) in enumerate(zip(steps, np.diff(stamps) * 1e-9, strict=True)):
            acc.add(step, dt)
            partial[k] = acc.delta
        if due:
            self._last = due[-1]
        assert self._last is not None
        last_ns, x, y, theta, v, w = self._last
        gap = (stamp_ns - last_ns) * 1e-9
        there = chain[-1]
        if gap > self.timeout_s:
            self.stale += 1
        elif gap > 0:
            there = compose(np.array([x, y, theta]), np.array([v * gap, 0.0, w * gap]))
            acc.add(relative(chain[-1], there), (stamp_ns - int(stamps[-1])) * 1e-9)
        self._ref, self._ref_ns = there, max(int(stamp_ns), int(stamps[-1]))
        if origin:
            return Increment(acc.delta, acc.covariance, stamps, np.vstack([np.zeros((1, 3)), partial]))
        return Increment(acc.delta, acc.covariance, stamps[1:], partial)
