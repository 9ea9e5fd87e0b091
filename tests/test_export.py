"""Tests of hfrad.io.export: coloured meshes (.glb, .ply) and tables (.npz, .csv)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from hfrad.io.export import RADIOSITY_FORMATS, export_mesh, vertex_colors, write_radiosity
from hfrad.render.shading import weld
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide


@pytest.fixture(scope="module")
def cornell():
    s = subdivide(cornell_box(), patches=600)
    rng = np.random.default_rng(1)
    B = s.reflectance * rng.uniform(5, 10, (s.n_patches, 1)) + s.emission
    return s, B


def _read_ply(path):
    """(header lines, vertex array, face array) of a binary PLY written by export_mesh."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    fprops = [h.split()[-1] for h in header[header.index(f"element face {nf}") + 2:-1]]
    fdt = np.dtype([("count", "u1"), ("vertex_indices", "<i4", (3,))] + [(p, "<f4") for p in fprops])
    v = np.frombuffer(data, vdt, nv, end)
    f = np.frombuffer(data, fdt, nf, end + nv * vdt.itemsize)
    assert end + nv * vdt.itemsize + nf * fdt.itemsize == len(data)
    return header, v, f


def test_glb_reloads_with_same_vertices_and_colours(tmp_path, cornell):
    import trimesh

    s, B = cornell
    path = export_mesh(s, B, tmp_path / "c.glb", exposure=-3.0)
    vertices, faces, rgb = vertex_colors(s, B, colors="linear", exposure=-3.0)
    loaded = trimesh.load(path, process=False)
    mesh = next(iter(loaded.geometry.values())) if hasattr(loaded, "geometry") else loaded
    assert len(mesh.vertices) == len(vertices)
    assert len(mesh.faces) == s.n_patches
    np.testing.assert_allclose(mesh.vertices, vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], rgb)


def test_mesh_is_split_at_materials_and_creases(cornell):
    s, B = cornell
    vertices, faces, rgb = vertex_colors(s, B)
    assert len(vertices) > len(np.unique(weld(s.vertices, s.faces)))
    # no vertex is shared by two materials or by patches more than 30 degrees apart
    owner_mat = np.full(len(vertices), -1)
    owner_normal = np.zeros((len(vertices), 3))
    for f in range(s.n_patches):
        for v in faces[f]:
            if owner_mat[v] < 0:
                owner_mat[v], owner_normal[v] = s.material[f], s.normals[f]
            else:
                assert owner_mat[v] == s.material[f]
                assert owner_normal[v] @ s.normals[f] > np.cos(np.radians(30)) - 1e-9
    # vertex positions are the patch corners
    np.testing.assert_allclose(vertices[faces], s.triangles)


def test_glb_colours_linear_by_default_srgb_on_request(cornell):
    s, B = cornell
    _, faces, lin = vertex_colors(s, B, colors="linear", exposure=-3.0)
    _, _, srgb = vertex_colors(s, B, colors="srgb", exposure=-3.0)
    assert (srgb.astype(int) >= lin.astype(int)).all() and (srgb > lin).any()
    # a vertex of a red-wall patch (constant-ish red): linear value = exposed radiance
    red = np.flatnonzero(s.material == s.material_index("red"))
    assert lin[faces[red[0], 0], 0] > lin[faces[red[0], 0], 1]
    with pytest.raises(ValueError, match="colors"):
        vertex_colors(s, B, colors="hdr")


def test_ply_has_face_properties(tmp_path, cornell):
    s, B = cornell
    path = write_radiosity(s, B, tmp_path / "c.ply", s.emission, exposure=-3.0)
    header, v, f = _read_ply(path)
    for prop in ("radiosity_r", "radiosity_g", "radiosity_b", "emission_r", "emission_g", "emission_b", "area"):
        assert f"property float {prop}" in header
    for name in ("red", "green", "blue"):
        assert f"property uchar {name}" in header
    assert len(f) == s.n_patches
    np.testing.assert_allclose(np.stack([f["radiosity_r"], f["radiosity_g"], f["radiosity_b"]], 1), B, rtol=1e-6)
    np.testing.assert_allclose(np.stack([f["emission_r"], f["emission_g"], f["emission_b"]], 1), s.emission)
    np.testing.assert_allclose(f["area"], s.areas, rtol=1e-6)
    _, faces, rgb = vertex_colors(s, B, colors="srgb", exposure=-3.0)
    np.testing.assert_array_equal(f["vertex_indices"], faces)
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), rgb)
    import trimesh  # and a third-party reader agrees

    mesh = trimesh.load(path, process=False)
    assert len(mesh.faces) == s.n_patches


def test_npz_and_csv(tmp_path, cornell):
    s, B = cornell
    E = s.emission * 2
    z = np.load(write_radiosity(s, B, tmp_path / "c.npz", E))
    np.testing.assert_array_equal(z["B"], B)
    np.testing.assert_array_equal(z["E"], E)
    np.testing.assert_array_equal(z["reflectance"], s.reflectance)
    np.testing.assert_array_equal(z["area"], s.areas)
    np.testing.assert_array_equal(z["centroid"], s.centroids)
    np.testing.assert_array_equal(z["normal"], s.normals)
    np.testing.assert_array_equal(z["material"], s.material)
    assert tuple(z["material_names"]) == s.material_names
    with open(write_radiosity(s, B, tmp_path / "c.csv", E), newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:3] == ["index", "material", "area"]
    assert len(rows) == s.n_patches + 1
    r = rows[7]
    assert int(r[0]) == 6 and r[1] == s.material_names[s.material[6]]
    np.testing.assert_allclose([float(x) for x in r[2:]],
                               [s.areas[6], *s.centroids[6], *B[6], *E[6]])


def test_bad_extension_and_shapes(tmp_path, cornell):
    s, B = cornell
    with pytest.raises(ValueError) as info:
        write_radiosity(s, B, tmp_path / "c.obj")
    for ext in RADIOSITY_FORMATS:
        assert ext in str(info.value)
    with pytest.raises(ValueError, match="supported"):
        export_mesh(s, B, tmp_path / "c.npz")
    with pytest.raises(ValueError, match="shape"):
        write_radiosity(s, B[:-1], tmp_path / "c.npz")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", [".npz", ".ply", ".glb", ".csv"])
def test_failed_write_leaves_no_file(tmp_path, cornell, monkeypatch, ext):
    s, B = cornell
    import hfrad.io.export as export

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(export.np, "savez_compressed", boom)
    monkeypatch.setattr(export.csv, "writer", boom)
    monkeypatch.setattr(export.Path, "write_bytes", boom)
    real_open = open

    def failing_open(file, mode="r", *args, **kwargs):  # the PLY writer's file
        fh = real_open(file, mode, *args, **kwargs)
        if "b" in mode and "w" in mode:
            fh.write(b"partial")
            fh.close()
            raise OSError("disk full")
        return fh

    monkeypatch.setattr("builtins.open", failing_open)
    target = tmp_path / f"out{ext}"
    with pytest.raises(OSError, match="disk full"):
        write_radiosity(s, B, target)
    assert list(tmp_path.iterdir()) == []
