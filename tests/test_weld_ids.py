"""Integer ids of rows and groups (hfrad.scene.weld: row_ids, grouped_order, first_index) against
NumPy's np.unique / np.argsort on tables built to hit each path (packed digits, two digits with long
runs, columns whose range overflows int64, floats, booleans)."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.scene.weld import _packed_digits, first_index, grouped_order, row_ids


def _table(kind: int, rng: np.random.Generator) -> np.ndarray:
    n, k = int(rng.integers(1, 600)), int(rng.integers(1, 6))
    if kind == 0:
        t = rng.integers(-3, 3, (n, k))  # one digit
    elif kind == 1:
        t = rng.integers(-2 ** 62, 2 ** 62, (n, k))  # a digit a column
    elif kind == 2:  # two digits, the major one with few values: long runs sorted by the minor
        t = np.column_stack([rng.integers(0, 3, n) * 2 ** 40, rng.integers(0, 2 ** 40, n)])
    elif kind == 3:
        t = rng.integers(-2 ** 63, 2 ** 63 - 1, (n, k), dtype=np.int64)  # ranges beyond int64
    elif kind == 4:
        t = rng.integers(-3, 3, (n, k)) * 0.5  # floats: not packed
    elif kind == 5:
        t = rng.integers(0, 3, (n, k)).astype(np.uint8)
    else:
        t = rng.integers(0, 2, (n, k)).astype(bool)
    t[n // 2:] = t[:n - n // 2]  # repeated rows
    return t


@pytest.mark.parametrize("kind", range(7))
def test_row_ids_are_np_unique_inverse(kind):
    rng = np.random.default_rng(kind)
    for _ in range(40):
        t = _table(kind, rng)
        np.testing.assert_array_equal(row_ids(t), np.unique(t, axis=0, return_inverse=True)[1].reshape(-1))


def test_packed_digits_keep_the_row_order():
    rng = np.random.default_rng(3)
    t = np.column_stack([rng.integers(0, 1000, 500), rng.integers(-5, 5, 500), rng.integers(0, 2 ** 60, 500)])
    digits = _packed_digits(t)
    assert len(digits) == 2  # 1000 x 10 values in one digit, the 2^60 column in a second
    np.testing.assert_array_equal(np.lexsort(digits[::-1]), np.lexsort(t.T[::-1]))


def test_grouped_order_and_first_index():
    rng = np.random.default_rng(8)
    ids = rng.integers(0, 50, 3000)
    np.testing.assert_array_equal(grouped_order(ids, 50), np.argsort(ids, kind="stable"))
    used, first = np.unique(ids, return_index=True)
    expected = np.full(52, -1)
    expected[used] = first
    np.testing.assert_array_equal(first_index(ids, 52), expected)
