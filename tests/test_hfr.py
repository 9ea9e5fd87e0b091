"""The .hfr file: round trip, damaged files, newer versions, atomic writes."""

from pathlib import Path

import h5py
import numpy as np
import pytest

import hfrad.solve.hfr as hfr
from hfrad.errors import FileFormatError
from hfrad import factorize_matrix
from hfrad.solve.hfr import FORMAT_VERSION, load_hfr, read_hfr_metadata, save_hfr
from hfrad.scene.scene import Material, Scene


def small_scene_and_factorization(n_side=6):
    """A grid of 2 n_side^2 triangles facing a second, parallel grid (point form factors)."""
    g = np.linspace(0, 1, n_side + 1)
    X, Y = np.meshgrid(g, g, indexing="ij")
    verts, faces = [], []
    for z, flip in ((0.0, False), (1.0, True)):
        base = len(verts) and sum(len(v) for v in verts)
        v = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])
        idx = np.arange(X.size).reshape(X.shape) + base
        for i in range(n_side):
            for j in range(n_side):
                a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
                tris = [(a, b, c), (a, c, d)]
                faces += [(t[0], t[2], t[1]) if flip else t for t in tris]
        verts.append(v)
    mats = (Material("floor", (0.5, 0.6, 0.7)), Material("lamp", (0.2, 0.2, 0.2), (10.0, 9.0, 8.0)))
    n = len(faces)
    scene = Scene(np.vstack(verts), np.array(faces), material=(np.arange(n) >= n // 2).astype(int),
                  materials=mats, group=(np.arange(n) >= n // 2).astype(int), groups=("floor", "ceiling"),
                  name="plates")
    P, N, A = scene.centroids, scene.normals, scene.areas
    d = P[None] - P[:, None]
    r2 = np.sum(d * d, axis=-1)
    np.fill_diagonal(r2, 1.0)
    F = (np.clip(np.einsum("ik,ijk->ij", N, d), 0, None) * np.clip(-np.einsum("jk,ijk->ij", N, d), 0, None)
         / (np.pi * r2 ** 2) * A[None])
    np.fill_diagonal(F, 0.0)
    fac = factorize_matrix(F, scene.reflectance, eps=0.01, block_size=16, order=np.arange(n)[::-1])
    fac.scene = scene
    return scene, fac


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    scene, fac = small_scene_and_factorization()
    path = tmp_path_factory.mktemp("hfr") / "plates.hfr"
    save_hfr(fac, path, timings={"factor": 1.5})
    return path, scene, fac


def test_round_trip(saved):
    path, scene, fac = saved
    back = load_hfr(path)
    for name in ("perm", "Q", "V", "rho_max", "reflectance"):
        np.testing.assert_array_equal(getattr(back, name), getattr(fac, name))
    np.testing.assert_array_equal(back.capacitance_inv, fac.capacitance_inv)
    assert back.Q.dtype == np.float32
    assert back.rank == fac.rank and back.eps == fac.eps
    assert back.achieved_error == fac.achieved_error and back.relative_error == fac.relative_error
    np.testing.assert_array_equal(back.sigma_max(), fac.sigma_max())
    np.testing.assert_array_equal(back.error_bound(), fac.error_bound())
    assert back.params["block_size"] == 16 and back.timings == {"factor": 1.5}
    E = scene.emission
    np.testing.assert_array_equal(back.solve(E), fac.solve(E))
    s = back.scene
    np.testing.assert_array_equal(s.vertices, scene.vertices)
    np.testing.assert_array_equal(s.faces, scene.faces)
    np.testing.assert_array_equal(s.group, scene.group)
    np.testing.assert_array_equal(s.emission, scene.emission)
    assert s.material_names == ("floor", "lamp") and s.groups == ("floor", "ceiling")
    meta = read_hfr_metadata(path)
    assert meta["format_version"] == FORMAT_VERSION == 5 and meta["rank"] == fac.rank and meta["has_patches"]
    with h5py.File(path) as f:
        np.testing.assert_array_equal(f["patches/areas"][()], scene.areas)


def test_truncated(saved, tmp_path):
    path, *_ = saved
    data = path.read_bytes()
    for cut in (len(data) // 2, 100):
        bad = tmp_path / f"cut{cut}.hfr"
        bad.write_bytes(data[:cut])
        with pytest.raises(FileFormatError, match=f"cut{cut}.hfr"):
            load_hfr(bad)


def test_not_hfr(tmp_path):
    p = tmp_path / "other.h5"
    with h5py.File(p, "w") as f:
        f["x"] = 1
    with pytest.raises(FileFormatError, match="not an hfrad"):
        load_hfr(p)


def test_newer_version(saved, tmp_path):
    path, *_ = saved
    newer = tmp_path / "newer.hfr"
    newer.write_bytes(path.read_bytes())
    with h5py.File(newer, "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(FileFormatError, match="upgrade"):
        load_hfr(newer)
    with pytest.raises(FileFormatError, match="upgrade"):
        read_hfr_metadata(newer)


def test_no_partial_file(saved, tmp_path, monkeypatch):
    _, _, fac = saved
    target = tmp_path / "fail.hfr"

    def boom(*a, **k):
        raise RuntimeError("disk full")
    monkeypatch.setattr(hfr, "_write_scene", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_hfr(fac, target)
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_reads_version_2_file(tmp_path):
    """A file written by hfrad 0.1 before format 3 (Y stored, tests/data/plates-v2.hfr) loads and solves.

    Its stored Y_c give the old solve ``B = E - Y_c (V^T E_c)``; the new solve from
    Q, V alone agrees to float32 rounding, and so does a v3 copy of it.
    """
    old = Path(__file__).parent / "data" / "plates-v2.hfr"
    assert read_hfr_metadata(old)["format_version"] == 2
    fac = load_hfr(old)
    with h5py.File(old) as f:
        Y, V, perm = f["factors/Y"][()], f["factors/V"][()], f["factors/perm"][()]
    E = fac.scene.emission
    Ei = E[perm]
    B_old = np.stack([Ei[:, c] - Y[c] @ (V.T @ Ei[:, c]) for c in range(3)], axis=1)[np.argsort(perm)]
    B = fac.solve(E)
    np.testing.assert_allclose(B, B_old, rtol=0, atol=2e-7 * np.abs(B_old).max())   # observed 3.5e-8
    e = np.random.default_rng(0).standard_normal(E.shape)
    Bt_old = np.stack([e[perm][:, c] - V @ (Y[c].T @ e[perm][:, c]) for c in range(3)], axis=1)[np.argsort(perm)]
    np.testing.assert_allclose(fac.solve(e, trans="T"), Bt_old, rtol=0, atol=2e-8 * np.abs(Bt_old).max())  # 3.4e-9
    new = save_hfr(fac, tmp_path / "plates-v3.hfr")
    assert read_hfr_metadata(new)["format_version"] == FORMAT_VERSION
    with h5py.File(new) as f:
        assert "Y" not in f["factors"] and f["factors/capacitance_inverse"].shape == (3, fac.rank, fac.rank)
    np.testing.assert_array_equal(load_hfr(new).solve(E), B)
    np.testing.assert_array_equal(load_hfr(new).solve(e, trans="T"), fac.solve(e, trans="T"))


def test_without_stored_inverses(saved, tmp_path):
    """A file without the k x k inverses (written before they were stored) recomputes them: same solve."""
    path, scene, fac = saved
    old = tmp_path / "noinv.hfr"
    old.write_bytes(path.read_bytes())
    with h5py.File(old, "a") as f:
        del f["factors/capacitance_inverse"]
    back = load_hfr(old)
    np.testing.assert_allclose(back.capacitance_inv, fac.capacitance_inv, rtol=0, atol=0)
    np.testing.assert_array_equal(back.solve(scene.emission), fac.solve(scene.emission))
