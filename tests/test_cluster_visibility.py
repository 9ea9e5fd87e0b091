"""Visibility decided once per cluster pair (formfactors/clustervis.py) gives the per-patch-ray F.

Observed: on the built-in Cornell box (612 patches, all of F) and on a clustered
Sponza (1,047 patches, three blocks of columns) the cluster-decided F equals the
per-patch-ray F bit for bit (max |dF| = 0), since a pair is decided only when
every one of its rays would have been free (or blocked) anyway. The tolerances below are a floor far
under the ray budget's error, so any pair decided wrongly (a shadow missed: an
error of F_ij itself) fails them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from hfrad.errors import InputError
from hfrad.formfactors.clustervis import BLOCKED, MIXED, VISIBLE
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.visibility import Visibility
from hfrad.scene.builtin import cornell_box, parallel_plates
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(),
                                  reason="../shared/scenes is absent (only in the developers' checkout)")

#: max |dF| / max F and ||dF||_F / ||F||_F allowed (observed: 0 on every scene here).
TOL = 1e-12


def _both(scene, col_sets, size):
    """F[:, cols] for each column set, rows in Z-order, without and with cluster visibility;
    the rays each cast and the pairs the clusters decided."""
    order = zorder_permutation(scene.centroids)
    out = []
    for s in (0, size):
        eng = FormFactorEngine(scene, cluster_size=s)
        try:
            F = np.hstack(list(eng.iter_blocks(order, col_sets(order))))
            cl = eng.visibility.clusters
            out.append((F, eng.rays, 0 if cl is None else cl.pairs_visible + cl.pairs_blocked))
        finally:
            eng.close()
    return out


def _check_same(F0, F1):
    d = F1 - F0
    assert np.abs(d).max() <= TOL * F0.max()
    assert np.linalg.norm(d) <= TOL * np.linalg.norm(F0)


def test_cornell_box_same_F_fewer_rays():
    scene = subdivide(cornell_box(), patches=600)
    (F0, rays0, _), (F1, rays1, decided) = _both(scene, lambda order: [order[k:k + 128]
                                                                       for k in range(0, len(order), 128)], 8)
    _check_same(F0, F1)
    # observed: 30,294 pairs decided, rays 15.23 M -> 12.74 M (16.3% saved)
    assert decided > 25_000
    saved = 1 - rays1 / rays0
    assert saved > 0.12, saved


def test_cornell_box_reciprocity_kept():
    scene = subdivide(cornell_box(), patches=300)
    eng = FormFactorEngine(scene, cluster_size=4)
    try:
        idx = np.arange(scene.n_patches)
        F = eng.block(idx, idx)
        assert eng.visibility.clusters.pairs_visible > 0
    finally:
        eng.close()
    A = scene.areas[:, None] * F
    assert np.abs(A - A.T).max() <= 1e-12 * A.max()


def _plates_with(occluder):
    """Two facing 1 m squares 1 m apart (32 patches each) and one occluder triangle (alone in the
    Embree scene: the plates cannot block each other)."""
    scene = subdivide(parallel_plates(), patches=64)
    return dataclasses.replace(scene, occluder_vertices=np.asarray(occluder, float),
                               occluder_faces=np.array([[0, 1, 2]]))


@pytest.mark.parametrize("occluder, state", [
    ([(-5, -5, 0.5), (10, -5, 0.5), (-5, 10, 0.5)], BLOCKED),  # a wall between the plates
    ([(0.95, 1.2, 0.5), (1.2, 0.95, 0.5), (1.2, 1.2, 0.3)], VISIBLE),  # beside the pencil, its box and plane cut it
    ([(0.2, 0.2, 0.5), (0.8, 0.2, 0.5), (0.5, 0.8, 0.5)], MIXED),  # a partial shadow
])
def test_plates_decided_without_rays(occluder, state):
    scene = _plates_with(occluder)
    vis = Visibility(scene, cluster_size=8)
    lo_plate = np.flatnonzero(scene.centroids[:, 2] < 0.5)
    hi_plate = np.flatnonzero(scene.centroids[:, 2] > 0.5)
    states = vis.clusters.pair_states(lo_plate, hi_plate, np.ones((len(lo_plate), len(hi_plate)), bool))
    vis.close()
    if state == MIXED:
        assert (states == MIXED).any()
    else:
        assert (states == state).all()
    (F0, rays0, _), (F1, rays1, decided) = _both(scene, lambda order: [order], 8)
    _check_same(F0, F1)
    if state == BLOCKED:
        assert F1.max() == 0 and rays1 == 0 and rays0 > 0 and decided == 2 * len(lo_plate) * len(hi_plate)
    elif state == VISIBLE:
        assert rays1 == 0 and rays0 > 0 and F1.max() > 0
    else:
        assert rays1 > 0 and 0 < F1.max()


def test_cluster_size_checked():
    with pytest.raises(InputError, match="cluster_size"):
        Visibility(subdivide(cornell_box(), patches=60), cluster_size=-1)


@pytest.mark.slow   # the Cornell box's test of the same property runs by default
@needs_shared
def test_clustered_sponza_same_F():
    from hfrad.scene.cluster import cluster
    from hfrad.scene.load import load_scene

    scene = cluster(load_scene(SHARED / "sponza-dabrovic" / "sponza.obj", emit={"ceiling": 1.0}), patches=1000)
    n = scene.n_patches
    (F0, rays0, _), (F1, rays1, decided) = _both(
        scene, lambda order: [order[s:s + 64] for s in (0, n // 2, n - 64)], 8)
    _check_same(F0, F1)
    # observed: 61 pairs decided, rays 5,821,738 -> 5,819,851 (0.03% saved): a cluster of Sponza's
    # 1,047 patches spans metres, and few pencils that long miss its columns and arches
    assert decided > 30 and rays1 < rays0
