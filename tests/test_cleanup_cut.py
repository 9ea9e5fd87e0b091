"""The compiled overlap cut and coplanar sweep (hfrad.scene.coplanar, used by hfrad.scene.cleanup)
against plain NumPy references (issue 46: cleaning the conference room in a fraction of the time,
the same triangles)."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.scene.cleanup import PLANE_ANGLE, WELD, find_face_problems, resolve_overlaps
from hfrad.scene.coplanar import by_plane_then_u, plane_coordinates, plane_keys
from hfrad.scene.scene import Material, Scene


def _reference_clip(poly, a, inward, keep_inside):
    side = (poly - a) @ inward
    side = side if keep_inside else -side
    out = []
    for k in range(len(poly)):
        sp, sq = side[k], side[(k + 1) % len(poly)]
        if sp >= 0:
            out.append(poly[k])
        if (sp >= 0) != (sq >= 0):
            out.append(poly[k] + sp / (sp - sq) * (poly[(k + 1) % len(poly)] - poly[k]))
    return np.array(out) if len(out) >= 3 else None


def _reference_minus(polys, tri, n):
    """Convex pieces of ``polys`` outside triangle ``tri``, one edge at a time (Sutherland-Hodgman)."""
    out = []
    inward = np.cross(n, np.roll(tri, -1, axis=0) - tri)
    for poly in polys:
        inside = poly
        for e in range(3):
            piece = _reference_clip(inside, tri[e], inward[e], False)
            if piece is not None:
                out.append(piece)
            inside = _reference_clip(inside, tri[e], inward[e], True)
            if inside is None:
                break
    return out


def _polygon_area(poly):
    return 0.5 * np.linalg.norm(np.cross(poly[1:-1] - poly[0], poly[2:] - poly[0]), axis=1).sum()


def _tilted_layers(seed: int, count: int = 12) -> Scene:
    """``count`` random triangles of one orientation in a tilted plane, overlapping each other."""
    rng = np.random.default_rng(seed)
    n = np.array([0.3, 0.8, 0.52])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    uv = rng.uniform(0, 2, (count, 3, 2))
    e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    flip = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0  # all counter-clockwise about n
    uv[flip] = uv[flip][:, ::-1]
    points = np.array([1.0, 2.0, 3.0]) + uv[..., :1] * u + uv[..., 1:] * v
    return Scene(vertices=points.reshape(-1, 3), faces=np.arange(3 * count).reshape(-1, 3),
                 material=np.zeros(count, np.int64), materials=(Material("floor", (0.5, 0.5, 0.5)),))


@pytest.mark.parametrize("seed", range(4))
def test_compiled_cut_matches_a_plain_numpy_clip(seed):
    scene = _tilted_layers(seed)
    report = find_face_problems(scene)
    assert len(report.overlaps) >= 5
    cut, counts = resolve_overlaps(scene, report.overlaps)
    # the reference: each later face minus every earlier face paired with it, fanned, small pieces dropped
    tri, n = np.asarray(scene.triangles), np.asarray(scene.normals)
    below = {}
    for i, j in report.overlaps:
        below.setdefault(int(j), []).append(int(i))
    pieces = []
    for j in sorted(below):
        polys = [tri[j]]
        for i in below[j]:
            polys = _reference_minus(polys, tri[i], n[j])
        for poly in (p for p in polys if _polygon_area(p) > 1e-4 * scene.areas[j]):
            pieces += [poly[[0, k, k + 1]] for k in range(1, len(poly) - 1)
                       if 0.5 * np.linalg.norm(np.cross(poly[k] - poly[0], poly[k + 1] - poly[0])) > 1e-6 * scene.areas[j]]
    kept = np.setdiff1d(np.arange(scene.n_patches), list(below))
    new = np.asarray(cut.triangles)[len(kept):]
    assert counts["pieces"] == len(new) == len(pieces)
    # the same operations; BLAS may order the sums of (p - a) . inward otherwise on another CPU (a few ulps)
    np.testing.assert_allclose(new, np.array(pieces), rtol=0, atol=1e-13)
    # the union is kept and covered once: a point under some face before lies under exactly one after
    samples = np.random.default_rng(99).uniform(0, 2, (4000, 2))
    before, after = _coverage(scene, samples), _coverage(cut, samples)
    np.testing.assert_array_equal(after[before > 0], 1)
    np.testing.assert_array_equal(after[before == 0], 0)


def _coverage(scene: Scene, samples: np.ndarray) -> np.ndarray:
    """How many faces cover each of the (s, 2) points (in the scene's plane coordinates)."""
    n = np.asarray(scene.normals)[0]
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    t = np.asarray(scene.triangles) - np.array([1.0, 2.0, 3.0])
    tuv = np.stack([t @ u, t @ v], axis=2)  # (f, 3, 2)
    a, b, c = tuv[:, 0][:, None], tuv[:, 1][:, None], tuv[:, 2][:, None]
    p = samples[None]

    def edge(x, y):
        return (y[..., 0] - x[..., 0]) * (p[..., 1] - x[..., 1]) - (y[..., 1] - x[..., 1]) * (p[..., 0] - x[..., 0])
    inside = (edge(a, b) > 1e-9) & (edge(b, c) > 1e-9) & (edge(c, a) > 1e-9)
    return inside.sum(axis=0)


def test_plane_keys_and_coordinates_match_numpy():
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tri = rng.uniform(-3, 3, (500, 3, 3))
    centre, step = np.array([0.1, -0.2, 0.3]), WELD * 6.0
    flip, plane_n, key = plane_keys(tri, normals, centre, np.array([0.2113248654, 0.5773502692, 0.7886751346]),
                                     PLANE_ANGLE, step)
    ref_flip = np.where(normals @ np.array([0.2113248654, 0.5773502692, 0.7886751346]) < 0, -1.0, 1.0)
    np.testing.assert_array_equal(flip, ref_flip)
    np.testing.assert_array_equal(plane_n, normals * ref_flip[:, None])
    offset = np.einsum("pd,pd->p", plane_n, tri.mean(axis=1) - centre)
    np.testing.assert_array_equal(key[:, :3], np.rint(plane_n / PLANE_ANGLE))
    assert np.abs(key[:, 3] - offset / step).max() <= 0.5 + 1e-6
    uv, lo, hi = plane_coordinates(tri, plane_n, centre)
    helper = np.where(np.abs(plane_n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    u = np.cross(plane_n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(plane_n, u)
    ref = np.stack([np.einsum("pkd,pd->pk", tri - centre, u), np.einsum("pkd,pd->pk", tri - centre, v)], axis=2)
    np.testing.assert_allclose(uv, ref, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(lo, uv.min(axis=1))
    np.testing.assert_array_equal(hi, uv.max(axis=1))


@pytest.mark.parametrize("seed", range(3))
def test_plane_order_is_the_lexsort(seed):
    rng = np.random.default_rng(seed)
    plane = rng.integers(0, [3, 40, 2000][seed], 5000)
    u = np.round(rng.normal(size=5000), 1)  # many ties, broken by index
    u[::7] = -0.0
    u[1::7] = 0.0
    np.testing.assert_array_equal(by_plane_then_u(plane, int(plane.max()) + 1, u), np.lexsort((u, plane)))
