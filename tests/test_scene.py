"""Scenes: loaders, built-ins, patches, Z-order, lighting options, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hfrad.errors import InputError, SceneError
from hfrad.scene import builtin_scene, subdivide, zorder_permutation
from hfrad.scene.load import load_scene
from hfrad.scene.zorder import morton_codes

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/scenes is absent (only in the developers' checkout)")


# -- built-in scenes --------------------------------------------------------

@pytest.mark.parametrize("name", ["cornell", "furnace"])
def test_closed_builtins_face_inward(name):
    s = builtin_scene(name)
    centre = np.array([0.0, 1.0, 0.0]) if name == "cornell" else np.full(3, 0.5)
    walls = np.isin(np.array(s.groups)[s.group], ["short_block", "tall_block"], invert=True)
    facing = ((centre - s.centroids) * s.normals).sum(axis=1)
    assert (facing[walls] > 0).all()


def test_cornell_geometry():
    s = builtin_scene("cornell")
    area = {g: s.areas[s.group == k].sum() for k, g in enumerate(s.groups)}
    # the floor loses the two 0.6 x 0.6 block footprints; the light is cut out of the ceiling
    assert area["floor"] == pytest.approx(4 - 2 * 0.36)
    assert area["ceiling"] + area["light"] == pytest.approx(4.0)
    assert area["tall_block"] == pytest.approx(4 * 0.6 * 1.2 + 0.36)
    red = s.material == s.material_names.index("red")
    assert np.allclose(s.centroids[red, 0], -1.0)  # red on the left (x = -1)
    assert s.emitters.sum() == 2 and (s.normals[s.emitters, 1] < -0.99).all()


# -- subdivision -------------------------------------------------------------

@pytest.mark.parametrize("kw", [{"max_edge": 0.1}, {"patches": 5000}])
def test_subdivision_conserves_area_per_material(kw):
    s = builtin_scene("cornell")
    t = subdivide(s, **kw)
    for k in range(len(s.materials)):
        a0 = s.areas[s.material == k].sum()
        a1 = t.areas[t.material == k].sum()
        assert abs(a1 - a0) <= 1e-9 * a0
    if "patches" in kw:
        assert 0.8 * kw["patches"] <= t.n_patches <= 1.2 * kw["patches"]
    else:
        edges = np.linalg.norm(t.triangles - np.roll(t.triangles, 1, axis=1), axis=2)
        assert edges.max() <= 0.1 + 1e-12
    assert (t.areas > 0).all()
    # shared vertices: far fewer vertices than 3 per patch
    assert len(t.vertices) < 0.7 * t.n_patches
    # emission and reflectance follow the material
    assert np.allclose(t.emission[t.emitters].max(axis=0), [17, 12, 4])
    assert np.array_equal(np.sign(t.normals[:, 1]).astype(int)[t.emitters], -np.ones(t.emitters.sum(), int))


def test_subdivision_keeps_occluders_and_parents():
    s = builtin_scene("furnace")
    t = subdivide(s, max_edge=0.25)
    assert len(t.occluder_faces) == 12
    # every patch centroid lies on its parent face's plane
    parent_n = s.normals[t.parent]
    offset = ((t.centroids - s.centroids[t.parent]) * parent_n).sum(axis=1)
    assert np.abs(offset).max() < 1e-12


# -- Z-order -------------------------------------------------------------------

def test_morton_order_keeps_neighbours_close():
    g = np.arange(16)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    perm = zorder_permutation(pts)
    assert sorted(perm.tolist()) == list(range(len(pts)))
    step = np.linalg.norm(np.diff(pts[perm], axis=0), axis=1)
    random_step = np.linalg.norm(np.diff(pts[np.random.default_rng(0).permutation(len(pts))], axis=0), axis=1)
    assert np.median(step) == 1.0  # most consecutive points are grid neighbours
    assert step.mean() < 0.25 * random_step.mean()
    # each aligned 2x2x2 cell is contiguous in the curve
    cells = (pts[perm] // 2).astype(int)
    first8 = cells[:8]
    assert (first8 == first8[0]).all()


def test_morton_ties_are_stable_and_bits_checked():
    pts = np.zeros((5, 3))
    assert zorder_permutation(pts).tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        morton_codes(pts, bits=30)


# -- shared scenes -------------------------------------------------------------

@needs_shared
def test_mcguire_cornell_relative_indices():
    # trimesh 5.2 resolves these negative indices wrongly; our reader must not
    s = load_scene(SHARED / "cornell-box" / "CornellBox-Original.obj", keep_duplicates=True)
    assert s.n_patches == 36
    assert s.total_area == pytest.approx(26.548, abs=1e-3)
    assert np.allclose(s.bounds, [[-1.02, 0.0, -1.04], [1.0, 1.99, 0.99]])
    assert s.material_names.count("light") == 1
    empty = load_scene(SHARED / "cornell-box" / "CornellBox-Empty-CO.obj")  # indented newmtl
    assert empty.total_area == pytest.approx(20.41, abs=1e-2)
    light = empty.materials[empty.material_index("light")]
    assert light.emission == (10.0, 10.0, 10.0)


@needs_shared
@pytest.mark.parametrize("path, faces, emit", [
    # duplicates merged; coplanar overlaps cut (faces cut into pieces) or dropped (covered wholly)
    ("sibenik/sibenik.obj", 73564 - 11 - 212 - 77 + 169 - 35, {"staklo_plavo": 5.0}),
    ("sponza-dabrovic/sponza.obj", 66454 - 1 - 6 - 138, {"ceiling": 1.0}),
    ("conference/conference.ply", None, None),
])
def test_shared_scenes_load(path, faces, emit):
    kw = {"unit_scale": 0.003, "area_light": (5, 5, 5)} if path.endswith(".ply") else {"emit": emit}
    s = load_scene(SHARED / path, **kw)
    if faces is not None:
        assert s.n_patches == faces
    assert s.emitters.any()
    assert any("degenerate" in w for w in s.warnings)
    assert (s.areas > 0).all()


@needs_shared
def test_info_cli_json(capsys):
    from typer.testing import CliRunner

    from hfrad.cli import app

    result = CliRunner().invoke(app, ["info", str(SHARED / "sibenik" / "sibenik.obj"), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["patches"] == 73553 - 212 - 77 + 169 - 35  # duplicates merged, overlaps cut and dropped
    assert summary["face_problems"]["overlaps"]["resolved"] == {"cut": 77, "dropped": 35, "pieces": 169}
    assert any("no emitter" in w for w in summary["warnings"])
    assert {m["name"] for m in summary["materials"]} >= {"kamen_zid", "staklo_plavo"}


# -- lighting options -----------------------------------------------------------

def test_emit_by_group_and_material():
    s = load_scene("cornell", emit={"tall_block": (1, 2, 3), "red": 4.0})
    tall = s.group == s.groups.index("tall_block")
    assert np.allclose(s.emission[tall], [1, 2, 3])
    assert np.allclose(s.emission[s.material == s.material_names.index("red")], 4.0)
    with pytest.raises(SceneError, match="no material or group named 'nope'"):
        load_scene("cornell", emit={"nope": 1.0})
    with pytest.raises(SceneError, match="R,G,B"):
        load_scene("cornell", emit={"red": (1.0, -1.0, 0.0)})


def test_area_light_faces_down():
    s = load_scene("furnace", area_light=(2, 2, 2))
    light = s.material == s.material_names.index("area_light")
    assert light.sum() == 2 and (s.normals[light, 1] < -0.99).all()
    assert len(s.occluder_faces) == 14


# -- bad input -----------------------------------------------------------------

def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_bad_files(tmp_path):
    with pytest.raises(SceneError, match="no such file"):
        load_scene(tmp_path / "missing.obj")
    with pytest.raises(SceneError, match="unknown scene format"):
        load_scene(_write(tmp_path, "a.xyz", "1 2 3"))
    with pytest.raises(SceneError, match=r"a\.obj:2: non-finite"):
        load_scene(_write(tmp_path, "a.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n"))
    with pytest.raises(SceneError, match=r"b\.obj:4: vertex index 4 out of range"):
        load_scene(_write(tmp_path, "b.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n"))
    with pytest.raises(SceneError, match="material library not found"):
        load_scene(_write(tmp_path, "c.obj", "mtllib nope.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"))
    s = load_scene(tmp_path / "c.obj", allow_missing_materials=True)
    assert any("not found" in w for w in s.warnings)


def test_bad_materials(tmp_path):
    _write(tmp_path, "m.mtl", "newmtl shiny\nKd 1.2 0.5 0.5\nnewmtl glow\nKd 0.5 0.5 0.5\nKe -1 0 0\n")
    geo = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
    with pytest.raises(SceneError, match="'shiny'.*outside \\[0, 1\\)"):
        load_scene(_write(tmp_path, "s.obj", "mtllib m.mtl\n" + geo + "usemtl shiny\nf 1 2 3\n"))
    with pytest.raises(SceneError, match="'glow'.*emission"):
        load_scene(_write(tmp_path, "g.obj", "mtllib m.mtl\n" + geo + "usemtl glow\nf 1 2 3\n"))
    with pytest.raises(SceneError, match="not defined in the .mtl: ghost"):
        load_scene(_write(tmp_path, "h.obj", "mtllib m.mtl\n" + geo + "usemtl ghost\nf 1 2 3\n"))


def test_degenerate_faces_dropped_with_count(tmp_path):
    text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\nf -4 -3 -2\n"
    s = load_scene(_write(tmp_path, "d.obj", text), keep_duplicates=True)  # face 3 repeats face 1
    assert s.n_patches == 2
    assert any("dropped 1 degenerate" in w for w in s.warnings)
    with pytest.raises(SceneError, match="every face is degenerate"):
        load_scene(_write(tmp_path, "e.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"))


def test_ply_and_gltf_materials(tmp_path):
    import trimesh  # a hard dependency: never skipped
    box = trimesh.creation.box(extents=(1, 1, 1))
    box.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(
        name="lamp", baseColorFactor=[0.5, 0.25, 0.125, 1.0], emissiveFactor=[1.0, 0.5, 0.25]))
    path = tmp_path / "box.glb"
    trimesh.Scene({"lampbox": box}).export(path)
    s = load_scene(path)
    assert s.n_patches == 12
    lamp = s.materials[s.material_index("lamp")]
    assert np.allclose(lamp.reflectance, [0.5, 0.25, 0.125], atol=0.01)
    assert np.allclose(lamp.emission, [1.0, 0.5, 0.25])
    plain = trimesh.creation.box(extents=(2, 2, 2))
    plain.visual.face_colors = np.tile([255, 128, 0, 255], (12, 1))
    plain.export(tmp_path / "box.ply")
    p = load_scene(tmp_path / "box.ply")
    assert p.total_area == pytest.approx(24.0)
    assert np.allclose(p.reflectance[0], [0.99, 128 / 255, 0.0])  # white-ish colour clamped below 1
    assert any("clamped" in w for w in p.warnings)


def test_hilbert_order_steps_to_face_neighbours():
    from hfrad.scene.zorder import patch_order

    g = np.arange(8)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3).astype(float)
    perm = patch_order(pts, "hilbert")
    assert sorted(perm.tolist()) == list(range(len(pts)))
    assert np.allclose(np.linalg.norm(np.diff(pts[perm], axis=0), axis=1), 1.0)
    with pytest.raises(ValueError, match="order must be one of"):
        patch_order(pts, "spiral")


@pytest.mark.parametrize("cut", ["subdivide", "load_scene"])
@pytest.mark.parametrize("kwargs, match", [
    ({"patches": 100, "max_edge": 0.1}, r"give either max_edge or patches, not both"),
    ({"patches": 0}, r"patches must be a whole number >= 1, got 0"),
    ({"patches": 99.5}, r"patches must be a whole number >= 1, got 99.5"),
    ({"max_edge": float("nan")}, r"max_edge must be a positive finite length in metres, got nan"),
    ({"max_edge": 0.0}, r"max_edge must be a positive finite length in metres, got 0.0"),
])
def test_a_bad_cut_request_is_one_input_error_everywhere(cut, kwargs, match):
    """subdivide, load_scene and cluster share one check of patches / max_edge."""
    with pytest.raises(InputError, match=match):
        if cut == "subdivide":
            subdivide(builtin_scene("cornell"), **kwargs)
        else:
            load_scene("cornell", **kwargs)


def test_remeshed_triangles_take_their_owners_properties():
    box = builtin_scene("cornell")
    owner = np.array([3, 3, 0, box.n_patches - 1])
    tri = box.triangles[owner]
    s = box.remeshed(tri.reshape(-1, 3), np.arange(12).reshape(4, 3), owner, notes=("cut four",))
    assert s.n_patches == 4 and not s.is_clustered
    np.testing.assert_array_equal(s.material, box.material[owner])
    np.testing.assert_array_equal(s.emission, box.emission[owner])
    np.testing.assert_array_equal(s.parent, box.parent[owner])
    np.testing.assert_allclose(s.areas, box.areas[owner], rtol=1e-15)
    assert s.warnings == box.warnings + ("cut four",) and s.name == box.name
    from hfrad.scene.cluster import cluster
    clustered = cluster(subdivide(box, patches=300), patches=60)
    with pytest.raises(SceneError, match="cannot remesh a clustered scene"):
        clustered.remeshed(tri.reshape(-1, 3), np.arange(12).reshape(4, 3), owner)
