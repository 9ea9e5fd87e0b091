"""Parts of the cluster growing (hfrad.scene.cluster.growing) against plain NumPy: per-cluster sums,
relabelling, compatibility classes, vertex stars and reach (issue 46: clustering in a fraction of the time,
the same clusters)."""

from __future__ import annotations

import numpy as np

from hfrad.scene.builtin import cornell_box
from hfrad.scene.cluster.growing import (_cluster_sums, _reach, _relabel, _vertex_stars, compatibility_classes)
from hfrad.scene.patches import subdivide
from hfrad.scene.weld import row_ids, weld


def test_cluster_sums_are_the_bincounts():
    rng = np.random.default_rng(2)
    t, count = 4000, 60
    label = rng.integers(-1, count, t)
    area, nrm, cent, key = rng.uniform(0, 1, t), rng.normal(size=(t, 3)), rng.normal(size=(t, 3)), rng.integers(0, 3, t)
    c_area, c_vec, c_sum, c_count, c_key = _cluster_sums(label, count, key, area, nrm, cent)
    ok = label >= 0
    # bincount adds in index order as the loop does: the same bits, not only close
    np.testing.assert_array_equal(c_area, np.bincount(label[ok], weights=area[ok], minlength=count))
    for k in range(3):
        np.testing.assert_array_equal(c_vec[:, k], np.bincount(label[ok], weights=area[ok] * nrm[ok, k], minlength=count))
        np.testing.assert_array_equal(c_sum[:, k], np.bincount(label[ok], weights=area[ok] * cent[ok, k], minlength=count))
    np.testing.assert_array_equal(c_count, np.bincount(label[ok], minlength=count))
    last = np.zeros(count, np.int64)
    last[label[ok]] = key[ok]
    np.testing.assert_array_equal(c_key, last)


def test_relabel_is_np_unique_inverse():
    rng = np.random.default_rng(4)
    label = rng.choice(np.array([-1, 3, 7, 8, 20, 41]), 500)
    expected = label.copy()
    used, inverse = np.unique(label[label >= 0], return_inverse=True)
    expected[label >= 0] = inverse
    assert _relabel(label) == len(used)
    np.testing.assert_array_equal(label, expected)


def test_compatibility_classes_are_the_ids_of_whole_rows():
    scene = subdivide(cornell_box(), patches=400)
    whole = row_ids(np.column_stack([scene.material, scene.group, scene.reflectance, scene.emission]))
    np.testing.assert_array_equal(compatibility_classes(scene), whole)
    reflectance = np.array(scene.reflectance)
    reflectance[::5] *= 0.5  # colours set per patch: they no longer follow the materials
    varied = scene.replace(reflectance=reflectance)
    whole = row_ids(np.column_stack([varied.material, varied.group, varied.reflectance, varied.emission]))
    assert len(np.unique(whole)) > len(np.unique(compatibility_classes(scene)))
    np.testing.assert_array_equal(compatibility_classes(varied), whole)


def test_vertex_stars_and_reach():
    scene = subdivide(cornell_box(), patches=300)
    welded = weld(scene.vertices, scene.faces)
    start, members = _vertex_stars(welded, int(welded.max()) + 1)
    order = np.argsort(welded.reshape(-1), kind="stable")
    np.testing.assert_array_equal(members, np.repeat(np.arange(len(welded)), 3)[order])
    np.testing.assert_array_equal(np.diff(start), np.bincount(welded.reshape(-1)))
    tri, cent = np.asarray(scene.triangles), np.asarray(scene.centroids)
    np.testing.assert_allclose(_reach(np.ascontiguousarray(tri), np.ascontiguousarray(cent)),
                               np.linalg.norm(tri - cent[:, None], axis=2).max(axis=1), rtol=1e-15)
