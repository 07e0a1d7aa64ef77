"""The motion model learns from the tracked poses how far the next scan can be: predictor, spread, velocity."""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.fusion.geometry import compose, relative
from trundle.fusion.odometry.motion_model import MotionModel, MotionPrediction

FLOOR = (0.05, 0.05, math.radians(0.5))
PRIOR = (0.3, 0.3, math.radians(10.0))


def feed(model: MotionModel, stamps_s, poses) -> None:
    for t, pose in zip(stamps_s, poses, strict=True):
        model.update(int(round(t * 1e9)), pose)


def test_prior_until_learned_then_constant_velocity_at_the_floor() -> None:
    model = MotionModel(PRIOR, FLOOR)
    first = model.predict(0.1)
    assert not first.learned and first.predictor == "standstill" and np.allclose(first.sigma, PRIOR)
    stamps = np.arange(30) * 0.1
    feed(model, stamps, [(0.5 * t, 0.0, 0.0) for t in stamps])  # 0.5 m/s straight, exactly
    prediction = model.predict(0.1)
    assert prediction.learned and prediction.predictor == "constant_velocity"
    np.testing.assert_allclose(prediction.delta, [0.05, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(prediction.sigma, FLOOR)  # no error at all: the matcher's precision is the floor
    np.testing.assert_allclose(model.velocity, [0.5, 0.0, 0.0], atol=1e-12)


def test_standstill_wins_when_the_motion_reverses_every_scan() -> None:
    model = MotionModel(PRIOR, FLOOR)
    stamps = np.arange(40) * 0.1
    feed(model, stamps, [(0.1 * (k % 2), 0.0, 0.0) for k in range(40)])  # back and forth by 10 cm
    prediction = model.predict(0.1)
    assert prediction.predictor == "standstill" and np.allclose(prediction.delta, 0.0)
    assert prediction.sigma[0] == pytest.approx(0.1) and prediction.largest[0] == pytest.approx(0.1)


def test_spread_follows_the_log_and_a_gap_widens_it() -> None:
    # a robot turning at a rate that changes by +-0.2 rad/s each scan, 10 Hz and 1 Hz logs of the same motion
    sigmas = {}
    for period in (0.1, 1.0):
        model = MotionModel(PRIOR, (0.001, 0.001, 1e-4))
        rates = 0.5 + 0.2 * np.where(np.arange(60) % 2, 1.0, -1.0)
        poses, pose = [], np.zeros(3)
        for rate in rates:
            pose = compose(pose, np.array([0.0, 0.0, rate * period]))
            poses.append(pose)
        feed(model, np.arange(60) * period, poses)
        sigmas[period] = model.predict(period).sigma[2]
        assert model.predict(5 * period).sigma[2] == pytest.approx(5 * sigmas[period])  # a dropout of 5 scans
    assert sigmas[1.0] == pytest.approx(10 * sigmas[0.1], rel=1e-6)


def test_a_short_interval_does_not_make_a_wild_velocity() -> None:
    # 4 Hz, 0.4 rad/s; two scans stamped 40 ms apart in the middle, whose 16 mrad would be 0.4 rad/s too,
    # but their poses carry 5 mrad of matching noise: over 40 ms that alone is 0.125 rad/s
    stamps = list(np.arange(20) * 0.25) + [4.79, 5.04, 5.29]
    poses = [(0.0, 0.0, 0.4 * t) for t in stamps]
    poses[-2] = (0.0, 0.0, 0.4 * stamps[-2] + 0.005)
    model = MotionModel(PRIOR, FLOOR)
    feed(model, stamps[:-1], poses[:-1])
    assert model.velocity[2] == pytest.approx(0.4 + 0.005 / 0.25, rel=0.05)  # measured over a typical interval


class ListMotionModel(MotionModel):
    """The model as first written (deques of errors and intervals, numpy over them at every call): the
    reference the kept statistics must equal to the bit."""

    def __init__(self, prior_sigma, floor_sigma, history=50, warmup=8) -> None:
        super().__init__(prior_sigma, floor_sigma, history, warmup)
        self._lists = {name: deque(maxlen=history) for name in self.PREDICTORS}
        self._dts: deque[float] = deque(maxlen=history)

    def typical_interval_s(self) -> float:
        return float(np.median(self._dts)) if self._dts else 0.0

    def predict(self, dt_s: float) -> MotionPrediction:
        typical = self.typical_interval_s()
        intervals = max(1.0, dt_s / typical) if typical > 0 else 1.0
        if min(len(errors) for errors in self._lists.values()) < self.warmup:
            name = "constant_velocity" if self._velocity is not None else "standstill"
            sigma = self.prior_sigma * intervals
            return MotionPrediction(self._guess(name, dt_s), np.maximum(sigma, self.floor_sigma), 3.0 * sigma, name,
                                    False)
        scores = {}
        for name, errors in self._lists.items():
            e = np.abs(np.array(errors))
            scores[name] = float(np.sum(np.sqrt(np.mean(e ** 2, axis=0)) / self.floor_sigma))
        name = min(scores, key=scores.__getitem__)
        e = np.abs(np.array(self._lists[name]))
        sigma = np.maximum(np.sqrt(np.mean(e ** 2, axis=0)) * intervals, self.floor_sigma)
        return MotionPrediction(self._guess(name, dt_s), sigma, e.max(axis=0) * intervals, name, True)

    def update(self, stamp_ns: int, pose: np.ndarray, tracked: bool = True) -> None:
        pose = np.asarray(pose, np.float64)
        if self._last is not None and tracked:
            last_stamp, last_pose = self._last
            dt = (stamp_ns - last_stamp) * 1e-9
            step = relative(last_pose, pose)
            if dt > 0:
                self._dts.append(dt)
                typical = self.typical_interval_s()
                scale = max(1.0, dt / typical) if typical > 0 else 1.0
                for name in self.PREDICTORS:
                    if name == "constant_velocity" and self._velocity is None:
                        continue
                    self._lists[name].append(relative(self._guess(name, dt), step) / scale)
        if tracked:
            self._tracked.append((int(stamp_ns), pose.copy()))
            self._velocity = self._measured_velocity()
        self._last = (int(stamp_ns), pose.copy())


scan = st.tuples(st.integers(0, 300_000_000),  # ns since the last scan: repeats and gaps included
                 st.tuples(*[st.floats(-0.5, 0.5, allow_nan=False)] * 3),  # the step
                 st.booleans(), st.floats(0.0, 1.0, allow_nan=False))  # tracked; the next prediction's dt (s)


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 12), st.integers(1, 6), st.lists(scan, max_size=60))
def test_the_kept_statistics_equal_numpy_over_the_whole_window(history, warmup, scans) -> None:
    kept, reference = MotionModel(PRIOR, FLOOR, history, warmup), ListMotionModel(PRIOR, FLOOR, history, warmup)
    stamp, pose = 0, np.zeros(3)
    for gap_ns, step, tracked, dt in scans:
        stamp, pose = stamp + gap_ns, compose(pose, np.array(step))
        for model in (kept, reference):
            model.update(stamp, pose, tracked)
        assert kept.typical_interval_s() == reference.typical_interval_s()
        a, b = kept.predict(dt), reference.predict(dt)
        assert (a.predictor, a.learned) == (b.predictor, b.learned)
        pairs = ((a.delta, b.delta), (a.sigma, b.sigma), (a.largest, b.largest), (kept.velocity, reference.velocity))
        assert all(np.array_equal(x, y) for x, y in pairs)
