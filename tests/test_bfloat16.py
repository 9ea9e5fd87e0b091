"""bfloat16 values (formfactors/bfloat16.py): float32 rounded to nearest even at 8 significant bits,
decoded exactly by numpy and inside numba kernels alike."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from hfrad.formfactors.bfloat16 import ROUNDING, from_bfloat16, stored_value, to_bfloat16, value_dtype


@njit(cache=False)
def _read_all(a):
    out = np.empty(a.size, np.float32)
    for i in range(a.size):
        out[i] = stored_value(a, i)
    return out


def test_rounding_is_to_nearest_within_2_to_the_minus_8_at_every_scale():
    rng = np.random.default_rng(0)
    x = (rng.random(200_000) * 10.0 ** rng.uniform(-12, 0, 200_000)).astype(np.float32)
    y = from_bfloat16(to_bfloat16(x))
    rel = np.abs(y.astype(np.float64) - x) / x
    assert rel.max() <= ROUNDING
    assert rel.max() > 0.9 * ROUNDING         # the bound is reached: truncation would give twice it
    assert 1.5e-3 < np.sqrt(np.mean(rel ** 2)) < 1.8e-3       # 0.17% root mean square (2^-8 / sqrt(3) x 0.74)
    assert abs(np.mean((y.astype(np.float64) - x) / x)) < 2e-5  # no bias (nearest, not toward zero)


def test_ties_go_to_even_and_exact_values_stay():
    ties = np.array([1 + 2 ** -8, 1 + 3 * 2 ** -8, -(1 + 2 ** -8)], np.float32)
    np.testing.assert_array_equal(from_bfloat16(to_bfloat16(ties)), np.array([1.0, 1 + 2 ** -6, -1.0], np.float32))
    exact = np.array([0.0, 1.0, 0.375, 2.0 ** -40, -3.0], np.float32)
    np.testing.assert_array_equal(from_bfloat16(to_bfloat16(exact)), exact)
    assert to_bfloat16(exact).dtype == np.uint16 and to_bfloat16(exact.reshape(5, 1)).shape == (5, 1)


def test_numba_kernels_read_both_kinds_as_float32():
    x = np.random.default_rng(1).random(1000).astype(np.float32)
    bits = to_bfloat16(x)
    np.testing.assert_array_equal(_read_all(bits), from_bfloat16(bits))
    np.testing.assert_array_equal(_read_all(x), x)


def test_value_kinds_are_named():
    assert value_dtype("float32") == np.float32 and value_dtype("bfloat16") == np.uint16
    with pytest.raises(ValueError, match="values must be one of 'float32', 'bfloat16'"):
        value_dtype("float16")
