"""The impairment model does what its formula says."""

import numpy as np

from trundle.tools.sim.sensor_model import RangeImpairment


def test_formula_without_noise() -> None:
    model = RangeImpairment(gain=1.01, bias=0.02, quadratic=0.003, centre=2.0, hysteresis=0.01, quantum=0)
    rising = model(np.array([1.0, 3.0]))
    np.testing.assert_allclose(rising, [1.01 + 0.02 + 0.003 + 0.005, 3.03 + 0.02 + 0.003 + 0.005])
    falling = model(np.array([0.5, 2.0]))
    np.testing.assert_allclose(falling, [0.505 + 0.02 + 0.003 * 2.25 - 0.005, 2.02 + 0.02 - 0.005])
    held = model(np.array([0.5, 2.0]))  # standing still keeps the last direction
    np.testing.assert_allclose(held, falling)


def test_quantum_noise_and_invalid_passthrough() -> None:
    model = RangeImpairment(noise_std=0.01, quantum=0.001, seed=3)
    out = model(np.full(20000, 2.0))
    assert np.allclose(out * 1000, np.round(out * 1000))
    assert abs(out.std() - 0.01) < 0.0005
    special = model(np.array([np.inf, np.nan, 1.0]))
    assert np.isposinf(special[0]) and np.isnan(special[1])
