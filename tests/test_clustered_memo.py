"""The clustered kernel's memo (formfactors/clustered.py): a near pair's A_P F_PQ, computed once for
(P, Q), is read for (Q, P); F must be the one computed without it, to the bit, in any block order."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.formfactors.clustered import FAR, ClusterGeometry, clustered_block, memo_table
from hfrad.scene.builtin import cornell_box
from hfrad.scene.cluster import cluster
from hfrad.scene.patches import subdivide


@pytest.fixture(scope="module")
def scene():
    return cluster(subdivide(cornell_box(), patches=1200), patches=150)


def test_memo_slots_are_exactly_the_pairs_within_half_far(scene):
    g = ClusterGeometry(scene)
    C, D = g.centroids, g.diameters
    d2 = ((C[:, None] - C[None]) ** 2).sum(-1)
    near = np.triu(d2 < (0.5 * FAR * (D[:, None] + D[None])) ** 2, 1)
    rows = np.repeat(np.arange(g.n), np.diff(g.memo_start))
    listed = np.zeros_like(near)
    listed[rows, g.memo_cols] = True
    np.testing.assert_array_equal(listed, near)
    assert 0 < near.sum() < g.n * (g.n - 1) / 2           # some pairs, not all
    for i in range(g.n):                                   # increasing within a patch (binary search)
        assert np.all(np.diff(g.memo_cols[g.memo_start[i]:g.memo_start[i + 1]]) > 0)
    assert np.isnan(g.memo_values).all()                   # nothing computed yet


def test_memo_gives_the_same_F_to_the_bit_in_any_block_order(scene):
    n = scene.n_patches
    rows = np.arange(n)
    plain = clustered_block(ClusterGeometry(scene, memo=False), rows, rows)
    g = ClusterGeometry(scene)
    blocks = np.array_split(np.random.default_rng(1).permutation(n), 7)
    F = np.empty((n, n))
    for cols in blocks[::-1]:                               # both orders of a pair in one call and in two
        F[:, cols] = clustered_block(g, rows, cols)
    np.testing.assert_array_equal(F, plain)
    assert not np.isnan(g.memo_values).any()               # every near pair was met and kept
    np.testing.assert_array_equal(clustered_block(g, rows, rows), plain)   # all read from the memo now
    # what it keeps is A_P F_PQ of the pair (F = A_P F_PQ / A_P: one rounding each way)
    i = np.repeat(np.arange(n), np.diff(g.memo_start))
    np.testing.assert_allclose(g.memo_values, scene.areas[i] * plain[i, g.memo_cols], rtol=1e-15, atol=0)
    AF = scene.areas[:, None] * F
    np.testing.assert_allclose(AF[i, g.memo_cols], AF[g.memo_cols, i], rtol=1e-15, atol=0)   # reciprocal


def test_memo_table_keeps_nothing_above_its_cap():
    C = np.zeros((5, 3))
    C[:, 0] = np.arange(5.0)
    D = np.ones(5)
    start, cols, values = memo_table(C, D, 1.5, 100)
    assert np.diff(start).tolist() == [2, 2, 2, 1, 0] and cols.tolist() == [1, 2, 2, 3, 3, 4, 4]
    start, cols, values = memo_table(C, D, 1.5, 6)
    assert start.tolist() == [0] * 6 and len(cols) == len(values) == 0
