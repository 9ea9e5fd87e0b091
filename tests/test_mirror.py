"""Rows of later column blocks taken by reciprocity (F_ij = A_j F_ji / A_i) instead of computed."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.formfactors import iter_column_blocks
from hfrad.formfactors.blocks import FormFactorEngine
from hfrad.formfactors.mirror import MIRROR_LAG, ReciprocityMirror, band_for
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation

BLOCK = 64


@pytest.fixture(scope="module")
def box():
    scene = subdivide(cornell_box(), patches=1500)
    return scene, zorder_permutation(scene.centroids)


def _F(scene, order, **kw):
    engine = FormFactorEngine(scene)
    F = np.concatenate([b for _, _, b in iter_column_blocks(scene, BLOCK, order=order, dtype=np.float64,
                                                            engine=engine, **kw)], axis=1)
    engine.close()
    return F, engine.pairs


@pytest.fixture(scope="module")
def computed(box):
    """F with every pair computed, and the pairs the kernel saw."""
    return _F(*box, reciprocity=False)


def test_copies_equal_the_computed_pairs(box, computed):
    scene, order = box
    F, pairs = computed
    G, mirrored_pairs = _F(scene, order)
    n = scene.n_patches
    blocks = -(-n // BLOCK)
    assert pairs == n * n
    # block b copies the rows of blocks 0 .. b - LAG - 1
    copied = sum((b - MIRROR_LAG) * BLOCK * min(BLOCK, n - b * BLOCK) for b in range(MIRROR_LAG + 1, blocks))
    assert mirrored_pairs == n * n - copied and copied > 0.2 * n * n
    err = np.abs(G - F).max() / F.max()
    print(f"\n{n} patches: {copied / n / n:.0%} of the pairs copied; largest difference {err:.1e} of max F")
    assert err <= 2e-15       # observed 1.6e-16: the kernel and visibility are reciprocal to rounding


def test_processes_and_resumed_passes_agree(box, computed):
    scene, order = box
    F = computed[0]
    two = np.concatenate([b for _, _, b in iter_column_blocks(scene, BLOCK, order=order, dtype=np.float64,
                                                              processes=2)], axis=1)
    one = _F(scene, order)[0]
    np.testing.assert_array_equal(two, one)       # which rows are copied does not depend on the processes
    first = 12                                    # a resumed pass copies only from the blocks it computed
    resumed = np.concatenate([b for _, _, b in iter_column_blocks(scene, BLOCK, order=order, dtype=np.float64,
                                                                  first_block=first)], axis=1)
    np.testing.assert_allclose(resumed, F[:, first * BLOCK:], rtol=0, atol=2e-15 * F.max())


def test_bands_and_budgets():
    """A reciprocal F = S / A (S symmetric) through keep/fill: each band copies its rows exactly,
    holds no more than its budget, and uses every tile it keeps."""
    rng = np.random.default_rng(0)
    n, b, lag = 700, 50, 2
    S = rng.random((n, n))
    S = S + S.T
    areas = rng.uniform(0.5, 2.0, n)
    F = S / areas[:, None]
    starts = np.r_[np.arange(0, n, b), n]
    blocks = len(starts) - 1
    full = band_for(blocks, b, 8, 1 << 40, lag=lag)
    assert full == blocks - lag - 1
    assert band_for(blocks, b, 8, 0, lag=lag) == 0
    for budget in (1 << 40, 12 * b * b * 8, 0):
        band = band_for(blocks, b, 8, budget, lag=lag)
        m = ReciprocityMirror(areas, starts, band=band, lag=lag)
        for k in range(blocks):
            rows = m.copied_rows(k)
            lo = max(0, k - lag - band)
            assert (rows.start, rows.stop) == ((starts[lo], starts[k - lag]) if k - lag > lo else (0, 0))
            block = F[:, starts[k]:starts[k + 1]].copy()
            block[rows] = np.nan
            m.fill(k, block, rows)
            np.testing.assert_allclose(block, F[:, starts[k]:starts[k + 1]], rtol=1e-14)
            m.keep(k, block)
        print(f"\nbudget {budget}: band {band}, peak {m.peak_bytes} bytes, {m.copied_pairs} pairs copied")
        assert m.peak_bytes <= budget and not m.tiles
        assert (m.copied_pairs > 0) == (band > 0)
    assert 0 < band_for(blocks, b, 8, 12 * b * b * 8, lag=lag) < full
    m = ReciprocityMirror(areas, starts, band=full, lag=lag)
    for k in range(6):
        m.keep(k, F[:, starts[k]:starts[k + 1]])
    m.discard(lag + 2)                                   # a block read from a cache: its tiles go
    assert (lag + 2, 0) not in m.tiles and m.bytes == sum(t.nbytes for t in m.tiles.values())
    with pytest.raises(ValueError, match="in order"):
        m.keep(0, F[:, :b])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_copy_kernel_rounds_as_numpy_does(dtype):
    """The fill kernel gives NumPy's ``(A_j / A_i) * tile.T`` stored in the block's dtype, bit for bit."""
    from hfrad.formfactors.mirror import _copy_transposed

    rng = np.random.default_rng(11)
    tile = (rng.random((48, 40)) ** 3 * 1e-2).astype(dtype)      # F[J_b, J_a]: 48 columns of b, 40 rows of a
    col_areas, row_areas = rng.uniform(1e-4, 3.0, 48), rng.uniform(1e-4, 3.0, 40)
    out = np.full((40, 48), np.nan, dtype)
    _copy_transposed(out, tile, col_areas, row_areas)
    expected = np.empty_like(out)
    expected[:] = (col_areas[None, :] / row_areas[:, None]) * tile.T
    assert np.array_equal(out, expected)
