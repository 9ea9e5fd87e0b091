"""Conforming subdivision: no T-junctions, bounded shapes, area kept (issue 11)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hfrad.scene.builtin import _Builder, _plate_materials, cornell_box
from hfrad.scene.patches import subdivide


def _edges(scene) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected patch edges (vertex-index pairs, vertices merged by position) and their use counts."""
    key = np.rint(scene.vertices * 1e9).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    f = inv.reshape(-1)[scene.faces]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges, count = np.unique(e, axis=0, return_counts=True)
    points = np.zeros((inv.max() + 1, 3))
    points[inv.reshape(-1)] = scene.vertices
    return points[edges], count


def _t_junctions(scene, tol: float = 1e-9) -> int:
    """How many (vertex, edge) pairs have the vertex strictly inside the edge."""
    seg, _ = _edges(scene)
    pts = np.unique(scene.vertices, axis=0)
    a, b = seg[:, 0], seg[:, 1]
    length = np.linalg.norm(b - a, axis=1)
    hits = 0
    for k, cand in enumerate(cKDTree(pts).query_ball_point(0.5 * (a + b), 0.5 * length + tol)):
        if not cand:
            continue
        p = pts[cand]
        t = (p - a[k]) @ (b[k] - a[k]) / length[k] ** 2
        off = np.linalg.norm(p - a[k] - t[:, None] * (b[k] - a[k]), axis=1)
        hits += int(((off < tol) & (t > 1e-9) & (t < 1 - 1e-9)).sum())
    return hits


def _min_angle(scene) -> float:
    t = scene.triangles
    out = []
    for k in range(3):
        u, v = t[:, (k + 1) % 3] - t[:, k], t[:, (k + 2) % 3] - t[:, k]
        cos = (u * v).sum(1) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        out.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return float(np.min(out))


@pytest.fixture(scope="module")
def cornell():
    return cornell_box()


@pytest.mark.parametrize("patches", [3000, 10000])
def test_cornell_patches_conform(cornell, patches):
    s = subdivide(cornell, patches=patches)
    assert 0.9 * patches <= s.n_patches <= 1.1 * patches
    # the box is closed: with no T-junctions every patch edge has exactly two patches
    _, count = _edges(s)
    assert (count == 2).all(), f"edge use counts {np.bincount(count)}"
    assert _t_junctions(s) == 0
    # no slivers: observed minimum angle 23.8 deg (3K), 25.4 deg (10K)
    assert _min_angle(s) > 20.0, _min_angle(s)
    for k in range(len(cornell.materials)):
        a0, a1 = cornell.areas[cornell.material == k].sum(), s.areas[s.material == k].sum()
        assert abs(a1 - a0) <= 1e-12 * a0 * s.n_patches
    # patches face the same way as the faces they were cut from
    assert ((s.normals * cornell.normals[s.parent]).sum(axis=1) > 1 - 1e-9).all()


def test_max_edge_is_a_bound(cornell):
    s = subdivide(cornell, max_edge=0.1)
    edges = np.linalg.norm(s.triangles - np.roll(s.triangles, 1, axis=1), axis=2)
    assert edges.max() <= 0.1 * (1 + 1e-9)
    assert np.median(edges.max(axis=1)) > 0.07  # not needlessly fine
    assert _min_angle(s) > 20.0


def test_input_t_junction_becomes_a_shared_vertex():
    # plate1 (one quad) meets plate2 (two quads) at 90 degrees along x in [0, 1]:
    # the vertex (0.4, 0, 0) of plate2 lies inside plate1's edge (a T-junction in the input)
    b = _Builder()
    b.quad((0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0), "plate1", "plate1")
    b.quad((0, 0, 0), (0.4, 0, 0), (0.4, 1, 0), (0, 1, 0), "plate2", "plate2")
    b.quad((0.4, 0, 0), (1, 0, 0), (1, 1, 0), (0.4, 1, 0), "plate2", "plate2")
    scene = b.build(_plate_materials(), "t-junction")
    assert _t_junctions(scene) > 0
    s = subdivide(scene, max_edge=0.3)
    assert _t_junctions(s) == 0
    seg, count = _edges(s)
    on_crease = (np.abs(seg[:, :, 1:]) < 1e-12).all(axis=(1, 2))  # both ends on y = z = 0
    assert (count[on_crease] == 2).all() and (count[~on_crease] <= 2).all()
    # the pieces on the crease: 0-0.4 cut in 2, 0.4-1 cut in 2 (each at most 0.3 long)
    assert on_crease.sum() == 4
    assert s.areas.sum() == pytest.approx(2.0, rel=1e-12)


def test_block_standing_on_an_uncut_floor_meets_it_along_the_contact_line():
    # CornellBox-Original's blocks stand on a floor of two triangles: their bottom edges lie
    # inside the floor; they must become edges of the floor's patches (same points)
    b = _Builder()
    b.quad((0, 0, 2), (2, 0, 2), (2, 0, 0), (0, 0, 0), "plate2", "floor")  # faces +y
    x0, x1, z0, z1, top = 0.6, 1.3, 0.5, 1.2, 0.5
    foot = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
    for k in range(4):
        (xa, za), (xb, zb) = foot[k], foot[(k + 1) % 4]
        b.quad((xa, 0, za), (xb, 0, zb), (xb, top, zb), (xa, top, za), "plate1", "block")
    b.quad((x0, top, z0), (x0, top, z1), (x1, top, z1), (x1, top, z0), "plate1", "block")
    s = subdivide(b.build(_plate_materials(), "block on floor"), max_edge=0.2)
    assert _t_junctions(s) == 0
    seg, count = _edges(s)
    on_floor = (np.abs(seg[:, :, 1]) < 1e-12).all(axis=1)
    inside = on_floor & (seg[:, :, 0] > 0.1).all(axis=1) & (seg[:, :, 0] < 1.9).all(axis=1) \
        & (seg[:, :, 2] > 0.1).all(axis=1) & (seg[:, :, 2] < 1.9).all(axis=1)
    # edges on the footprint's outline: two floor patches and one block side each
    outline = inside & (count == 3)
    assert outline.sum() == 4 * 4  # each 0.7 m side cut into 4 pieces of at most 0.2 m
    assert (count[inside & ~outline] == 2).all()
    floor = s.group == s.groups.index("floor")
    assert s.areas[floor].sum() == pytest.approx(4.0, rel=1e-12)
