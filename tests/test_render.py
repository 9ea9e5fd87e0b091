"""Tests of hfrad.render: camera, primary rays, smooth shading, tone mapping, false colour."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import InputError
from hfrad.render import Camera, render_image, render_radiance, save_png, smooth_corners
from hfrad.render.falsecolor import colorbar_width, nice_scale, photometric
from hfrad.render.raycast import patch_caster
from hfrad.render.tonemap import auto_exposure, srgb_decode, srgb_encode, tonemap
from hfrad.scene.builtin import cornell_box, furnace
from hfrad.scene.patches import subdivide


@pytest.fixture(scope="module")
def furnace_scene():
    return subdivide(furnace(reflectance=0.5, emission=1.0), patches=800)


@pytest.fixture(scope="module")
def cornell():
    s = subdivide(cornell_box(), patches=3000)
    return s, s.reflectance * 10 + s.emission


# -- furnace: exact uniform radiosity -------------------------------------------------
@pytest.mark.parametrize("camera", ["0.5,0.5,0.5:0.5,0.5,0:100",   # one wall and its four neighbours
                                    "0.3,0.6,0.7:1,0,0:120"])      # into a corner
def test_furnace_picture_is_uniform(furnace_scene, camera):
    s = furnace_scene
    B = s.emission / (1 - s.reflectance)  # exact: 2 W/m^2 everywhere
    radiance, face = render_radiance(s, B, camera, width=160, height=120)
    assert (face >= 0).all(), "every pixel inside a closed cube must see a wall"
    assert np.isfinite(radiance).all()
    np.testing.assert_allclose(radiance * np.pi, 2.0, rtol=0.01)
    img = render_image(s, B, camera=camera, width=160, height=120)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    assert int(img.max()) - int(img.min()) <= 1  # no seams or speckles


def test_auto_exposure_maps_percentile_to_target(furnace_scene):
    s = furnace_scene
    B = s.emission / (1 - s.reflectance)
    # every patch emits, so "ignore emitters" must fall back to all pixels
    img = render_image(s, B, camera="0.5,0.5,0.5:0.5,0.5,0:90", width=32, height=32)
    assert np.all(img == np.rint(srgb_encode(0.8) * 255))


# -- Cornell box from the front --------------------------------------------------------
def test_cornell_front_colours(cornell):
    s, B = cornell
    img = render_image(s, B, camera="front", width=128, height=128).astype(float)
    half = img.shape[1] // 2
    left, right = img[:, :half], img[:, half:]
    assert (left[..., 0] - left[..., 1]).mean() > (right[..., 0] - right[..., 1]).mean() + 20
    assert (right[..., 1] - right[..., 0]).mean() > (left[..., 1] - left[..., 0]).mean() + 20


def test_cornell_camera_sees_through_front_wall(cornell):
    s, B = cornell
    radiance, face = render_radiance(s, B, "front", width=96, height=96)
    assert np.isfinite(radiance).all()
    group = np.asarray(s.groups)[s.group[face[face >= 0]]]
    assert "front" not in set(group)
    assert (group == "back").sum() > 0.1 * face.size
    cy = 48
    assert np.asarray(s.groups)[s.group[face[cy, 48]]] in ("back", "tall_block", "short_block")


def test_cornell_no_cracks(cornell):
    s, B = cornell
    caster = patch_caster(s)
    for size in (256, 301):
        _, face = render_radiance(s, B, "front", width=size, height=size, caster=caster)
        covered = face >= 0
        rows = np.flatnonzero(covered.any(1))
        cols = np.flatnonzero(covered.any(0))
        inside = covered[rows[0] + 1:rows[-1], cols[0] + 1:cols[-1]]
        assert inside.all(), f"{(~inside).sum()} background pixels inside the box at {size} px"


def test_smoothing_does_not_bleed_across_materials_or_creases(cornell):
    s, B = cornell
    # radiosity constant per material: every corner must keep its patch's value exactly
    corners = smooth_corners(s, B)
    np.testing.assert_allclose(corners, np.repeat(B[:, None, :], 3, axis=1), rtol=1e-12)


def test_smoothing_averages_within_a_surface():
    s = subdivide(furnace(), patches=200)
    rng = np.random.default_rng(0)
    B = rng.random((s.n_patches, 3))
    corners = smooth_corners(s, B)
    # corners at one vertex on one wall agree (continuous interpolation)
    wall = np.flatnonzero(np.abs(s.normals[:, 2] - 1) < 1e-9)
    key = {}
    for f in wall:
        for k in range(3):
            v = tuple(np.round(s.vertices[s.faces[f, k]], 9))
            key.setdefault(v, []).append(corners[f, k])
    spread = max(np.ptp(np.array(vals), axis=0).max() for vals in key.values())
    assert spread < 1e-12
    lo, hi = B.min(axis=0), B.max(axis=0)
    assert (corners >= lo - 1e-12).all() and (corners <= hi + 1e-12).all()


def test_flat_shading_is_patch_value(cornell):
    s, B = cornell
    radiance, face = render_radiance(s, B, "front", width=48, height=48, flat=True)
    hit = face >= 0
    np.testing.assert_allclose(radiance[hit] * np.pi, B[face[hit]])
    assert (radiance[~hit] == 0).all()


def test_falsecolor_has_colour_bar(cornell):
    s, B = cornell
    w, h = 320, 240
    img = render_image(s, B, camera="front", width=w, height=h, falsecolor=True, unit="lux")
    assert img.shape == (h, w, 3)
    bar = img[:, w - colorbar_width(w):]
    # a vertical ramp: many distinct colours down one column of the strip
    column = bar[:, bar.shape[1] // 10 + 4]
    assert len(np.unique(column, axis=0)) > 50
    top = column[h // 6].astype(int)
    bottom = column[h - h // 8].astype(int)
    assert top[1] > bottom[1] + 100  # viridis: yellow-green at the top, purple at the bottom
    with pytest.raises(InputError, match="unit must be one of"):
        render_image(s, B, falsecolor=True, unit="nits", width=16, height=16)


@pytest.mark.parametrize("vmax", [15_000.0, 2.5e6])
def test_colour_bar_labels_fit_the_narrowest_bar(vmax):
    """Large scales ("15k", "2.5M") stay inside the bar's panel: its last column is panel grey."""
    from hfrad.render.falsecolor import falsecolor_image

    h, width = 360, 360
    w = width - colorbar_width(width)
    values = np.linspace(0.0, vmax, h * w).reshape(h, w)
    img = falsecolor_image(values, np.ones((h, w), bool), width=width, unit="lux", vmax=vmax)
    assert (img[:, -2:] == 32).all()


def test_photometric_units():
    B = np.array([[1.0, 1.0, 1.0], [0.0, 1.0, 0.0]])
    np.testing.assert_allclose(photometric(B, "W/m2"), [1.0, 0.7152])
    np.testing.assert_allclose(photometric(B, "lux"), [683.0, 683.0 * 0.7152])
    assert nice_scale(7.3) == (8.0, 2.0)


# -- tone mapping ---------------------------------------------------------------------
def test_srgb_roundtrip_and_nan_safety():
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)
    assert srgb_encode(0.0031308) == pytest.approx(0.04045, abs=1e-5)
    out = tonemap(np.array([[np.nan, -1.0, np.inf], [0.5, 2.0, 0.0]]), exposure=0.0)
    assert out.dtype == np.uint8
    assert out.tolist() == [[0, 0, 255], [188, 255, 0]]
    assert auto_exposure(np.full((5, 3), np.nan)) == 0.0


def test_exposure_override(cornell):
    s, B = cornell
    dark = render_image(s, B, camera="front", width=32, height=32, exposure=-6)
    bright = render_image(s, B, camera="front", width=32, height=32, exposure=4)
    assert dark.mean() < bright.mean()


# -- camera and arguments ---------------------------------------------------------------
def test_camera_views():
    s = cornell_box()
    front = Camera.parse("front", s.bounds)
    np.testing.assert_allclose(front.position, (0, 1, 3.9), atol=0.1)
    np.testing.assert_allclose(front.target, (0, 1, 0))
    cam = Camera.parse("1,2,3:0,1,0:50", s.bounds)
    assert cam.position == (1.0, 2.0, 3.0) and cam.fov == 50.0
    auto = Camera.parse("auto", s.bounds)
    assert np.linalg.norm(np.subtract(auto.position, auto.target)) > 3
    for bad in ("side", "1,2:0,0,0", "a,b,c:0,0,0", "1,2,3", "1,2,3:0,0,0:40:1", "1,2,3:0,0,0:wide", ""):
        with pytest.raises(InputError, match="camera must be"):
            Camera.parse(bad, s.bounds)
    with pytest.raises(InputError, match="parallel"):
        Camera((0, 0, 0), (0, 1, 0))


def test_bad_radiosity_shape():
    s = cornell_box()
    with pytest.raises(InputError, match=r"shape \(\d+, 3\)"):
        render_image(s, np.ones((3, 3)), width=8, height=8)


def test_save_png_roundtrip(tmp_path, cornell):
    from PIL import Image

    s, B = cornell
    img = render_image(s, B, camera="front", width=40, height=30)
    path = save_png(img, tmp_path / "c.png")
    np.testing.assert_array_equal(np.asarray(Image.open(path)), img)
    assert [p.name for p in tmp_path.iterdir()] == ["c.png"]
