"""The motion model learns from the tracked poses how far the next scan can be: predictor, spread, velocity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trundle.fusion.geometry import compose
from trundle.fusion.odometry.motion_model import MotionModel

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
