"""The one welding rule of scene/ (hfrad.scene.weld): what is welded, what is kept apart, far from the origin."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.scene.builtin import cornell_box
from hfrad.scene.cleanup import find_face_problems
from hfrad.scene.patches import split_faces
from hfrad.scene.weld import weld, weld_points

#: A box of side 2 centred on the origin: the grid step is 2 * rel_tol and the grid is centred at 0.
BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _grid_points(step: float, origin: np.ndarray) -> np.ndarray:
    """(27, 3): a 3 x 3 x 3 block of grid points 10 steps apart, around ``origin``."""
    k = np.array([-10, 0, 10])
    return origin + step * np.stack(np.meshgrid(k, k, k, indexing="ij"), axis=-1).reshape(-1, 3)


@pytest.mark.parametrize("shift", [0.0, 1e5])
def test_within_tolerance_welded_just_outside_kept(shift):
    rel_tol = 1e-6
    step = 2 * rel_tol  # the box's largest side is 2
    bounds = BOX + shift
    base = _grid_points(step, np.full(3, shift))
    rng = np.random.default_rng(4)
    # copies moved by up to 0.4 steps along each axis stay in the grid point's cell: one vertex each
    near = base + rng.uniform(-0.4, 0.4, base.shape) * step
    ids = weld_points(np.vstack([base, near]), rel_tol=rel_tol, bounds=bounds)
    np.testing.assert_array_equal(ids[:27], ids[27:])
    assert len(np.unique(ids)) == 27
    # copies moved by 1.1 steps along one axis are another vertex (any axis, either direction)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            far = base.copy()
            far[:, axis] += sign * 1.1 * step
            ids = weld_points(np.vstack([base, far]), rel_tol=rel_tol, bounds=bounds)
            assert len(np.unique(ids)) == 54, (axis, sign)


def test_far_from_origin_welds_as_at_the_origin():
    """A 1 mm part 100 km from the origin: a tolerance relative to the largest coordinate (1e5 x 1e-9
    = 0.1 mm) would weld its vertices 0.01 mm apart; relative to its size, they stay apart."""
    rng = np.random.default_rng(7)
    pts = rng.integers(0, 100, (400, 3)) * 1e-5  # on a 0.01 mm grid, 1 mm wide, many repeated
    at_origin = weld_points(pts)
    far = weld_points(pts + 1e5)
    np.testing.assert_array_equal(far, at_origin)
    expected = np.unique(pts, axis=0, return_inverse=True)[1].reshape(-1)
    np.testing.assert_array_equal(at_origin, expected)


def test_the_same_point_computed_two_ways_welds_where_float64_cannot_resolve_the_tolerance(monkeypatch):
    """At 1e9 m, one float64 step is 1.2e-7 m, above 1e-9 of a 10 m scene: the ULPS floor of the
    grid step still welds a point at a third of an edge computed as a + (b - a) / 3 and as (2a + b) / 3."""
    a = np.array([1000000000.8574042, 1000000000.0335855, 1000000000.7296555])
    b = np.array([1000000003.4383048, 1000000008.8021959, 1000000006.6028064])
    m1 = a + (b - a) / 3
    m2 = (2 * a + b) / 3
    assert not np.array_equal(m1, m2)  # two roundings of one point
    ids = weld_points(np.array([a, b, m1, m2]), bounds=np.array([a, a + 10.0]))
    assert ids[2] == ids[3] and len(np.unique(ids)) == 3
    # without the floor the grid step would be 1e-8 m, a twelfth of float64's step there: not welded
    monkeypatch.setattr("hfrad.scene.weld.ULPS", 0)
    ids = weld_points(np.array([a, b, m1, m2]), bounds=np.array([a, a + 10.0]))
    assert ids[2] != ids[3]


def test_weld_renumbers_face_corners_and_ignores_unused_vertices():
    # two triangles of a soup sharing an edge, plus an unused vertex far away
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1e3, 1e3, 1e3]], float)
    f = np.array([[0, 1, 2], [3, 5, 4]])
    w = weld(v, f)
    assert w.shape == (2, 3)
    assert w[0, 1] == w[1, 0] and w[0, 2] == w[1, 2]
    assert len(np.unique(w)) == 4
    # the unused vertex does not widen the tolerance: a point 1e-6 from a corner is its own vertex
    v2 = np.vstack([v, [[1 + 1e-6, 1, 0]]])
    f2 = np.vstack([f, [[5, 7, 2]]])
    w2 = weld(v2, f2)
    assert w2[2, 1] != w2[1, 1]
    assert weld(v, np.zeros((0, 3), np.int64)).shape == (0, 3)
    assert weld_points(np.zeros((0, 3))).shape == (0,)


def test_every_welder_shares_the_rule():
    """Cutting into patches and the duplicate-face check weld the same points the same way."""
    box = cornell_box()
    cut, _ = split_faces(box, np.full(box.n_patches, 3))
    # the cut's vertices are welded: no two are within the tolerance of each other
    assert len(np.unique(weld_points(cut.vertices, bounds=cut.bounds))) == len(cut.vertices)
    # a copy of a face whose corners moved by well under the tolerance is found as a duplicate
    size = float(np.max(np.ptp(box.bounds, axis=0)))
    moved = box.vertices + 1e-9 * size
    soup = box.replace(vertices=np.vstack([box.vertices, moved]),
                       faces=np.vstack([box.faces, box.faces[:1] + len(box.vertices)]),
                       material=np.r_[box.material, box.material[:1]], group=np.r_[box.group, box.group[:1]],
                       reflectance=np.vstack([box.reflectance, box.reflectance[:1]]),
                       emission=np.vstack([box.emission, box.emission[:1]]), parent=np.r_[box.parent, box.parent[:1]])
    np.testing.assert_array_equal(find_face_problems(soup).duplicates, [[0, box.n_patches]])
