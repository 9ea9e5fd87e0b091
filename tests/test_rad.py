"""Radiance scene files (hfrad.scene.rad, hfrad.scene.radcmd): each material and surface kind, inline
commands run without a shell, refused inputs with their file and line."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hfrad
from hfrad.errors import SceneError
from hfrad.scene.rad import read_rad
from hfrad.scene.radcmd import MAX_COPIES

SQUARE = "12 0 0 0  1 0 0  1 1 0  0 1 0"   # 1 m^2 facing +z (up), counter-clockwise


def _write(folder, text, name="m.rad"):
    path = folder / name
    path.write_text(text)
    return path


def _material(kind, name, reals, strings=""):
    return f"void {kind} {name}\n{len(strings.split())} {strings}\n0\n{len(reals.split())} {reals}\n"


def _square(mod, name="sq", reals=SQUARE):
    return f"{mod} polygon {name}\n0\n0\n{reals}\n"


def _props(tmp_path, text):
    raw = read_rad(_write(tmp_path, text))
    return raw, raw["materials"]


def test_plastic_is_its_diffuse_part_and_the_specular_part_is_reported(tmp_path):
    raw, mats = _props(tmp_path, _material("plastic", "p", ".5 .4 .3 .1 0") + _square("p"))
    assert mats["p"]["reflectance"] == pytest.approx((0.45, 0.36, 0.27))
    assert any("specular part" in w and "m.rad:1" in w for w in raw["warnings"])


def test_metal_keeps_its_diffuse_part_and_names_the_dropped_specular_colour(tmp_path):
    raw, mats = _props(tmp_path, _material("metal", "m", ".8 .6 .4 .5 0") + _square("m"))
    assert mats["m"]["reflectance"] == pytest.approx((0.4, 0.3, 0.2))
    assert any("metal m: the specular part (0.4, 0.3, 0.2)" in w for w in raw["warnings"])


def test_trans_splits_reflected_and_transmitted_light(tmp_path):
    _, mats = _props(tmp_path, _material("trans", "t", ".8 .8 .8 0 0 .25 0") + _square("t"))
    assert mats["t"]["reflectance"] == pytest.approx((0.6,) * 3)
    assert mats["t"]["transmittance"] == pytest.approx((0.2,) * 3)


def test_glass_transmissivity_gives_radiance_s_transmittance(tmp_path):
    # Radiance's reference manual: a transmissivity of 0.96 is a transmittance of 0.88 (clear glass)
    _, mats = _props(tmp_path, _material("glass", "g", ".96 .96 .96") + _square("g"))
    assert mats["g"]["transmittance"][0] == pytest.approx(0.88, abs=0.002)
    assert 0.07 < mats["g"]["reflectance"][0] < 0.09          # two surfaces of ((n-1)/(n+1))^2 = 0.043
    scene = hfrad.load_scene(tmp_path / "m.rad")
    assert scene.materials[0].is_glazing


@pytest.mark.parametrize("kind,reals", [("light", "2 3 4"), ("glow", "2 3 4 0")])
def test_light_and_glow_emit_pi_times_their_radiance_and_do_not_reflect(tmp_path, kind, reals):
    # exitance pi L, in hfrad's photometric unit: Radiance's watt is 179 lm, hfrad's 683 lm
    _, mats = _props(tmp_path, _material(kind, "l", reals) + _square("l"))
    assert mats["l"]["emission"] == pytest.approx(tuple(math.pi * x * 179 / 683 for x in (2, 3, 4)))
    assert mats["l"]["reflectance"] == (0.0, 0.0, 0.0)


def test_alias_and_pattern_chain(tmp_path):
    text = (_material("plastic", "white", ".7 .7 .7 0 0") + "void alias paint white\n"
            + "void brightfunc dirt\n2 dirt dirt.cal\n0\n0\n"
            + "dirt plastic dirty\n0\n0\n5 .5 .5 .5 0 0\n" + _square("paint", "a") + _square("dirty", "b"))
    raw, mats = _props(tmp_path, text)
    assert raw["material_names"] == ["white", "dirty"]
    assert any("brightfunc dirt ignored" in w for w in raw["warnings"])


@pytest.mark.parametrize("corners,area", [
    ("18 0 0 0  2 0 0  2 1 0  1 1 0  1 2 0  0 2 0", 3.0),      # an L: a fan from corner 0 would cover the notch
    ("30 0 0 0  4 0 0  4 4 0  0 4 0  0 0 0  1 1 0  1 3 0  3 3 0  3 1 0  1 1 0", 12.0),   # a hole joined by a seam
])
def test_concave_polygon_keeps_its_area_and_faces_up(tmp_path, corners, area):
    scene = hfrad.load_scene(_write(tmp_path, _material("plastic", "p", ".5 .5 .5 0 0") + _square("p", "L", corners)))
    assert scene.total_area == pytest.approx(area, rel=1e-12)
    assert np.allclose(scene.normals, [0, 1, 0])              # +z turned to hfrad's y-up


def test_z_up_is_turned_to_y_up(tmp_path):
    tri = "9 1 2 3  2 2 3  1 3 3"
    raw, _ = _props(tmp_path, _material("plastic", "p", ".5 .5 .5 0 0") + _square("p", "t", tri))
    assert np.allclose(raw["vertices"][0], [1, 3, -2])
    assert any("Z-up" in w for w in raw["warnings"])


def test_redefined_material_keeps_both(tmp_path):
    text = (_material("plastic", "p", ".5 .5 .5 0 0") + _square("p", "a")
            + _material("plastic", "p", ".2 .2 .2 0 0") + _square("p", "b"))
    raw, mats = _props(tmp_path, text)
    assert mats["p"]["reflectance"][0] == 0.5 and mats["p~1"]["reflectance"][0] == 0.2


@pytest.mark.parametrize("text,where,words", [
    (_material("mirror", "m", "1 1 1") + _square("m"), "m.rad:1", "mirror"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "p sphere s\n0\n0\n4 0 0 0 1\n", "m.rad:5", "sphere"),
    (_square("nothing"), "m.rad:1", "not defined"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "p polygon x\n0\n0\n999999999999\n", "m.rad:8", "999,999,999,999"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "p polygon x\n0\n0\n8 0 0 0 1 0 0 1 1\n", "m.rad:5", "3 numbers"),
    (_material("plastic", "p", "1.5 .5 .5 0 0") + _square("p"), "m.rad:1", "outside [0, 1)"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!cat /etc/passwd\n", "m.rad:5", "not allowed"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!genbox p b 1 1 1; rm -rf x\n", "m.rad:5", "number"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!genbox p b 1 1 1 -r .1\n", "m.rad:5", "rounded"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!xform -t 0 0 1 ../outside.rad\n", "m.rad:5", "outside the model"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + f"!xform -a {MAX_COPIES} -a 2 -t 1 0 0 m.rad\n", "m.rad:5",
     "copies"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!xform -t 1 0 0\n", "m.rad:5", "without a file"),
    (_material("plastic", "p", ".5 .5 .5 0 0") + "!xform -t 1 0 0 m.rad\n", "m.rad:5", "include itself"),
])
def test_refused_inputs_name_the_file_and_line(tmp_path, text, where, words):
    (tmp_path.parent / "outside.rad").write_text(_square("p"))
    with pytest.raises(SceneError) as err:
        hfrad.load_scene(_write(tmp_path, text))
    assert where in str(err.value) and words in str(err.value)


def test_genbox_and_xform_run_radiance_without_a_shell(tmp_path):
    pytest.importorskip("pyradiance")
    _write(tmp_path, _material("plastic", "wood", ".4 .3 .2 0 0") + "void alias oak wood\n"
           + "!genbox oak desk 1 2 3\n", "desk.rad")
    text = (_material("plastic", "p", ".5 .5 .5 0 0") + _square("p")
            + "!genbox p box 1 2 3\n" + "!xform -t 10 0 0 -a 3 -t 0 5 0 desk.rad\n")
    scene = hfrad.load_scene(_write(tmp_path, text))
    # the square (1) + a 1 x 2 x 3 box (22) + three desks of 1 x 2 x 3 (66)
    assert scene.total_area == pytest.approx(1 + 22 + 66, rel=1e-9)
    desks = scene.material == scene.material_names.index("wood")
    lo = scene.triangles[desks].reshape(-1, 3)              # an uncut scene: one triangle per patch
    # Z-up (10..11, 0..12, 0..3) turned to y-up: x 10..11, y 0..3, z -12..0
    assert np.allclose(lo.min(axis=0), [10, 0, -12]) and np.allclose(lo.max(axis=0), [11, 3, 0])


def test_command_error_names_the_command_s_line(tmp_path):
    pytest.importorskip("pyradiance")
    _write(tmp_path, "void mirror m\n0\n0\n3 1 1 1\n", "bad.rad")
    text = _material("plastic", "p", ".5 .5 .5 0 0") + "!xform -t 1 0 0 bad.rad\n"
    with pytest.raises(SceneError, match=r"bad\.rad:1 \(read by .*m\.rad:5\).*mirror"):
        hfrad.load_scene(_write(tmp_path, text))


def test_info_cli_reports_windows_and_refuses_with_exit_2(tmp_path):
    from typer.testing import CliRunner

    from hfrad.cli import app

    good = _write(tmp_path, _material("glass", "g", ".96 .96 .96") + _material("plastic", "p", ".5 .5 .5 0 0")
                  + _square("g", "w") + _square("p", "f", "12 0 0 0  0 1 0  1 1 0  1 0 0"), "good.rad")
    out = CliRunner().invoke(app, ["info", str(good)])
    assert out.exit_code == 0 and "windows: 2 patches (g)" in " ".join(out.output.split())
    bad = _write(tmp_path, _material("mirror", "m", "1 1 1"), "bad.rad")
    out = CliRunner().invoke(app, ["info", str(bad)])
    assert out.exit_code == 2 and "bad.rad:1" in out.output and "Traceback" not in out.output


@pytest.mark.parametrize("module,path,text", [
    ("pyradiance", "m.rad", _material("plastic", "p", ".5 .5 .5 0 0") + "!genbox p b 1 1 1\n"),
    ("ifcopenshell", "m.ifc", "ISO-10303-21;\n"),
])
def test_a_missing_package_is_named_with_its_pip_command_at_use(tmp_path, monkeypatch, module, path, text):
    import sys

    from typer.testing import CliRunner

    from hfrad.cli import app

    monkeypatch.setitem(sys.modules, module, None)       # `import module` raises ImportError
    scene = _write(tmp_path, text, path)
    with pytest.raises(ImportError, match=f"pip install {module}"):
        hfrad.load_scene(scene)
    out = CliRunner().invoke(app, ["info", str(scene)])
    assert out.exit_code == 2 and f"pip install {module}" in out.output and "Traceback" not in out.output
    # a file that needs neither reads without them
    plain = _write(tmp_path, _material("plastic", "p", ".5 .5 .5 0 0") + _square("p"), "plain.rad")
    assert hfrad.load_scene(plain).n_patches == 2


def test_glazing_survives_the_hfr_file(tmp_path):
    # a closed unit box: five plastic sides and a glass one
    quads = ["12 0 0 0  0 1 0  1 1 0  1 0 0", "12 0 0 1  1 0 1  1 1 1  0 1 1", "12 0 0 0  1 0 0  1 0 1  0 0 1",
             "12 0 1 0  0 1 1  1 1 1  1 1 0", "12 0 0 0  0 0 1  0 1 1  0 1 0", "12 1 0 0  1 1 0  1 1 1  1 0 1"]
    text = (_material("plastic", "p", ".5 .5 .5 0 0") + _material("glass", "g", ".96 .96 .96")
            + "".join(_square("g" if k == 5 else "p", f"s{k}", q) for k, q in enumerate(quads)))
    scene = hfrad.load_scene(_write(tmp_path, text), emit={"p": (1.0, 1.0, 1.0)})
    fac = hfrad.factorize(scene, eps=0.05)
    back = hfrad.load(hfrad.save(fac, tmp_path / "box.hfr")).scene
    glass = back.materials[back.material_index("g")]
    assert glass.transmittance == pytest.approx((0.8815,) * 3, abs=1e-4) and glass.is_glazing
    assert not back.materials[back.material_index("p")].is_glazing


def _scene_as_rad(scene, path):
    """The scene's triangles as Radiance polygons (Z-up), written independently of hfrad's reader:
    reflectance -> plastic, emission E -> light of radiance E / pi x 683 / 179."""
    lines = []
    for k, m in enumerate(scene.materials):
        rgb = np.asarray(m.emission) / math.pi * 683 / 179 if m.is_emitter else np.asarray(m.reflectance)
        kind, extra = ("light", "") if m.is_emitter else ("plastic", " 0 0")
        lines.append(f"void {kind} m{k}\n0\n0\n{3 + 2 * (kind == 'plastic')} "
                     + " ".join(repr(float(x)) for x in rgb) + extra)
    for t, tri in enumerate(np.asarray(scene.triangles)):
        zup = np.stack([tri[:, 0], -tri[:, 2], tri[:, 1]], axis=1)
        lines.append(f"m{scene.material[t]} polygon t{t}\n0\n0\n9 " + " ".join(repr(float(x)) for x in zup.ravel()))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_scene_written_as_rad_reads_back_with_the_same_radiosity(tmp_path):
    # the Cornell box round trip: triangles, reflectance and light as Radiance describes them
    cornell = hfrad.load_scene("cornell")
    back = hfrad.load_scene(_scene_as_rad(cornell, tmp_path / "cornell.rad"))
    assert back.n_patches == cornell.n_patches
    np.testing.assert_allclose(back.triangles, cornell.triangles, atol=1e-12)
    lit = np.asarray(cornell.emission).max(axis=1) > 0
    np.testing.assert_allclose(back.emission, cornell.emission, rtol=1e-12)
    np.testing.assert_allclose(back.reflectance[~lit], cornell.reflectance[~lit], rtol=1e-12)
    assert (back.reflectance[lit] == 0).all()            # a Radiance light does not reflect
    same = cornell.replace(reflectance=back.reflectance)  # ... so compare with hfrad's light not reflecting either
    b = [hfrad.factorize(s, eps=0.01).solve(s.emission) for s in (same, back)]
    np.testing.assert_allclose(b[1], b[0], rtol=1e-9, atol=1e-12)
