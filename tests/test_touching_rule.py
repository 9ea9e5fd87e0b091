"""The clustered kernel's touching rule (formfactors/clustered.py, ``_touching_area_ff``): two
perpendicular triangulated rectangles sharing an edge, against the closed form (catalogue C-14),
reciprocity to the bit, and its counter of contour integrals."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hfrad.formfactors.analytic import perpendicular_rectangles
from hfrad.formfactors.clustered import ClusterGeometry, clustered_block, touching_pairs


def _grid(origin, u, v, m):
    """(2 m^2, 3, 3): the rectangle origin + [0, 1] u + [0, 1] v as m x m quads of two triangles,
    wound so that the normal is u x v."""
    tris = []
    for a in range(m):
        for b in range(m):
            p00 = origin + (a / m) * u + (b / m) * v
            p10 = origin + ((a + 1) / m) * u + (b / m) * v
            p01 = origin + (a / m) * u + ((b + 1) / m) * v
            p11 = origin + ((a + 1) / m) * u + ((b + 1) / m) * v
            tris += [(p00, p10, p11), (p00, p11, p01)]
    return np.array(tris, float)


def _corner(edge, width1, width2, m):
    """A clustered scene of two patches: the floor (edge along x, width1 along y, facing +z) and the
    wall (the same edge, width2 along z, facing +y), each m x m quads of two triangles."""
    x = np.array([edge, 0.0, 0.0])
    floor = _grid(np.zeros(3), x, np.array([0.0, width1, 0.0]), m)
    wall = _grid(np.zeros(3), np.array([0.0, 0.0, width2]), x, m)
    tri = np.concatenate([floor, wall])
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    tri_areas = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / (2.0 * tri_areas[:, None])
    k = len(floor)
    start = np.array([0, k, 2 * k])
    areas = np.add.reduceat(tri_areas, start[:-1])
    vectors = np.add.reduceat(tri_areas[:, None] * normals, start[:-1])
    centroids = np.add.reduceat(tri_areas[:, None] * tri.mean(axis=1), start[:-1]) / areas[:, None]
    flat = tri.reshape(-1, 3)
    return SimpleNamespace(patch_triangles=(start, np.arange(2 * k)), triangles=tri, n_triangles=2 * k,
                           triangle_normals=normals, triangle_areas=tri_areas, n_patches=2, areas=areas,
                           area_vectors=vectors, normals=vectors / np.linalg.norm(vectors, axis=1)[:, None],
                           centroids=centroids, bounds=np.array([flat.min(axis=0), flat.max(axis=0)]))


@pytest.mark.parametrize("edge, width1, width2, m", [
    (1.0, 1.0, 1.0, 4),    # 32 triangles a patch (1,024 pairs, EXACT_PAIRS): observed 3.6e-6 (old rule 8.8e-4)
    (1.0, 0.5, 2.0, 6),    # 72 triangles a patch, unequal widths: observed 1.5e-4 (old 4.0e-4)
    (2.0, 1.0, 0.3, 5),    # a long edge, a narrow wall of slivers: observed 1.6e-3 (old 2.0e-3)
    (1.0, 1.0, 1.0, 8),    # 128 triangles a patch: observed 4.3e-4 (old 3.8e-4)
])
def test_touching_rule_matches_perpendicular_rectangles(edge, width1, width2, m):
    # the rule's tolerance is CLUSTER_TOLERANCE (3e-2) per contact triangle pair; the sum is far closer
    geom = ClusterGeometry(_corner(edge, width1, width2, m))
    exact = edge * width1 * perpendicular_rectangles(edge, width1, width2)   # A_1 F_12, m^2
    got = touching_pairs(geom, [0], [1])[0]
    assert got == pytest.approx(exact, rel=4e-3)


def test_touching_rule_is_reciprocal_to_the_bit_and_used_by_the_kernel():
    geom = ClusterGeometry(_corner(1.0, 0.7, 1.3, 4), memo=False)   # both orders computed
    both = touching_pairs(geom, [0, 1], [1, 0])
    assert both[0] == both[1] > 0
    F = clustered_block(geom, np.arange(2), np.arange(2))
    assert geom.areas[0] * F[0, 1] == pytest.approx(geom.areas[1] * F[1, 0], rel=1e-15)
    # the kernel's pair is this rule's (32 x 32 triangle pairs: EXACT_PAIRS, and the patches touch)
    assert F[0, 1] == pytest.approx(both[0] / geom.areas[0], rel=1e-12)


def test_shared_budget_takes_fewer_contour_integrals_at_a_like_error():
    geom = ClusterGeometry(_corner(1.0, 1.0, 1.0, 4))
    exact = perpendicular_rectangles(1.0, 1.0, 1.0)
    value, count = touching_pairs(geom, [0], [1], count=True)
    # every triangle pair nearer than kernel.py's NEAR with both rules and its own budget
    each, each_count = touching_pairs(geom, [0], [1], rules=[3.0, 3.0, 1e9, 0.0, 0.0], count=True)
    assert 0 < count[0] < 0.7 * each_count[0]
    assert abs(value[0] - exact) < 3 * abs(each[0] - exact) + 1e-4 * exact
