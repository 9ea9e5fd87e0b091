"""16-bit row-scaled storage of tall matrices (the near-field solver's Z_c)."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.solve.quantized import CODE_MAX, QuantizedRows
from hfrad.solve.thin import THIN_MAX


@pytest.fixture(scope="module")
def matrix():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((700, 37)).astype(np.float32) * np.exp(rng.uniform(-8, 3, (700, 1))).astype(np.float32)
    A[5] = 0                                            # an all-zero row codes as zeros
    return A


def test_each_entry_within_half_a_step_of_its_row(matrix):
    q = QuantizedRows.encode(matrix)
    assert q.codes.dtype == np.int16 and q.scale.dtype == np.float32 and q.shape == matrix.shape
    np.testing.assert_array_equal(np.abs(q.codes).max(axis=1)[matrix.any(axis=1)], CODE_MAX)
    err = np.abs(q.decode().astype(np.float64) - matrix)
    # half a step, plus float32 rounding of scale * code (6e-8 of the row's largest entry)
    assert (err <= q.scale[:, None] * (0.5 + 1e-2)).all()
    assert not q.decode()[5].any()
    actual = float(np.linalg.norm(q.decode().astype(np.float64) - matrix))
    print(f"\n||A - decode|| {actual:.3e}, bound {q.error_bound():.3e}")
    # uniform rounding errors: the bound sqrt(k) * step/2 per row is ~sqrt(3) x the actual
    assert actual <= q.error_bound() <= 2.5 * actual     # observed ratio 1.75


@pytest.mark.parametrize("columns", [1, 3, THIN_MAX, THIN_MAX + 9])
def test_products_equal_the_decoded_matrix(matrix, columns):
    q = QuantizedRows.encode(matrix)
    S = np.random.default_rng(columns).standard_normal((matrix.shape[1], columns))
    ref = q.decode().astype(np.float64) @ S
    got = q.matmul(S)
    assert got.shape == (matrix.shape[0], columns) and got.dtype == np.float32
    tol = 1e-6 * np.abs(q.decode()).max(axis=1, keepdims=True) * np.abs(S).sum(axis=0)
    assert (np.abs(got - ref) <= tol).all()


def test_stack_and_index(matrix):
    parts = [QuantizedRows.encode(matrix), QuantizedRows.encode(2 * matrix[::-1])]
    s = QuantizedRows.stack(parts)
    assert s.shape == (2, *matrix.shape) and s.nbytes == 2 * (matrix.size * 2 + matrix.shape[0] * 4)
    np.testing.assert_array_equal(s[1].decode(), parts[1].decode())
    with pytest.raises(ValueError, match="do not match"):
        QuantizedRows(s.codes, s.scale[:, :-1])


@pytest.mark.parametrize("m", [1, 2, 5])
def test_added_products_of_a_stack(matrix, m):
    """``out[:, c] += Z_{which[c]} S[:, c]``: shared matrices (grey channels) and wide batches (BLAS)."""
    rng = np.random.default_rng(m)
    s = QuantizedRows.stack([QuantizedRows.encode(matrix), QuantizedRows.encode(matrix[::-1])])
    which = [1, 0, 1]
    S = rng.standard_normal((matrix.shape[1], 3, m))
    base = rng.standard_normal((matrix.shape[0], 3, m))
    out = base.copy()
    s.add_products(out, S, which)
    for c, w in enumerate(which):
        ref = base[:, c] + s[w].decode().astype(np.float64) @ S[:, c]
        tol = 1e-6 * np.abs(s[w].decode()).max(axis=1, keepdims=True) * np.abs(S[:, c]).sum(axis=0)
        assert (np.abs(out[:, c] - ref) <= tol + 1e-12).all()
