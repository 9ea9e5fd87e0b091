"""ACA of far blocks of F (formfactors/aca.py): entries equal to the block functions' to the bit,
and factors within a small multiple of the tolerance of the dense block, from few entries."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import InputError
from hfrad.formfactors.aca import PROBES, aca_blocks, pair_values
from hfrad.formfactors.clustered import kernel_for
from hfrad.formfactors.kernel import PatchGeometry, unoccluded_block
from hfrad.scene.builtin import cornell_box
from hfrad.scene.cluster import cluster
from hfrad.scene.load import load_scene
from hfrad.scene.patches import subdivide


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell", patches=4000)


@pytest.fixture(scope="module")
def clustered():
    return cluster(subdivide(cornell_box(), patches=1200), patches=150)


def _walls(scene):
    """Patch lists of the floor, the ceiling, the left wall's front half and the back wall's right half."""
    N, C = scene.normals, scene.centroids
    floor = np.flatnonzero((N[:, 1] > 0.99) & (C[:, 1] < 1e-6))
    ceiling = np.flatnonzero((N[:, 1] < -0.99) & (C[:, 1] > 2 - 1e-6))
    left = np.flatnonzero((N[:, 0] > 0.99) & (C[:, 0] < -1 + 1e-6) & (C[:, 2] > 0))
    back = np.flatnonzero((N[:, 2] > 0.99) & (C[:, 2] < -1 + 1e-6) & (C[:, 0] > 0))
    return floor, ceiling, left, back


def _run(geometry, blocks, tol, max_rank):
    rows = np.concatenate([r for r, _ in blocks])
    cols = np.concatenate([c for _, c in blocks])
    row_ptr = np.cumsum([0] + [len(r) for r, _ in blocks])
    col_ptr = np.cumsum([0] + [len(c) for _, c in blocks])
    return aca_blocks(geometry, rows, row_ptr, cols, col_ptr, tol, max_rank)


def _all_pairs(rows, cols):
    I, J = np.meshgrid(rows, cols, indexing="ij")
    return I.ravel(), J.ravel()


def test_pair_values_equal_the_block_function_to_the_bit_one_triangle_per_patch():
    scene = load_scene("cornell", patches=600)
    geometry, block = kernel_for(scene)
    assert geometry.one_triangle_per_patch
    n = scene.n_patches
    dense = block(geometry, np.arange(n), np.arange(n))      # every rule of the kernel, distant to touching
    I, J = _all_pairs(np.arange(n), np.arange(n))
    np.testing.assert_array_equal(pair_values(geometry, I, J).reshape(n, n), dense)


def test_pair_values_equal_the_block_functions_to_the_bit_clustered(clustered):
    n = clustered.n_patches
    I, J = _all_pairs(np.arange(n), np.arange(n))
    geometry, block = kernel_for(clustered)                  # ClusterGeometry + clustered_block
    assert geometry.clustered
    dense = block(geometry, np.arange(n), np.arange(n))
    np.testing.assert_array_equal(pair_values(geometry, I, J).reshape(n, n), dense)
    triangles = PatchGeometry(clustered)                     # kernel.py's CSR path over the same patches
    assert not triangles.one_triangle_per_patch
    np.testing.assert_array_equal(pair_values(triangles, I, J).reshape(n, n),
                                  unoccluded_block(triangles, np.arange(n), np.arange(n)))


@pytest.mark.parametrize("tol", [1e-2, 1e-3])
def test_aca_of_well_separated_blocks_is_within_the_tolerance_from_few_entries(cornell, tol):
    geometry, block = kernel_for(cornell)
    floor, ceiling, left, back = _walls(cornell)
    rng = np.random.default_rng(0)
    blocks = [(floor, ceiling), (ceiling, floor), (left, back), (rng.permutation(back), rng.permutation(left))]
    res = _run(geometry, blocks, tol, 64)
    assert res.ok.all()
    assert len(res.U) == (res.block_rows * res.ranks).sum() and res.U.dtype == np.float32
    for t, (rows, cols) in enumerate(blocks):
        dense = block(geometry, rows, cols)
        U, V = res.factors(t)
        error = np.linalg.norm(dense - U.astype(float) @ V.astype(float).T) / np.linalg.norm(dense)
        assert error <= 2.5 * tol                            # observed 0.6-1.8 tol
        m, b = dense.shape
        assert 1 <= res.ranks[t] <= res.aca_ranks[t] <= 0.1 * min(m, b)
        # only the rows and columns ACA visits, k (m + b) entries, and its probes (one plane a side:
        # PROBES rows and columns spread over the block)
        assert res.aca_ranks[t] * (m + b) <= res.evaluated[t] <= (res.aca_ranks[t] + PROBES + 1) * (m + b)


def test_aca_on_clustered_patches(clustered):
    geometry, block = kernel_for(clustered)
    floor, ceiling, _, _ = _walls(clustered)
    res = _run(geometry, [(floor, ceiling)], 1e-2, 32)
    dense = block(geometry, floor, ceiling)
    U, V = res.factors(0)
    assert res.ok[0] and 1 <= res.ranks[0] < min(dense.shape) // 2
    assert np.linalg.norm(dense - U.astype(float) @ V.astype(float).T) <= 2.5e-2 * np.linalg.norm(dense)


def test_a_zero_block_is_rank_zero_at_the_cost_of_a_few_rows(cornell):
    geometry, block = kernel_for(cornell)
    floor = _walls(cornell)[0]
    assert not block(geometry, floor, floor).any()           # coplanar patches: F = 0 exactly
    res = _run(geometry, [(floor, floor)], 1e-3, 16)
    assert res.ok[0] and res.ranks[0] == 0 and res.factors(0)[0].shape == (len(floor), 0)
    # the first row, one column for the columns' plane, then PROBES rows and columns spread over the block
    assert res.evaluated[0] == (2 * PROBES + 2) * len(floor)


def test_hitting_max_rank_is_reported(cornell):
    geometry, _ = kernel_for(cornell)
    floor, ceiling, left, back = _walls(cornell)
    res = _run(geometry, [(floor, ceiling), (floor, floor), (left, back)], 1e-6, 3)
    np.testing.assert_array_equal(res.ok, [False, True, False])
    assert (res.aca_ranks <= 3).all()


def test_bad_input_is_refused_with_one_line(cornell):
    geometry, _ = kernel_for(cornell)
    with pytest.raises(InputError, match="tol"):
        aca_blocks(geometry, [0], [0, 1], [1], [0, 1], 0.0, 4)
    with pytest.raises(InputError, match="cols_ptr"):
        aca_blocks(geometry, [0], [0, 1], [1], [0, 2], 1e-3, 4)
    with pytest.raises(InputError, match="patch indices"):
        pair_values(geometry, [0], [cornell.n_patches])
    with pytest.raises(InputError, match="same length"):
        pair_values(geometry, [0, 1], [2])
