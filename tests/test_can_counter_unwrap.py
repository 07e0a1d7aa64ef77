"""Counter unwrapping of any width or range."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers.counter_unwrap import CounterUnwrapper, unwrap, wrap_delta

moduli = st.one_of(st.sampled_from([2**8, 2**12, 2**16, 2**24, 2**32, 3600, 100_000, 2**64]), st.integers(3, 10**6))


@settings(max_examples=200, deadline=None)
@given(moduli, st.data())
def test_unwrap_recovers_the_true_count(modulus, data):
    half = modulus // 2
    steps = data.draw(st.lists(st.integers(-half + 1, half - 1), min_size=1, max_size=60))
    start = data.draw(st.integers(-(2**40), 2**40))
    true = start + np.concatenate(([0], np.cumsum(np.array(steps, dtype=object)))).astype(object)
    raw = [int(v) % modulus for v in true]
    if modulus <= 2**62:
        assert unwrap(np.array(raw), modulus, start=start).tolist() == [int(v) for v in true]
    counter = CounterUnwrapper(modulus)
    got = [counter.update(r) for r in raw]
    assert [g - got[0] for g in got] == [int(v) - start for v in true]


def test_signed_32_bit_wrap():
    # an i32 shadow count running past 2**31 - 1 continues upward
    counter = CounterUnwrapper(2**32)
    assert [counter.update(v) for v in (2**31 - 2, 2**31 - 1, -(2**31), -(2**31) + 5)] == [
        2**31 - 2, 2**31 - 1, 2**31, 2**31 + 5]
    assert counter.wraps == 1


def test_unsigned_16_bit_wrap_backwards():
    assert unwrap(np.array([3, 1, 65534, 65000]), 2**16).tolist() == [3, 1, -2, -536]
    assert wrap_delta(0, 3599, 3600) == 1 and wrap_delta(3599, 0, 3600) == -1
