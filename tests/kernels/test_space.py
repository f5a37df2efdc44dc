"""Minimum image and wrapping."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from numba import njit

from kernels.space import minimum_image, wrap


@njit
def _mi(dx, L):  # called from numba code, as other kernels do
    return minimum_image(dx, L)


@settings(deadline=None)  # the first example compiles
@given(dx=st.floats(-1e3, 1e3), L=st.floats(1e-2, 1e2))
def test_minimum_image_range_and_period(dx, L):
    d = _mi(dx, L)
    assert -L / 2 - 1e-12 * (abs(dx) + L) <= d <= L / 2 + 1e-12 * (abs(dx) + L)
    k = round((dx - d) / L)  # differs from dx by a whole number of periods
    assert abs(dx - d - k * L) <= 1e-9 * (abs(dx) + L)


def test_minimum_image_exact_cases():
    assert _mi(0.3, 1.0) == 0.3
    assert _mi(0.7, 1.0) == pytest.approx(-0.3, abs=1e-15)
    assert _mi(-0.7, 1.0) == pytest.approx(0.3, abs=1e-15)
    assert _mi(2.25, 2.0) == pytest.approx(0.25, abs=1e-15)


def test_wrap_into_box():
    box = np.array([1.0, 2.0])
    p = np.array([[-1e-17, -1e-17], [1.0, 2.0], [3.5, -2.5], [0.25, 1.5]])
    w = wrap(p, box)
    assert np.all(w >= 0) and np.all(w < box)
    assert np.allclose(w[2], [0.5, 1.5]) and np.array_equal(w[3], p[3])


def test_wrap_rejects_bad_input():
    with pytest.raises(ValueError, match="positions"):
        wrap(np.zeros(3), (1, 1))
    with pytest.raises(ValueError, match="box"):
        wrap(np.zeros((2, 2)), (1, -1))
