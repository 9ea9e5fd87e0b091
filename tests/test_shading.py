"""Smooth shading (hfrad.render.shading) and anti-aliased pictures (hfrad.render.image)."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.render import Camera, render_image, render_radiance, smooth_corners
from hfrad.render.raycast import trace_camera
from hfrad.render.image import check_samples
from hfrad.errors import InputError
from hfrad.scene.builtin import cornell_box, furnace
from hfrad.scene.patches import subdivide


@pytest.fixture(scope="module")
def box():
    return subdivide(cornell_box(), patches=1500)


def _linear_field(s):
    """Radiosity linear in height, per patch: its mean over a triangle is its value at the centroid."""
    height = lambda p: 0.2 + 0.4 * p[..., 1]   # noqa: E731 - y in [0, 2] m
    B = np.repeat(height(s.vertices[s.faces].mean(axis=1))[:, None], 3, axis=1)
    return B, height


def _back_wall_inner(s):
    """Triangles of the back wall (z = -1) with every vertex away from its borders."""
    v = s.vertices[s.faces]
    on = (np.abs(v[..., 2] + 1) < 1e-9).all(axis=1)
    inner = ((np.abs(v[..., 0]) < 0.999) & (v[..., 1] > 0.001) & (v[..., 1] < 1.999)).all(axis=1)
    return on & inner


def test_linear_radiosity_is_reproduced_at_every_inner_corner(box):
    # The Cornell box's irregular mesh made the area-weighted vertex mean miss a linear field by up to
    # ~1% of its value (the saw-tooth smudges under the ceiling); the least-squares fit is exact.
    B, height = _linear_field(box)
    corners = smooth_corners(box, B)
    inner = _back_wall_inner(box)
    truth = height(box.vertices[box.faces[inner]])
    err = np.abs(corners[inner, :, 0] - truth).max()
    assert err < 1e-9, err


def test_no_smudges_under_the_ceiling(box):
    # Picture level: every back-wall pixel under the ceiling shows the linear field at its hit point.
    B, height = _linear_field(box)
    w = h = 160
    cam = Camera.parse("front", box.bounds, aspect=1.0)
    radiance, face = render_radiance(box, B, cam, width=w, height=h, samples=1)
    tri, dist, _ = trace_camera(box, cam, w, h)
    o, d = cam.rays(w, h)
    point = (o + dist.reshape(-1, 1) * d).reshape(h, w, 3)
    sel = (tri >= 0) & _back_wall_inner(box)[np.maximum(tri, 0)] & (point[..., 1] > 1.5)
    assert sel.sum() > 500
    rel = np.abs(radiance[sel, 0] * np.pi - height(point[sel])) / height(point[sel])
    assert rel.max() < 1e-6, rel.max()


def test_corners_stay_within_their_neighbours_values():
    s = subdivide(furnace(), patches=300)
    B = np.random.default_rng(1).random((s.n_patches, 3))
    corners = smooth_corners(s, B)
    assert (corners >= B.min(axis=0) - 1e-12).all() and (corners <= B.max(axis=0) + 1e-12).all()


def test_anti_aliased_edge_gets_intermediate_values(box):
    # A bright light on a dark ceiling: without anti-aliasing every pixel is either; with it the
    # light's outline has pixels in between, while flat regions keep exactly their value.
    B = np.where(box.emitters[:, None], 50.0, 0.05) * np.ones((1, 3))
    kw = dict(camera="front", width=96, height=96, exposure=0.0, flat=True)
    one = render_image(box, B, samples=1, **kw)[..., 0]
    four = render_image(box, B, samples=4, **kw)[..., 0]
    dark, white = np.sort(np.unique(one))[[1, -1]]          # ceiling grey and the light's white (0 is the frame)
    assert set(np.unique(one)) <= {0, dark, white}
    middle = (four > dark) & (four < white)
    assert middle.sum() >= 10
    # pixels whose 3 x 3 neighbourhood is all one value (no edge nearby) are unchanged
    from scipy.ndimage import maximum_filter, minimum_filter
    flat_region = maximum_filter(one, 3) == minimum_filter(one, 3)
    assert (four[flat_region] == one[flat_region]).all()
    assert not middle[flat_region].any()


def test_samples_are_checked(box):
    assert check_samples(9) == 9
    for bad in (0, 3, 65, 2.0, True):
        with pytest.raises(InputError, match="square number"):
            check_samples(bad)


def test_curved_surface_stays_continuous():
    # a 48-sided open cylinder (7.5 degrees between neighbours: one smooth surface): corners that
    # share a vertex and a smoothing set share one value, so the picture has no seams
    from hfrad.render import corner_vertices
    from hfrad.scene.scene import Material, Scene

    k, rows = 48, 4
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    V = np.array([(np.cos(a), y, np.sin(a)) for y in np.linspace(0, 1, rows + 1) for a in t])
    F = []
    for r in range(rows):
        for i in range(k):
            p, q = r * k + i, r * k + (i + 1) % k
            F += [[p, p + k, q], [q, p + k, q + k]]
    s = Scene(V, np.array(F), np.zeros(len(F), int), (Material("wall", (0.5,) * 3),))
    B = np.random.default_rng(2).random((s.n_patches, 3))
    corners = smooth_corners(s, B).reshape(-1, 3)
    _, vid = corner_vertices(s)
    vid = vid.reshape(-1)
    for v in np.unique(vid)[:200]:
        same = corners[vid == v]
        assert np.ptp(same, axis=0).max() < 1e-12
    # and a field linear along the axis comes back exactly at the inner rings
    y = s.vertices[s.faces].mean(axis=1)[:, 1]
    lin = smooth_corners(s, np.repeat((0.5 + y)[:, None], 3, axis=1))
    inner = (s.vertices[s.faces][..., 1] > 0.01) & (s.vertices[s.faces][..., 1] < 0.99)
    np.testing.assert_allclose(lin[..., 0][inner], 0.5 + s.vertices[s.faces][..., 1][inner], atol=1e-9)


def test_falsecolor_scale_ignores_pixels_that_average_a_light_in(box):
    # the bar tops at the brightest non-emitting pixel: the same scale with 1 or 4 rays a pixel
    B = box.reflectance * 10 + box.emission * 50
    kw = dict(camera="front", width=200, height=150, falsecolor=True, unit="lux")
    one, four = render_image(box, B, samples=1, **kw), render_image(box, B, samples=4, **kw)
    from hfrad.render.falsecolor import colorbar_width
    bar = np.s_[:, 200 - colorbar_width(200):]
    assert np.array_equal(one[bar], four[bar])
