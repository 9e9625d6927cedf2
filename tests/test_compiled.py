"""The kernels' shared helpers (sim.compiled) against what they replicate."""

import numpy as np
from hypothesis import given, settings, strategies as st

from sim.compiled import numpy_sum, numpy_sum_where


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2000), st.integers(0, 2**32 - 1), st.floats(-8.0, 8.0))
def test_numpy_sum_is_numpys_sum_bit_for_bit(count, seed, spread):
    """Every length through the pairwise recursion (below 8, up to 128, halves above), over values of
    magnitudes 10^-spread .. 10^spread where the order of additions shows in the last bits."""
    rng = np.random.default_rng(seed)
    values = rng.standard_normal(count) * 10.0 ** rng.uniform(-abs(spread), abs(spread), count)
    assert numpy_sum(values) == np.add.reduce(values)
    assert numpy_sum(values[: count // 3]) == np.add.reduce(values[: count // 3])


def test_numpy_sum_of_nothing_and_of_specials():
    assert numpy_sum(np.empty(0)) == 0.0
    assert np.isnan(numpy_sum(np.array([1.0, np.nan, 2.0])))
    assert numpy_sum(np.array([np.inf] * 9)) == np.inf


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 400), st.integers(0, 2**32 - 1), st.floats(0.0, 1.0))
def test_numpy_sum_where_is_numpys_sum_of_the_picked(count, seed, share):
    rng = np.random.default_rng(seed)
    values = rng.standard_normal(count) * 10.0 ** rng.uniform(-6, 6, count)
    where = rng.random(count) < share
    total, picked = numpy_sum_where(values, where)
    assert picked == int(where.sum())
    assert total == np.add.reduce(values[where])
