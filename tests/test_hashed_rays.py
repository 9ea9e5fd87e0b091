"""The H-matrix's hashed rays, made and traced a chunk at a time, against their definition ray by ray
(:meth:`Visibility.segments_blocked` on the hashed points, one NumPy array per quantity)."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.formfactors import hashed_rays
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.hashed_rays import probe_counts, scale_by_edge_visibility, unit_hash
from hfrad.scene.load import load_scene


@pytest.fixture(scope="module")
def engine():
    scene = load_scene("cornell", patches=600)
    return FormFactorEngine(scene), scene.n_patches


def _hash(a, b, k) -> np.ndarray:
    return np.array([unit_hash(x, y, z) for x, y, z in np.broadcast(a, b, k)])


@pytest.fixture(params=[1 << 17, 64], ids=["one-chunk", "many-chunks"])
def chunk(request, monkeypatch):
    """The module's chunk, and a tiny one: rows and pairs cut across many chunks count the same."""
    monkeypatch.setattr(hashed_rays, "CHUNK_RAYS", request.param)
    return request.param


def test_probe_counts_are_those_of_each_ray(engine, chunk):
    engine, n = engine
    vis = engine.visibility
    rng = np.random.default_rng(3)
    perm = rng.permutation(n)
    node_start = np.array([0, n // 4, n // 2])
    node_size = np.array([n // 4, n // 4, n - n // 2])
    rows = np.sort(rng.choice(n, 300, replace=False))
    c = rng.integers(0, 3, rows.size)
    first, k = 6, 8
    n_facing, n_blocked = probe_counts(vis, rows, c, node_start, node_size, perm, first, k)
    # the definition: ray s of row r goes to the node's patch at a hashed place in the s-th of k parts
    r, s = np.repeat(rows, k), np.tile(np.arange(k), rows.size)
    node = np.repeat(c, k)
    ray = first + s
    at = np.minimum(((s + _hash(r, node, ray)) * node_size[node] / k).astype(np.int64), node_size[node] - 1)
    target = node_start[node] + at
    points = vis.probe_design_points
    ki, kj = (_hash(r, target, ray) * points).astype(np.int64), (_hash(target, r, ray) * points).astype(np.int64)
    facing, blocked = vis.segments_blocked(perm[r], perm[target], ki, kj)
    np.testing.assert_array_equal(n_facing, facing.reshape(-1, k).sum(1))
    np.testing.assert_array_equal(n_blocked, blocked.reshape(-1, k).sum(1))
    assert 0 < n_blocked.sum() < n_facing.sum() < rows.size * k      # some blocked, some not facing


def test_edge_visibility_is_the_open_share_of_each_pairs_rays(engine, chunk):
    engine, n = engine
    vis = engine.visibility
    rng = np.random.default_rng(4)
    rows, cols = rng.choice(n, 120, replace=False), rng.choice(n, 30, replace=False)
    K = np.ascontiguousarray(engine.unoccluded(rows, cols))
    F = K.copy()
    k = 4
    scale_by_edge_visibility(vis, F, rows, cols, k)
    ii, jj = np.nonzero(K > 0)
    i, j, s = np.repeat(rows[ii], k), np.repeat(cols[jj], k), np.tile(np.arange(k), ii.size)
    points = vis.probe_design_points
    facing, blocked = vis.segments_blocked(i, j, (_hash(i, j, s) * points).astype(np.int64),
                                           (_hash(j, i, s) * points).astype(np.int64))
    f, b = facing.reshape(-1, k).sum(1), blocked.reshape(-1, k).sum(1)
    want = K.copy()
    want[ii, jj] *= np.where(f > 0, 1.0 - b / np.maximum(f, 1), 1.0)
    np.testing.assert_array_equal(F, want)
    assert 0 < (F < K).sum() and (F[K > 0] > 0).any()                   # some pairs shaded, some open
    with pytest.raises(ValueError, match="C-contiguous"):
        scale_by_edge_visibility(vis, np.asfortranarray(K), rows, cols, k)
