"""Eq. (3) of formfactors/clustered.py: triangles far from a quadrature point take the disk-corrected
point rule instead of Lambert's contour integral (POINT_FAR); checked against the contour integral."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.formfactors.clustered import POINT_FAR, ClusterGeometry, _point_to_cluster, clustered_block
from hfrad.formfactors.kernel import point_to_patch
from hfrad.scene.builtin import cornell_box
from hfrad.scene.cluster import cluster
from hfrad.scene.patches import subdivide


def _one_triangle(tri):
    """Arrays of _point_to_cluster for one triangle (3, 3): corners, normal, area, centroid, diameter."""
    T = np.ascontiguousarray(np.asarray(tri, float).reshape(1, 3, 3))
    cr = np.cross(T[0, 1] - T[0, 0], T[0, 2] - T[0, 0])
    N = (cr / np.linalg.norm(cr)).reshape(1, 3)
    A = np.array([0.5 * np.linalg.norm(cr)])
    C = T.mean(axis=1)
    D = np.array([np.linalg.norm(T[0] - np.roll(T[0], 1, axis=0), axis=1).max()])
    return T, N, A, C, D


def _rule(tri, point, normal, far=POINT_FAR):
    T, N, A, C, D = _one_triangle(tri)
    return _point_to_cluster(*point, *normal, T, N, A, C, D, 0, 1, 1e-12, far * far)


# an equilateral triangle of edge 0.1 m facing -z, centred on the z axis, lifted to height h
_TRI = np.array([[0.05, -0.0289, 0.0], [-0.05, -0.0289, 0.0], [0.0, 0.0577, 0.0]])


@pytest.mark.parametrize("h, shift, tilt, tol", [
    (0.4, 0.0, 0.0, 4e-3),    # coaxial at 4 diameters: observed 1.8e-3
    (0.6, 0.3, 0.0, 4e-3),    # off axis: observed 1.6e-3
    (0.5, 0.2, 0.5, 8e-3),    # off axis and tilted: observed 3.5e-3
])
def test_point_rule_matches_the_contour_integral_beyond_point_far(h, shift, tilt, tol):
    c, s = np.cos(tilt), np.sin(tilt)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    tri = (_TRI @ rot.T) + [shift, 0.0, h]   # its corners wind clockwise seen from +z: it faces -z
    x, n = np.zeros(3), np.array([0.0, 0.0, 1.0])
    exact = point_to_patch(x[None], n, tri)[0]
    assert exact > 0
    assert _rule(tri, x, n) == pytest.approx(exact, rel=tol)


def test_point_rule_leaves_near_and_straddling_triangles_to_the_contour_integral():
    x = np.zeros(3)
    # nearer than POINT_FAR diameters: eq. (1) itself, to the bit
    tri = _TRI + [0.0, 0.0, 0.2]
    assert _rule(tri, x, [0.0, 0.0, 1.0]) == point_to_patch(x[None], np.array([0.0, 0.0, 1.0]), tri)[0]
    # far, but crossing the point's tangent plane (the point's normal along x): eq. (1) clips it
    n = np.array([1.0, 0.0, 0.0])
    tri = _TRI + [0.02, 0.0, 1.0]
    exact = point_to_patch(x[None], n, tri)[0]
    assert 0 < exact and _rule(tri, x, n) == exact
    # far and behind the triangle's plane: 0
    assert _rule(_TRI[::-1] + [0.0, 0.0, 1.0], x, [0.0, 0.0, 1.0]) == 0.0


def test_clustered_F_moves_by_far_less_than_its_own_error():
    """A refined Cornell box clustered to ~600 patches: F with the point rule against F with the
    contour integral for every triangle (POINT_FAR infinite)."""
    c = cluster(subdivide(cornell_box(), patches=2400), patches=600)
    rows = np.arange(c.n_patches)
    F = clustered_block(ClusterGeometry(c), rows, rows)
    exact = clustered_block(ClusterGeometry(c, point_far=np.inf), rows, rows)
    assert np.linalg.norm(F - exact) / np.linalg.norm(exact) < 2e-3       # observed 7.6e-4
    assert np.abs(F.sum(axis=1) - exact.sum(axis=1)).max() < 6e-3         # observed 2.3e-3
    AF = c.areas[:, None] * F
    np.testing.assert_allclose(AF, AF.T, rtol=1e-12, atol=1e-17)          # still reciprocal
