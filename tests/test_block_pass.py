"""The fused pass over a column block (PassStatistics.add_scaled, assemble.far_block) against NumPy.

What it replaces, written out with NumPy: G = rho * F (the working dtype's product), the
row and column sums and the probe sketch rho * (F @ Omega') in float64, ||G||_F^2 in
float64, and the near-field split's entries moved out.
"""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.lowrank.nearsplit import NearFieldSplit
from hfrad.precompute.assemble import far_block
from hfrad.solve.stats import PassStatistics


def _block(n: int, b: int, dtype, seed: int = 3):
    rng = np.random.default_rng(seed)
    F = (rng.random((n, b)) ** 4 * 1e-3).astype(dtype)        # skewed, as form factors are
    F[rng.random((n, b)) < 0.1] = 0                            # occluded pairs
    rows_rho = rng.uniform(0.2, 0.9, (n, 1)).astype(dtype)
    weights = rng.uniform(0.5, 2.0, n)
    return F, rows_rho, weights


def _numpy_reference(stats: PassStatistics, start: int, F, rows_rho):
    F64 = F.astype(np.float64)
    omega = stats._omega[start:start + F.shape[1]]
    G = rows_rho * F
    return (F64.sum(axis=1), F64.sum(axis=0), rows_rho.astype(np.float64) * (F64 @ omega), G,
            float(np.sum(G.astype(np.float64) ** 2)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_add_scaled_equals_the_numpy_passes(dtype):
    n, b, start = 5003, 37, 64
    F, rows_rho, weights = _block(n, b, dtype)
    stats = PassStatistics(n, weights)
    G, norm2 = stats.add_scaled(start, start + b, F, rows_rho)
    rows, cols, sketch, G_ref, norm2_ref = _numpy_reference(stats, start, F, rows_rho)
    assert G.dtype == dtype and np.array_equal(G, G_ref)       # the same rounding of the same product
    # float64 sums in another order: a few float64 ulps of the sums (observed <= 4.6e-16 and 3.6e-15 relative)
    assert np.allclose(stats.row_sums, rows, rtol=2e-15, atol=0)
    assert np.allclose(stats.col_sums[start:start + b], cols, rtol=1e-14, atol=0)
    assert np.all(stats.col_sums[:start] == 0) and np.all(stats.col_sums[start + b:] == 0)
    scale = np.abs(rows_rho.astype(np.float64) * (F.astype(np.float64) @ np.abs(stats._omega[start:start + b])))
    assert np.all(np.abs(stats.sketch - sketch) <= 3e-15 * scale)        # observed <= 7.1e-16
    assert norm2 == pytest.approx(norm2_ref, rel=2e-14, abs=0)            # observed <= 4.0e-15


def test_add_accumulates_over_blocks_as_the_whole_matrix():
    n, b = 2000, 50
    F, rows_rho, weights = _block(n, 4 * b, np.float32, seed=5)
    whole, parts = PassStatistics(n, weights), PassStatistics(n, weights)
    whole.add(0, 4 * b, F, rows_rho)
    for start in range(0, 4 * b, b):
        parts.add(start, start + b, F[:, start:start + b], rows_rho)
    for name in ("row_sums", "col_sums"):      # observed <= 2.3e-16 relative
        assert np.allclose(getattr(parts, name), getattr(whole, name), rtol=1e-15, atol=0)
    # the sketch's entries are sums of signed terms: their rounding is relative to the sum of magnitudes
    scale = np.abs(rows_rho.astype(np.float64) * (F.astype(np.float64) @ np.abs(whole._omega[:4 * b])))
    assert np.all(np.abs(parts.sketch - whole.sketch) <= 1.5e-15 * scale)     # observed <= 2.9e-16


def test_far_block_moves_the_near_entries_and_keeps_both_norms():
    n, b, start = 3000, 40, 200
    F, rows_rho, weights = _block(n, b, np.float32, seed=7)
    centroids = np.random.default_rng(8).random((n, 3))
    split = NearFieldSplit(centroids, 0.15)   # ~40 neighbours a column
    G, norm2, block_norm2 = far_block(PassStatistics(n, weights), start, start + b, F, rows_rho, split)
    G_full = rows_rho * F
    near = split.matrix().toarray()[:, start:start + b]
    assert np.count_nonzero(near) > 10 * b                     # the split moved something
    assert np.array_equal(G + near.astype(np.float32), G_full)  # moved out exactly, nothing else touched
    assert norm2 == pytest.approx(float(np.sum(G_full.astype(np.float64) ** 2)), rel=3e-14, abs=0)   # observed 6.4e-15
    assert block_norm2 == pytest.approx(float(np.sum(G.astype(np.float64) ** 2)), rel=3e-14, abs=0)   # observed 6.7e-15
    assert block_norm2 < 0.99 * norm2
    G2, n2, own2 = far_block(PassStatistics(n, weights), start, start + b, F, rows_rho)
    assert np.array_equal(G2, G_full) and n2 == own2 == norm2


def test_a_block_of_the_wrong_shape_is_refused():
    stats = PassStatistics(100)
    with pytest.raises(ValueError, match="must be"):
        stats.add(0, 10, np.zeros((100, 9), np.float32), np.ones((100, 1), np.float32))
