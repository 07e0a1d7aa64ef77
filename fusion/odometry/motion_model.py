"""A motion model that learns from the log how far the next scan can be: no fixed speed or rate.

Two predictions of the motion to the next scan are kept side by side: *standstill* (no motion)
and *constant velocity* (robot frame; measured over at least the log's typical scan interval
back, so one short interval, e.g. two scans stamped 40 ms apart in a 4 Hz log, cannot make a
wild velocity). After every
tracked scan the error each would have made is recorded. The model predicts with whichever has
had the smaller recent errors, and its uncertainty is the spread of those errors, so the search
window follows the log: a 10 Hz laser on a slow robot gets a window of centimetres, a log that
keeps one scan per metre travelled (GMapping's output) one of about a metre. Errors are recorded
in units of the log's typical scan interval, so a dropout of several intervals widens the window
in proportion. Until ``warmup`` errors are known a prior stands in.
"""

from __future__ import annotations

from bisect import bisect_left, insort
from collections import deque
from dataclasses import dataclass

import numpy as np

from trundle.fusion.geometry import relative


@dataclass(frozen=True)
class MotionPrediction:
    """Predicted step (robot frame at the last scan), its per-axis standard deviations and largest
    recent error (x m, y m, theta rad), and which predictor made it."""

    delta: np.ndarray
    sigma: np.ndarray
    largest: np.ndarray
    predictor: str
    learned: bool

    @property
    def covariance(self) -> np.ndarray:
        return np.diag(self.sigma ** 2)


class MotionModel:
    """Standstill or constant-velocity prediction with errors learned over the last ``history`` scans.

    ``prior_sigma`` (x m, y m, theta rad) is the uncertainty per scan interval before ``warmup``
    errors are known; ``floor_sigma`` the least uncertainty ever claimed (the matcher's own
    precision: a grid cell and the angular step).
    """

    PREDICTORS = ("standstill", "constant_velocity")

    def __init__(self, prior_sigma: tuple[float, float, float], floor_sigma: tuple[float, float, float],
                 history: int = 50, warmup: int = 8) -> None:
        self.prior_sigma = np.asarray(prior_sigma, np.float64)
        self.floor_sigma = np.asarray(floor_sigma, np.float64)
        self.warmup = int(warmup)
        self._errors = {name: _ErrorWindow(history) for name in self.PREDICTORS}
        self._intervals: deque[float] = deque(maxlen=history)
        self._sorted_intervals: list[float] = []  # the same, sorted: their median without sorting each scan
        self._typical_interval: float | None = None   # their median, until the next interval
        self._last: tuple[int, np.ndarray] | None = None
        self._tracked: deque[tuple[int, np.ndarray]] = deque(maxlen=history)
        self._velocity: np.ndarray | None = None  # per second, robot frame

    @property
    def velocity(self) -> np.ndarray:
        """The velocity (vx m/s, vy m/s, wz rad/s, robot frame) of the last tracked step (zeros at first)."""
        return np.zeros(3) if self._velocity is None else self._velocity.copy()

    def typical_interval_s(self) -> float:
        """Median interval between tracked scans (s); 0 before two scans."""
        if self._typical_interval is None:
            values, n = self._sorted_intervals, len(self._sorted_intervals)
            if not n:
                self._typical_interval = 0.0
            elif n % 2:
                self._typical_interval = values[n // 2]
            else:  # as numpy's median: the mean of the middle two
                self._typical_interval = (values[n // 2 - 1] + values[n // 2]) / 2.0
        return self._typical_interval

    def _guess(self, name: str, dt: float) -> np.ndarray:
        if name == "constant_velocity" and self._velocity is not None:
            return self._velocity * dt
        return np.zeros(3)

    def predict(self, dt_s: float) -> MotionPrediction:
        """The step expected over the next ``dt_s`` seconds and its uncertainty."""
        typical = self.typical_interval_s()
        intervals = max(1.0, dt_s / typical) if typical > 0 else 1.0
        if min(len(errors) for errors in self._errors.values()) < self.warmup:
            name = "constant_velocity" if self._velocity is not None else "standstill"
            sigma = self.prior_sigma * intervals
            return MotionPrediction(self._guess(name, dt_s), np.maximum(sigma, self.floor_sigma), 3.0 * sigma, name,
                                    False)
        scores = {name: float(np.sum(errors.rms() / self.floor_sigma)) for name, errors in self._errors.items()}
        name = min(scores, key=scores.__getitem__)
        errors = self._errors[name]
        sigma = np.maximum(errors.rms() * intervals, self.floor_sigma)
        return MotionPrediction(self._guess(name, dt_s), sigma, errors.largest() * intervals, name, True)

    def update(self, stamp_ns: int, pose: np.ndarray, tracked: bool = True) -> None:
        """Record the pose of a scan: when it was ``tracked`` (matched), each predictor's error (per
        typical interval) and the velocity; otherwise (a predicted pose) only the pose."""
        pose = np.asarray(pose, np.float64)
        if self._last is not None and tracked:
            last_stamp, last_pose = self._last
            dt = (stamp_ns - last_stamp) * 1e-9
            step = relative(last_pose, pose)
            if dt > 0:
                self._add_interval(dt)
                typical = self.typical_interval_s()
                scale = max(1.0, dt / typical) if typical > 0 else 1.0
                for name in self.PREDICTORS:
                    if name == "constant_velocity" and self._velocity is None:
                        continue
                    self._errors[name].add(relative(self._guess(name, dt), step) / scale)
        if tracked:
            self._tracked.append((int(stamp_ns), pose.copy()))
            self._velocity = self._measured_velocity()
        self._last = (int(stamp_ns), pose.copy())

    def _add_interval(self, dt: float) -> None:
        if len(self._intervals) == self._intervals.maxlen:
            del self._sorted_intervals[bisect_left(self._sorted_intervals, self._intervals[0])]
        self._intervals.append(dt)
        insort(self._sorted_intervals, dt)
        self._typical_interval = None

    def _measured_velocity(self) -> np.ndarray | None:
        """Velocity from the newest tracked pose back to the latest one at least a typical interval older."""
        now_ns, now = self._tracked[-1]
        span = self.typical_interval_s()
        for stamp_ns, pose in reversed(self._tracked):
            dt = (now_ns - stamp_ns) * 1e-9
            if dt > 0 and dt >= span * (1.0 - 1e-9):
                return relative(pose, now) / dt
        return None


class _ErrorWindow:
    """The last ``size`` errors (x, y, theta) of one predictor, oldest first, in one array, with their
    root mean square and largest absolute value per axis kept until the next error (each scan reads
    them, a scan adds one)."""

    def __init__(self, size: int) -> None:
        self._rows = np.empty((size, 3))
        self._count = 0
        self._rms: np.ndarray | None = None
        self._largest: np.ndarray | None = None

    def __len__(self) -> int:
        return self._count

    def add(self, error: np.ndarray) -> None:
        if self._count == len(self._rows):
            self._rows[:-1] = self._rows[1:]
            self._rows[-1] = error
        else:
            self._rows[self._count] = error
            self._count += 1
        self._rms = self._largest = None

    def rms(self) -> np.ndarray:
        if self._rms is None:
            self._rms = np.sqrt(np.mean(np.abs(self._rows[:self._count]) ** 2, axis=0))
        return self._rms

    def largest(self) -> np.ndarray:
        if self._largest is None:
            self._largest = np.abs(self._rows[:self._count]).max(axis=0)
        return self._largest
