"""The public API as a user meets it: ``import hfrad`` and the names it exports."""

from __future__ import annotations

import re

import numpy as np
import pytest

import hfrad


def test_factorize_works_twice_after_the_subpackage_is_imported():
    # the factorizers' subpackage is hfrad.lowrank; importing it must leave the
    # function hfrad.factorize alone (it once shared the name: issue 10, item 4)
    import hfrad.lowrank.hf  # noqa: F401
    from hfrad.lowrank.hf import HFStream  # noqa: F401
    from hfrad.lowrank.factors import LowRank  # noqa: F401

    scene = hfrad.load_scene("furnace", patches=60)
    first = hfrad.factorize(scene, eps=0.05)
    second = hfrad.factorize(scene, eps=0.05)
    assert callable(hfrad.factorize)
    from hfrad import factorize
    assert factorize is hfrad.factorize
    B1, B2 = first.solve(scene.emission), second.solve(scene.emission)
    np.testing.assert_array_equal(B1, B2)


def test_exports_resolve_to_documented_objects_of_that_name():
    # the API reference (docs/reference.md) is generated from these names and their docstrings
    for name in hfrad.__all__:
        obj = getattr(hfrad, name)
        if name == "__version__":
            assert re.fullmatch(r"\d+\.\d+\.\d+\S*", obj), obj
            continue
        assert callable(obj) and obj.__name__ == name, name              # a function or class, not an alias
        assert (obj.__doc__ or "").strip(), f"hfrad.{name} has no docstring"
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        hfrad.not_a_name  # noqa: B018


def _small_system():
    scene = hfrad.load_scene("cornell", patches=300)
    F = hfrad.form_factor_matrix(scene)
    return scene, F


def test_linear_operator_is_the_woodbury_inverse_and_preconditions_gmres():
    from scipy.sparse.linalg import gmres

    scene, F = _small_system()
    fac = hfrad.factorize_matrix(F, scene.reflectance, eps=0.05, dtype="float64")
    n = scene.n_patches
    for c in range(3):
        A = np.eye(n) - scene.reflectance[:, [c]] * F                 # the exact operator
        M = fac.as_linear_operator(c)
        e = scene.emission[:, c]
        np.testing.assert_allclose(M @ e, fac.solve(scene.emission)[:, c], rtol=1e-12)
        g = np.random.default_rng(c).standard_normal(n)
        np.testing.assert_allclose(M.rmatvec(g), fac.solve(np.repeat(g[:, None], 3, 1), trans="T")[:, c],
                                   rtol=1e-10, atol=1e-12)
        counts = {}
        for name, pre in (("none", None), ("hf", M)):
            it = [0]
            x, info = gmres(A, e, M=pre, rtol=1e-10, atol=0.0, restart=200,
                            callback=lambda _: it.__setitem__(0, it[0] + 1), callback_type="pr_norm")
            assert info == 0
            assert np.linalg.norm(A @ x - e) <= 1e-9 * np.linalg.norm(e)
            counts[name] = it[0]
        # an eps = 0.05 factorization leaves a residual operator of norm << 1: few iterations
        assert counts["hf"] <= 8 and counts["hf"] < counts["none"], counts


def test_trans_and_deprecated_transpose_agree():
    import pytest

    scene, F = _small_system()
    fac = hfrad.factorize_matrix(F, scene.reflectance, eps=0.05, dtype="float64")
    g = np.random.default_rng(1).standard_normal((scene.n_patches, 3))
    with pytest.warns(DeprecationWarning, match="trans='T'"):
        old = fac.solve(g, transpose=True)
    np.testing.assert_array_equal(old, fac.solve(g, trans="T"))
    with pytest.raises(hfrad.InputError, match="trans must be"):
        fac.solve(g, trans="X")


def test_factorize_input_errors():
    import pytest

    scene, F = _small_system()
    with pytest.raises(hfrad.InputError, match=r"not ndarray; for a form-factor matrix use hfrad.factorize_matrix"):
        hfrad.factorize(F)
    with pytest.raises(hfrad.InputError, match=r"for a Scene use hfrad.factorize\(scene\)"):
        hfrad.factorize_matrix(scene, scene.reflectance)
    with pytest.raises(hfrad.InputError, match=r"load the file first: hfrad.load_scene\('room.obj'\)"):
        hfrad.factorize("room.obj")
    bad = F.copy()
    bad[3, 5] = np.nan
    with pytest.raises(hfrad.InputError, match=r"F\[3, 5\]"):
        hfrad.factorize_matrix(bad, scene.reflectance)
    rho = scene.reflectance.copy()
    rho[7, 1] = np.nan
    with pytest.raises(ValueError, match="patch 7"):
        hfrad.factorize_matrix(F, rho)
    with pytest.raises(hfrad.SceneError, match="patch 2 reflectance"):
        scene.replace(reflectance=np.where(np.arange(scene.n_patches)[:, None] == 2, np.nan, scene.reflectance))


def test_trimesh_round_trip():
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    rho = np.linspace(0.1, 0.8, len(box.faces))[:, None].repeat(3, 1)
    scene = hfrad.Scene.from_trimesh(box, reflectance=rho)
    assert scene.n_patches == len(box.faces)
    np.testing.assert_allclose(scene.total_area, box.area)
    np.testing.assert_allclose(scene.normals, box.face_normals, atol=1e-12)
    np.testing.assert_array_equal(scene.reflectance, rho)
    back = scene.to_trimesh()
    np.testing.assert_array_equal(back.faces, box.faces)
    np.testing.assert_allclose(back.vertices, box.vertices)
    np.testing.assert_array_equal(back.face_attributes["reflectance"], rho)
    import pytest
    with pytest.raises(hfrad.SceneError, match="face 0"):
        hfrad.Scene.from_trimesh(box, reflectance=(1.0, 0.5, 0.5))


def test_writers_take_the_object_first(tmp_path):
    import pytest

    image = np.zeros((4, 4, 3), np.uint8)
    hfrad.save_png(image, tmp_path / "a.png")
    with pytest.warns(DeprecationWarning, match=r"save_png\(image, path\)"):
        hfrad.save_png(tmp_path / "b.png", image)
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
