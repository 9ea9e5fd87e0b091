"""Dirty inputs (issue 26, items 1 and 2): scene readers and numbers a user may hand hfrad.

Each test is a case that went wrong before: a traceback, a silent wrong
answer, or a misleading message. The full list of cases tried is in the
issue's note; these are the ones that needed a fix.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import hfrad
from conftest import run_cli
from hfrad.errors import FileFormatError, InputError, SceneError
from hfrad.scene.load import load_scene
from hfrad.scene.scene import Scene

# a 2 x 1 x 0 strip: two unit quads and a triangle, each with its own reflectance; the triangle emits
_V = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0), (2, 1, 0), (1.5, 2, 0)], float)
_POLYGONS = [(0, 1, 2, 3), (1, 4, 5, 2), (2, 5, 6)]
_RHO = [(0.125, 0.25, 0.375), (0.5, 0.625, 0.75), (0.25, 0.5, 0.125)]  # exact in float32
_EM = [(0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (17.0, 12.0, 4.0)]


def _ply(fmt: str, vertices=_V, polygons=_POLYGONS, rho=_RHO, em=_EM, declared_faces=None) -> bytes:
    """A PLY file (our own writer): double x y z, list uchar uint indices, float reflectance/emission."""
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(vertices)}\n"
            "property double x\nproperty double y\nproperty double z\n"
            f"element face {len(polygons) if declared_faces is None else declared_faces}\n"
            "property list uchar uint vertex_indices\n"
            + "".join(f"property float {p}_{c}\n" for p in ("reflectance", "emission") for c in "rgb")
            + "end_header\n").encode()
    if fmt == "ascii":
        body = "".join(f"{float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in vertices)
        body += "".join(f"{len(f)} {' '.join(map(str, f))} {' '.join(repr(float(x)) for x in (*r, *e))}\n"
                        for f, r, e in zip(polygons, rho, em))
        return head + body.encode()
    o = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(f"{o}3d", *v) for v in vertices)
    body += b"".join(struct.pack(f"{o}B", len(f)) + struct.pack(f"{o}{len(f)}I", *f) + struct.pack(f"{o}6f", *r, *e)
                     for f, r, e in zip(polygons, rho, em))
    return head + body


def _write(path, data) -> str:
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return str(path)


# -- PLY --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("polygons", ["triangles", "triangles and quads"])
def test_ascii_ply_loads_like_binary(tmp_path, polygons):
    """Every ASCII PLY failed ('dict' object has no attribute 'dtype'), and a binary PLY mixing
    triangles and quads failed ('PLY is unexpected length!'); all encodings give one scene."""
    k = 2 if polygons == "triangles" else 0
    kw = {"polygons": _POLYGONS[k:], "rho": _RHO[k:], "em": _EM[k:]}
    a = load_scene(_write(tmp_path / "a.ply", _ply("ascii", **kw)))
    for fmt in ("binary_little_endian", "binary_big_endian"):
        b = load_scene(_write(tmp_path / "b.ply", _ply(fmt, **kw)))
        assert a.n_patches == b.n_patches
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.reflectance, b.reflectance)
        np.testing.assert_array_equal(a.emission, b.emission)
    assert a.reflectance[-1].tolist() == list(_RHO[2]) and a.emission[-1].tolist() == list(_EM[2])


def test_ascii_ply_polygons_keep_their_properties(tmp_path):
    """Quads are fan-triangulated here, each triangle with its polygon's reflectance and emission."""
    s = load_scene(_write(tmp_path / "p.ply", _ply("ascii")))
    assert s.total_area == pytest.approx(2.5, rel=1e-12)  # two unit quads and a triangle of area 1/2
    by_colour = {tuple(r): 0.0 for r in _RHO}
    for r, a in zip(s.reflectance, s.areas):
        by_colour[tuple(r)] += a
    assert by_colour == pytest.approx({_RHO[0]: 1.0, _RHO[1]: 1.0, _RHO[2]: 0.5}, rel=1e-12)
    assert s.emission[s.emitters].max(axis=0).tolist() == list(_EM[2])


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_bad_ply_files_are_one_line(tmp_path, fmt):
    tri = [(0, 1, 2), (0, 2, 3), (2, 5, 6)]
    with pytest.raises(SceneError, match=r"face 2 uses vertex 500, but the file has 7 vertices"):
        load_scene(_write(tmp_path / "oob.ply", _ply(fmt, polygons=[(0, 1, 2), (0, 2, 3), (2, 500, 6)])))
    v = _V.copy()
    v[3, 0] = np.nan
    with pytest.raises(SceneError, match=r"nan\.ply: vertex 3 has a non-finite coordinate"):
        load_scene(_write(tmp_path / "nan.ply", _ply(fmt, vertices=v, polygons=tri)))
    with pytest.raises(SceneError, match=r"face 1 has a non-finite reflectance"):
        load_scene(_write(tmp_path / "rho.ply", _ply(fmt, polygons=tri, rho=[_RHO[0], (np.nan, 0, 0), _RHO[2]])))
    with pytest.raises(SceneError, match=r"face 2 has a non-finite emission.*3.4e38"):
        big = 1e39 if fmt == "ascii" else np.inf  # a float property holds at most 3.4e38: 1e39 reads as inf
        load_scene(_write(tmp_path / "em.ply", _ply(fmt, polygons=tri, em=[_EM[0], _EM[1], (big, 0, 0)])))


def test_truncated_ply_is_refused(tmp_path):
    """An ASCII file cut short used to load the faces it had, silently."""
    with pytest.raises(SceneError, match=r"t\.ply: truncated or malformed PLY: the header declares 9 'face'"):
        load_scene(_write(tmp_path / "t.ply", _ply("ascii", declared_faces=9)))
    data = _ply("binary_little_endian")
    with pytest.raises(SceneError, match=r"b\.ply: truncated PLY: element 'face' ends after 2 of 3 rows"):
        load_scene(_write(tmp_path / "b.ply", data[:-10]))
    with pytest.raises(SceneError, match=r"h\.ply: truncated PLY: element 'face' declares 100,000,000,000 rows"):
        load_scene(_write(tmp_path / "h.ply", _ply("binary_little_endian", declared_faces=10**11)))


# -- OBJ / MTL --------------------------------------------------------------------------------------

_GEO = "v 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl glow\nf 1 2 3\n"
_MTL = "newmtl glow\nKd 0.5 0.25 0.125\nKe 3 2 1\n"


def test_mtllib_names_with_spaces_and_accents(tmp_path):
    (tmp_path / "my materials.mtl").write_text(_MTL, encoding="utf-8")
    s = load_scene(_write(tmp_path / "a.obj", "mtllib my materials.mtl\n" + _GEO))
    assert s.emission[0].tolist() == [3.0, 2.0, 1.0]
    (tmp_path / "matériaux.mtl").write_text(_MTL.replace("3 2 1", "5 5 5"), encoding="utf-8")
    for encoding in ("utf-8", "latin-1"):  # exporters on Windows write Latin-1
        path = tmp_path / f"{encoding}.obj"
        path.write_bytes(("mtllib matériaux.mtl\n" + _GEO).encode(encoding))
        assert load_scene(path).emission[0].tolist() == [5.0, 5.0, 5.0]


def test_material_libraries_stay_in_the_scene_folder(tmp_path):
    """``mtllib ../x.mtl`` used to be read from anywhere (``/etc/passwd`` too)."""
    (tmp_path / "outside.mtl").write_text(_MTL, encoding="utf-8")
    scene_dir = tmp_path / "scene"
    (scene_dir / "sub").mkdir(parents=True)
    (scene_dir / "sub" / "inside.mtl").write_text(_MTL, encoding="utf-8")
    assert load_scene(_write(scene_dir / "ok.obj", "mtllib sub/inside.mtl\n" + _GEO)).emission.max() == 3.0
    for lib in ("../outside.mtl", str(tmp_path / "outside.mtl"), "sub/../../outside.mtl"):
        with pytest.raises(SceneError, match="lies outside the scene's folder"):
            load_scene(_write(scene_dir / "bad.obj", f"mtllib {lib}\n" + _GEO), allow_missing_materials=True)


def test_obj_oddities(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl glow\nKd 0.5 0.25\n", encoding="utf-8")
    with pytest.raises(SceneError, match=r"m\.mtl:2: Kd needs one number \(grey\) or three"):
        load_scene(_write(tmp_path / "two.obj", "mtllib m.mtl\n" + _GEO))  # was read as (0.5, 0.25, 0.5)
    (tmp_path / "d.obj").mkdir()
    with pytest.raises(SceneError, match=r"d\.obj: is a directory"):
        load_scene(tmp_path / "d.obj")
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(SceneError, match=r"d\.ply: is a directory"):
        load_scene(tmp_path / "d.ply")
    with pytest.raises(SceneError, match="UTF-16"):
        load_scene(_write(tmp_path / "u.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".encode("utf-16")))


def test_error_lines_quote_at_most_about_200_characters(tmp_path):
    long = "1" * 100_000
    cases = [("v.obj", f"v 0 0 0\nv {long}x 0 0\n"), ("f.obj", f"v 0 0 0\nv 1 0 0\nv 0 1 0\nf {long} 1 2\n"),
             ("g.obj", f"v 0 0 0\ng {'x' * 5000}\n")]
    for name, text in cases:
        with pytest.raises(SceneError) as info:
            load_scene(_write(tmp_path / name, text))
        message = str(info.value).replace(str(tmp_path), "")
        assert len(message) < 300 and "characters" in message, message  # was the whole 100,000
    doc = {"format": "hfrad-emission", "version": 1, "emitters": [{"name": "light", "exitance": ["y" * 10**5, 1, 1]}]}
    from hfrad.io.emission import loads_emission
    with pytest.raises(FileFormatError) as info:
        loads_emission(json.dumps(doc))
    assert len(str(info.value)) < 400


# -- glTF -------------------------------------------------------------------------------------------

def _gltf(material: dict) -> str:
    import base64
    data = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0)], np.float32).tobytes() + np.arange(3, dtype=np.uint32).tobytes()
    return json.dumps({
        "asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "scene": 0, "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [{"name": "m", **material}],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5125, "count": 3, "type": "SCALAR"}]})


def test_gltf_factors_are_read_exactly_and_checked(tmp_path):
    ok = _gltf({"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 0.125, 1]}, "emissiveFactor": [1, 1, 1],
                "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4}}})
    s = load_scene(_write(tmp_path / "ok.gltf", ok))
    assert s.reflectance[0].tolist() == [0.5, 0.25, 0.125]  # was 128/255, 64/255, 32/255
    assert s.emission[0].tolist() == [4.0, 4.0, 4.0]
    with pytest.raises(SceneError, match="material 'm': baseColorFactor: expected 4 finite numbers"):
        load_scene(_write(tmp_path / "nan.gltf", ok.replace("[0.5, 0.25, 0.125, 1]", "[NaN, 0.25, 0.125, 1]")))
    with pytest.raises(SceneError, match="emissiveStrength must be a finite number"):
        load_scene(_write(tmp_path / "str.gltf", ok.replace('"emissiveStrength": 4', '"emissiveStrength": "lots"')))


# -- numbers ----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_fac():
    from conftest import closed_system
    F, areas, rho = closed_system(12)
    return hfrad.factorize_matrix(F, rho * 0.9, areas=areas), F, rho * 0.9


def test_exitance_beyond_float32_is_refused_before_any_work(tmp_path, small_fac):
    """Ke 1e39 gave NaN radiosity with exit 0 (or an all-black picture)."""
    fac, F, rho = small_fac
    E = np.zeros((12, 3))
    E[0] = 1e39
    with pytest.raises(InputError, match="above the largest exitance"):
        fac.solve(E)
    with pytest.raises(InputError, match="above the largest exitance"):
        fac.solve(E[:, 0] * 1e261, trans="T")
    (tmp_path / "m.mtl").write_text("newmtl glow\nKd 0.5 0.5 0.5\nKe 1e39 1e39 1e39\n", encoding="utf-8")
    with pytest.raises(SceneError, match="material 'glow'.*above the largest exitance"):
        load_scene(_write(tmp_path / "k.obj", "mtllib m.mtl\n" + _GEO))
    with pytest.raises(SceneError, match="above the largest exitance"):
        load_scene("cornell", emit={"light": (1e39, 1, 1)})
    from hfrad.io.emission import loads_emission
    doc = {"format": "hfrad-emission", "version": 1, "emitters": [{"name": "light", "exitance": [1e300, 1, 1]}]}
    with pytest.raises(FileFormatError, match="above the largest exitance"):
        loads_emission(json.dumps(doc))
    doc["emitters"][0]["exitance"] = [10**400, 1, 1]  # a JSON integer no float holds: was OverflowError
    with pytest.raises(FileFormatError, match="expected three finite numbers"):
        loads_emission(json.dumps(doc))


@pytest.mark.parametrize("bad", ["complex", "bool", "str", "object", "ragged"])
def test_arrays_that_are_not_real_numbers_are_refused(small_fac, bad):
    """``solve(E + 1j)`` silently dropped the imaginary part; strings were parsed, booleans read as 0/1."""
    fac, F, rho = small_fac
    E = np.ones((12, 3))
    make = {"complex": lambda a: a + 1j, "bool": lambda a: a > 0.5, "str": lambda a: a.astype(str),
            "object": lambda a: a.astype(object), "ragged": lambda a: [list(r) for r in a[:-1]] + [[1.0]]}[bad]
    for call in (lambda: fac.solve(make(E)), lambda: fac.solve(make(E), trans="T"),
                 lambda: fac.with_reflectance(make(rho)), lambda: hfrad.factorize_matrix(make(F), rho),
                 lambda: hfrad.factorize_matrix(F, make(rho)), lambda: fac.residual(E, make(E), form_factors=F)):
        with pytest.raises(InputError, match="real numbers"):
            call()


def test_factorize_refuses_negative_or_energy_creating_form_factors(small_fac):
    fac, F, rho = small_fac
    G = F.copy()
    G[1, 2] = -0.1
    with pytest.raises(InputError, match=r"form factors must be >= 0.*F\[1, 2\] = -0.1"):
        hfrad.factorize_matrix(G, rho)
    # rows summing to 2: the solve returned radiosity -1.25 for an exitance of 1, silently
    with pytest.raises(InputError, match=r"form factors: row 0 sums to 2; a patch cannot send out more"):
        hfrad.factorize_matrix(np.full((4, 4), 0.5), np.full((4, 3), 0.9))


def test_render_refuses_complex_or_nan_radiosity():
    s = load_scene("cornell")
    B = np.ones((s.n_patches, 3))
    with pytest.raises(InputError, match="radiosity must be real numbers"):
        hfrad.render_image(s, B + 1j, width=8, height=8)
    with pytest.raises(InputError, match="radiosity has a NaN"):
        hfrad.render_image(s, B * np.nan, width=8, height=8)


# -- scale and position -----------------------------------------------------------------------------

@pytest.mark.parametrize("size", [1e13, 1e-20, 1e-30])
def test_ray_caster_hits_at_any_scale(size):
    """Embree missed every hit from a size of 1e13 and below 1e-20 (float32 limits of its own)."""
    from hfrad.formfactors.raycast import RayCaster
    caster = RayCaster(np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]]) * size + 3 * size, np.array([[0, 1, 2]]),
                       threads=1)
    o = np.array([[0, 0, -1.0], [0, 0, -1.0], [2, 2, -1.0]]) * size + 3 * size
    d = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]])
    assert caster.occluded(o, d, np.array([2.0, 0.5, 2.0]) * size).tolist() == [True, False, False]
    face, dist, _ = caster.intersect(o, d)
    assert face.tolist() == [0, 0, -1]
    assert dist[:2] == pytest.approx([size, size], rel=1e-6)


def test_form_factors_do_not_depend_on_unit_or_position():
    """At 1e13 m the form factors lost the shadows of the Cornell blocks (15% Frobenius error)."""
    base = load_scene("cornell", patches=60)
    F0 = hfrad.form_factor_matrix(base)
    for scale, offset in ((1e13, 0.0), (1e13, 1e13), (1e-25, 0.0), (1.0, 1e4)):
        s = base.replace(vertices=base.vertices * scale + offset, occluder_vertices=base.occluder_vertices * scale + offset)
        F = hfrad.form_factor_matrix(s)
        # float32 ray end points round differently in each frame: 3e-5 observed
        assert np.abs(F - F0).max() < 2e-4, (scale, offset)


def test_scenes_out_of_range_are_refused_with_the_reason():
    """A scene 1e-160 m across was reported as 'every face is degenerate'; one 1e13 m from the
    origin loaded as 12 patches of zero size (its points merged), silently."""
    with pytest.raises(SceneError, match=r"the scene is 2e-160 m across; hfrad computes with scenes between"):
        load_scene("cornell", unit_scale=1e-160)
    with pytest.raises(SceneError, match=r"the scene is 2e\+200 m across"):
        load_scene("cornell", unit_scale=1e200)
    s = load_scene("cornell")
    with pytest.raises(SceneError, match=r"2 m across but lies 1e\+13 m from the origin.*Move it near the origin"):
        s.replace(vertices=s.vertices + 1e13, occluder_vertices=s.occluder_vertices + 1e13)
    assert load_scene("cornell", unit_scale=1e-13).total_area == pytest.approx(s.total_area * 1e-26, rel=1e-9)
    # a stray vertex no face uses does not count
    stray = s.replace(vertices=np.vstack([s.vertices, [[1e40, 0, 0]]]))
    assert stray.n_patches == s.n_patches


# -- command line -----------------------------------------------------------------------------------

def test_cli_reads_ascii_ply_and_refuses_escapes_in_one_line(tmp_path):
    ply = _write(tmp_path / "a.ply", _ply("ascii"))
    r = run_cli("info", ply)
    assert r.exit_code == 0, r.output
    (tmp_path / "s").mkdir()
    obj = _write(tmp_path / "s" / "e.obj", "mtllib ../../../../../../etc/passwd\n" + _GEO)
    r = run_cli("info", obj)
    assert r.exit_code == 2 and "outside the scene's folder" in r.output and "Traceback" not in r.output
    tri = [(0, 1, 2), (0, 2, 3), (2, 5, 6)]
    nan = _write(tmp_path / "nan.ply", _ply("binary_little_endian", polygons=tri, rho=[_RHO[0], (np.nan, 0.5, 0.5), _RHO[2]]))
    r = run_cli("info", nan)  # was loaded with the default reflectance for that face, exit 0
    # values in parentheses: the command line's rich console takes "[nan, ...]" for a markup tag and drops it
    assert r.exit_code == 2 and "face 1 has a non-finite reflectance_r/reflectance_g/reflectance_b: (nan, 0.5, 0.5)" \
        in " ".join(r.output.split()), r.output


def test_patches_far_from_the_origin_keep_their_areas():
    """Points were merged within 1e-9 of the largest coordinate: a 2 m box 1e6 m from the origin lost
    whole patches to zero area (and factorize then asked to remove degenerate patches)."""
    from hfrad.scene.patches import subdivide

    base = load_scene("cornell")
    near = subdivide(base, patches=300)
    moved = base.replace(vertices=base.vertices + 1e6, occluder_vertices=base.occluder_vertices + 1e6)
    far = subdivide(moved, patches=300)
    assert far.n_patches == near.n_patches
    assert len(far.vertices) == len(near.vertices)   # shared corners still shared
    # the mesher may flip a diagonal on rounding (2 of 300 patch pairs here), never lose area:
    # float64 at 1e6 m keeps ~1e-10 m, 4e-10 relative observed
    assert far.areas.sum() == pytest.approx(near.areas.sum(), rel=1e-8)
    assert far.areas.min() > 0.5 * near.areas.min()


def test_pictures_do_not_depend_on_unit_or_position():
    """A Cornell box 1e-20 m across rendered black (the camera framed at least 1e-9 m), and one 1e6 m
    from the origin too (the step past back faces was 1e-5 of the coordinates: 10 m); 5e3 m off
    the origin changed 27 of 2,304 pixels."""
    from hfrad.render.image import render_image

    base = load_scene("cornell", patches=200)
    fac = hfrad.factorize(base, eps=0.05)
    B = fac.solve(base.emission)
    reference = render_image(base, B, camera="front", width=48, height=48)
    assert reference.mean() > 50
    for scale, offset in ((1e-20, 0.0), (1.0, 5e3), (1.0, 1e6), (1e13, 1e13)):
        s = base.replace(vertices=base.vertices * scale + offset,
                         occluder_vertices=base.occluder_vertices * scale + offset)
        picture = render_image(s, B, camera="front", width=48, height=48)
        # identical pictures observed at every scale and offset; allow one 8-bit step of rounding
        assert np.abs(picture.astype(int) - reference).max() <= 1, (scale, offset)
