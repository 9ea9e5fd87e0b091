"""Form-factor kernel against the view-factor catalogue, closure and reciprocity."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import InputError
from hfrad.formfactors import analytic, form_factor_matrix, point_to_patch, unoccluded_block
from hfrad.formfactors.kernel import PatchGeometry
from hfrad.scene.builtin import coaxial_disks, cornell_box, parallel_plates, perpendicular_plates
from hfrad.scene.patches import subdivide


def plate_view_factor(scene, F, src="plate1", dst="plate2") -> float:
    """Area-weighted F from group ``src`` to group ``dst``."""
    p1 = scene.group == scene.groups.index(src)
    p2 = scene.group == scene.groups.index(dst)
    a = scene.areas
    return float((a[p1, None] * F[np.ix_(p1, p2)]).sum() / a[p1].sum())


def unoccluded(scene) -> np.ndarray:
    g = PatchGeometry(scene)
    return unoccluded_block(g, np.arange(g.n), np.arange(g.n))


def polygon_disks(r1, r2, distance, segments):
    """Closed form for disks of the regular polygons' areas (the built-in disks are polygons)."""
    shrink = np.sqrt(np.sin(2 * np.pi / segments) / (2 * np.pi / segments))
    return analytic.coaxial_disks(r1 * shrink, r2 * shrink, distance)


def parallel_unequal(rect1, rect2, distance):
    """Two parallel, aligned rectangles: plate1 = rect1 at z = 0 facing +z, plate2 = rect2 at z = distance."""
    from hfrad.scene.builtin import _Builder, _plate_materials

    b = _Builder()
    (x1, x2, y1, y2), (u1, u2, v1, v2) = rect1, rect2
    b.quad((x1, y1, 0), (x2, y1, 0), (x2, y2, 0), (x1, y2, 0), "plate1", "plate1")
    b.quad((u1, v1, distance), (u1, v2, distance), (u2, v2, distance), (u2, v1, distance), "plate2", "plate2")
    return b.build(_plate_materials(), "parallel_unequal")


# (name, scene factory, exact F_1->2, exact F_2->1): the view-factor catalogue [Howell]
CASES = [
    ("C-11 parallel 1x1 d1", lambda: parallel_plates(1, 1, 1), analytic.parallel_rectangles(1, 1, 1)),
    ("C-11 parallel 2x1 d0.5", lambda: parallel_plates(2, 1, 0.5), analytic.parallel_rectangles(2, 1, 0.5)),
    ("C-11 parallel 1x1 d0.1", lambda: parallel_plates(1, 1, 0.1), analytic.parallel_rectangles(1, 1, 0.1)),
    ("C-11 parallel 1x1 d3", lambda: parallel_plates(1, 1, 3), analytic.parallel_rectangles(1, 1, 3)),
    ("C-13 unequal concentric", lambda: parallel_unequal((0, 2, 0, 1), (0.5, 1.5, 0.25, 0.75), 0.7),
     analytic.parallel_rectangles_offset((0, 2, 0, 1), (0.5, 1.5, 0.25, 0.75), 0.7)),
    ("C-13 offset", lambda: parallel_unequal((0, 1, 0, 1), (0.5, 2, 0.2, 1.5), 0.3),
     analytic.parallel_rectangles_offset((0, 1, 0, 1), (0.5, 2, 0.2, 1.5), 0.3)),
    ("C-14 perpendicular 1,1,1", lambda: perpendicular_plates(1, 1, 1), analytic.perpendicular_rectangles(1, 1, 1)),
    ("C-14 perpendicular 2,0.5,1", lambda: perpendicular_plates(2, 0.5, 1), analytic.perpendicular_rectangles(2, 0.5, 1)),
    ("C-14 perpendicular 1,2,0.5", lambda: perpendicular_plates(1, 2, 0.5), analytic.perpendicular_rectangles(1, 2, 0.5)),
    ("C-41 disks 1,1,1", lambda: coaxial_disks(1, 1, 1, segments=48), polygon_disks(1, 1, 1, 48)),
    ("C-41 disks 1,0.5,0.5", lambda: coaxial_disks(1, 0.5, 0.5, segments=48), polygon_disks(1, 0.5, 0.5, 48)),
    ("C-41 disks 0.5,1,2", lambda: coaxial_disks(0.5, 1, 2, segments=48), polygon_disks(0.5, 1, 2, 48)),
]
SPLITS = (1, 4, 12)  # edge splits of the longest side: from 2 triangles per plate to hundreds


def _both_directions(scene, F, exact_12):
    """Relative errors of F_1->2 and of F_2->1 (exact: A1 F12 / A2, reciprocity)."""
    a1 = scene.areas[scene.group == scene.groups.index("plate1")].sum()
    a2 = scene.areas[scene.group == scene.groups.index("plate2")].sum()
    f12 = plate_view_factor(scene, F)
    f21 = plate_view_factor(scene, F, "plate2", "plate1")
    return f12 / exact_12 - 1, f21 / (exact_12 * a1 / a2) - 1


@pytest.mark.parametrize("splits", SPLITS, ids=[f"split{m}" for m in SPLITS])
@pytest.mark.parametrize("name,make,exact", CASES, ids=[c[0] for c in CASES])
def test_catalogue_within_a_tenth_of_a_percent(name, make, exact, splits):
    base = make()
    size = float(np.ptp(base.bounds, axis=0).max())
    scene = subdivide(base, max_edge=size / splits) if splits > 1 else base
    F = form_factor_matrix(scene)  # with visibility: nothing blocks, so V must be exactly 1
    e12, e21 = _both_directions(scene, F, exact)
    # observed 2e-9 to 8.7e-4 (the worst: C-41 disks 1,1,1 and C-11 d3 at split 12); the target is 0.1%
    assert max(abs(e12), abs(e21)) < 1e-3, f"{name}, {scene.n_patches} patches: F12 error {e12:+.2e}, F21 {e21:+.2e}"
    # V = 1 on every pair; rows of earlier column blocks are reciprocity copies A_j F_ji / A_i
    # of what unoccluded() computes as F_ij: equal to rounding
    np.testing.assert_allclose(F, unoccluded(scene), rtol=4e-15, atol=0)


def test_adaptive_path_converges_with_the_tolerance():
    # every pair on the adaptive path (near = adaptive = huge): the error follows the tolerance
    scene = perpendicular_plates(1, 1, 1)  # two triangles per plate, all pairs share an edge or vertex
    exact = analytic.perpendicular_rectangles(1, 1, 1)
    errors = []
    for tol in (1e-2, 1e-3, 1e-4, 1e-5):
        g = PatchGeometry(scene, near=1e9, adaptive=1e9, tolerance=tol)
        F = unoccluded_block(g, np.arange(g.n), np.arange(g.n))
        errors.append(abs(plate_view_factor(scene, F) / exact - 1))
    assert errors[-1] < 1e-6, errors   # observed 1.6e-7
    # the promise is the tolerance: observed 3.2e-4, 1.5e-5, 3.5e-6, 1.6e-7 (29-65x below each)
    assert all(e < tol for e, tol in zip(errors, (1e-2, 1e-3, 1e-4, 1e-5))), errors


def test_unequal_offset_parallel_rectangles_closed_form():
    # concentric unequal plates through the general parallel-rectangle formula
    exact = analytic.parallel_rectangles_offset((0, 2, 0, 1), (0.5, 1.5, 0.25, 0.75), 0.7)
    assert 0 < exact < 1
    assert analytic.parallel_rectangles_offset((0, 2, 0, 1), (0, 2, 0, 1), 0.7) == pytest.approx(
        analytic.parallel_rectangles(2, 1, 0.7), rel=1e-14)   # observed 2.8e-16
    with pytest.raises(InputError, match="distance must be a positive finite length, got 0"):
        analytic.parallel_rectangles(1, 1, 0)


def test_kernel_options_are_checked():
    from hfrad.formfactors.kernel import split_centroids

    scene = cornell_box()
    with pytest.raises(InputError, match=r"tolerance must be in \(0, 1\), got 0"):
        PatchGeometry(scene, tolerance=0.0)
    with pytest.raises(InputError, match="need finite 0 <= adaptive <= near, got adaptive=4.0, near=3.0"):
        PatchGeometry(scene, adaptive=4.0)
    with pytest.raises(InputError, match="split count must be >= 1, got 0"):
        split_centroids(0)
    assert split_centroids(2).shape == (4, 3)


def test_point_to_patch_is_exact_for_a_differential_area():
    # dA below the corner of a rectangle a x b at height c: catalogue B-3
    a, b, c = 1.0, 2.0, 0.5
    A, B = a / c, b / c
    exact = (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
             + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B))) / (2 * np.pi)
    quad = np.array([[0, 0, c], [0, b, c], [a, b, c], [a, 0, c]], float)  # faces -z
    f = sum(point_to_patch([[0, 0, 0]], [0, 0, 1], quad[list(t)])[0] for t in ((0, 1, 2), (0, 2, 3)))
    assert f == pytest.approx(exact, rel=1e-14)   # observed 2.5e-16
    # half behind the tangent plane: only the front half counts (clipping)
    tilted = np.array([[0, 0, -1], [0, 1, 1], [0, -1, 1]], float)
    assert 0 < point_to_patch([[1, 0, 0]], [0, 0, 1], tilted)[0] < point_to_patch([[1, 0, 0]], [-1, 0, 0], tilted)[0]
    assert point_to_patch([[-1, 0, 0]], [1, 0, 0], tilted)[0] == 0  # behind the patch


@pytest.fixture(scope="module")
def cornell_F():
    scene = subdivide(cornell_box(), patches=1500)
    return scene, form_factor_matrix(scene)


def test_cornell_rows_sum_to_one(cornell_F):
    scene, F = cornell_F
    err = np.abs(F.sum(axis=1) - 1)
    # observed: mean 8.5e-4, max 8.4e-3 (visibility of floor patches between the blocks)
    assert err.mean() < 2e-3, f"mean |row sum - 1| = {err.mean():.2e}"
    assert err.max() < 0.015, f"max |row sum - 1| = {err.max():.2e} (patch {err.argmax()})"


def test_cornell_reciprocity_and_sign(cornell_F):
    scene, F = cornell_F
    assert np.isfinite(F).all()
    assert (F >= 0).all()
    AF = scene.areas[:, None] * F
    np.testing.assert_allclose(AF, AF.T, rtol=1e-14, atol=1e-300)   # observed 1.7e-15
    assert (np.diag(F) == 0).all()


ASPECTS = [(1, 1, 1), (1, 0.1, 1), (1, 1, 0.05), (0.1, 1, 1), (4, 0.2, 0.2), (0.05, 0.5, 0.05)]


@pytest.mark.parametrize("edge,w1,w2", ASPECTS, ids=[f"C-14 {e}x{a}x{b}" for e, a, b in ASPECTS])
def test_adjacent_plates_at_several_aspect_ratios(edge, w1, w2):
    # one quad each (two triangles), sharing an edge: all pairs on the adaptive path
    scene = perpendicular_plates(edge, w1, w2)
    exact = analytic.perpendicular_rectangles(edge, w1, w2)
    e12, e21 = _both_directions(scene, unoccluded(scene), exact)
    # observed 2e-9 to 7.1e-5 (the worst: 4 x 0.2 x 0.2)
    assert max(abs(e12), abs(e21)) < 2.5e-4, f"aspect {edge}:{w1}:{w2}: F12 error {e12:+.2e}, F21 {e21:+.2e}"


def test_differential_element_to_rectangle_both_sides():
    # catalogue B-3 (dA below a corner of a rectangle) integrated over a small plate:
    # the plate-to-rectangle factor tends to B-3 as the plate shrinks, seen from both sides
    a, b, c = 1.0, 2.0, 0.5
    A, B = a / c, b / c
    exact = (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
             + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B))) / (2 * np.pi)
    small = 1e-3
    scene = parallel_unequal((0, small, 0, small), (0, a, 0, b), c)
    F = unoccluded(scene)
    f12 = plate_view_factor(scene, F)
    assert f12 == pytest.approx(exact, rel=5e-3)  # observed 2.1e-3: the plate is not a point (size 2e-3 c)
    e12, e21 = _both_directions(scene, F, f12)
    assert abs(e21) < 1e-14  # reciprocity, exact to rounding: observed 2.0e-15


def test_adjacent_patches_are_finite_and_positive():
    scene = subdivide(perpendicular_plates(1, 1, 1), max_edge=0.25)
    F = unoccluded(scene)
    assert np.isfinite(F).all()
    p1 = np.flatnonzero(scene.group == scene.groups.index("plate1"))
    p2 = np.flatnonzero(scene.group == scene.groups.index("plate2"))
    # the patches touching the shared edge see each other strongly
    touching = [(i, j) for i in p1 for j in p2
                if len(set(map(int, scene.faces[i])) & set(map(int, scene.faces[j]))) >= 1]
    assert touching and all(F[i, j] > 0 for i, j in touching)


def test_coplanar_and_facing_away_are_zero():
    scene = subdivide(parallel_plates(1, 1, 1), max_edge=0.5)
    F = unoccluded(scene)
    p1 = scene.group == scene.groups.index("plate1")
    assert (F[np.ix_(p1, p1)] == 0).all()  # coplanar
    flipped = scene.replace(faces=scene.faces[:, ::-1])  # every patch now faces away
    assert (unoccluded(flipped) == 0).all()


def test_scene_far_from_origin_gives_the_same_form_factors():
    # site coordinates: float32 spacing at 3e6 m is 0.25 m, far above the ray end-point offset
    scene = subdivide(cornell_box(), patches=600)
    shift = np.array([1e6, 2e5, -3e6])
    moved = scene.replace(vertices=scene.vertices + shift, occluder_vertices=scene.occluder_vertices + shift)
    F, G = form_factor_matrix(scene), form_factor_matrix(moved)
    err = (np.abs(F - G) / np.maximum(F, 1e-3)).max()
    # observed 4.2e-4 relative on one entry of 0.047 (adaptive splits decided a rounding apart,
    # within the near rule's tolerance 1e-3); before the fix: 0.43 absolute
    assert err < 1e-3, f"max relative |F - F_translated| = {err:.2e}"
    assert np.abs(F.sum(axis=1) - G.sum(axis=1)).max() < 5e-5  # observed 2.3e-5


def test_kernel_settings_are_recorded_in_the_hfr(tmp_path):
    import hfrad
    from hfrad.formfactors.kernel import KERNEL_VERSION, TOLERANCE
    from hfrad.scene.builtin import furnace

    fac = hfrad.factorize(subdivide(furnace(), max_edge=0.5), eps=0.05)
    hfrad.save(fac, tmp_path / "f.hfr")
    recorded = hfrad.load(tmp_path / "f.hfr").params["form_factors"]
    assert recorded["tolerance"] == TOLERANCE and recorded["kernel_version"] == KERNEL_VERSION
    from hfrad.formfactors.visibility import BOUNDARY_SAMPLES, REFINE_SAMPLES
    assert recorded["refine_samples"] == REFINE_SAMPLES and recorded["boundary_samples"] == BOUNDARY_SAMPLES
    from hfrad.formfactors.budget import LARGE_FACTOR, REFINE_FACTOR
    assert recorded["budget_factors"]["refine"] == REFINE_FACTOR and recorded["budget_factors"]["large"] == LARGE_FACTOR


def test_single_triangle_kernel_equals_the_general_one():
    """Scenes of one triangle per patch take their own block loop (the distant pairs' shortcut
    in SIMD lanes over a row's columns, then the rest pair by pair): the general per-patch
    loop's numbers, bit for bit, on every kind of pair (distant, near, coplanar, itself)."""
    from hfrad.formfactors.kernel import PatchGeometry, _unoccluded_block, row_chunks, unoccluded_block
    from hfrad.scene.builtin import cornell_box
    from hfrad.scene.patches import subdivide

    scene = subdivide(cornell_box(), patches=1500)
    geom = PatchGeometry(scene)
    assert geom.one_triangle_per_patch
    rows = np.arange(scene.n_patches)[::-1].copy()
    cols = np.arange(100, 420)
    fast = unoccluded_block(geom, rows, cols)
    general = np.empty_like(fast)
    _unoccluded_block(geom.triangles, geom.normals, geom.areas, geom.centroids, geom.diameters, geom.start,
                      geom.index, geom.patch_areas, rows, cols, geom.near, geom.adaptive, geom.eps, geom.tolerance,
                      general, row_chunks(len(rows)))
    assert (fast > 0).mean() > 0.3 and (fast == 0).any()
    np.testing.assert_array_equal(fast, general)


@pytest.mark.parametrize("kept", [1, 2])
def test_a_triangle_across_the_tangent_plane_counts_its_front_part(kept):
    """eq. (1)'s clip: a triangle with one or two corners above the plane of dA sends dA what its
    part above the plane sends, that part cut by hand and summed as triangles wholly in front."""
    from hfrad.formfactors.kernel import point_to_patch

    heights = [0.8, -0.5, -0.3] if kept == 1 else [0.8, 0.6, -0.4]
    rel = np.array([[0.3, 0.2, heights[0]], [1.4, -0.1, heights[1]], [0.5, 1.3, heights[2]]])  # dA at 0
    if np.cross(rel[1] - rel[0], rel[2] - rel[0]) @ -rel[0] < 0:   # its front towards dA
        rel = rel[::-1].copy()
    up = np.array([0.0, 0.0, 1.0])
    # the tangent plane of dA: normal ``up`` through the origin; corners' heights over it
    h = rel @ up
    assert ((h > 0).sum() == kept) and (h < 0).any()
    cut = []                          # the polygon above the plane, in the triangle's order
    for k in range(3):
        a, b = rel[k], rel[(k + 1) % 3]
        if h[k] >= 0:
            cut.append(a)
        if (h[k] >= 0) != (h[(k + 1) % 3] >= 0):
            cut.append(a + h[k] / (h[k] - h[(k + 1) % 3]) * (b - a))
    fan = [(cut[0], cut[k], cut[k + 1]) for k in range(1, len(cut) - 1)]
    by_hand = sum(point_to_patch(np.zeros((1, 3)), up, np.array(t))[0] for t in fan)
    clipped = point_to_patch(np.zeros((1, 3)), up, rel)[0]
    assert by_hand > 0.01
    assert clipped == pytest.approx(by_hand, rel=1e-12)
