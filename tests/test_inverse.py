"""Inverse lighting design (``hfrad.design``, ``hfrad design``) on a small Cornell box.

The reference is an exact dense solve we did not write the solver for: the
dense form-factor matrix F and ``numpy.linalg.solve`` of ``(I - R_c F) B = E``,
with irradiance taken from its definition ``H = F B``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import hfrad
from hfrad.cli import app
from hfrad.formfactors.blocks import form_factor_matrix
from hfrad.inverse import SpecError, design, parse_spec
from hfrad.render.falsecolor import photometric


@pytest.fixture(scope="module")
def case():
    """A 200-patch Cornell box factored almost exactly (eps 1e-9, float64), its dense F."""
    scene = hfrad.load_scene("cornell", patches=200)
    fac = hfrad.factorize(scene, eps=1e-9, dtype="float64")
    F = form_factor_matrix(scene)
    return scene, fac, F


def dense_solve(F, rho, E):
    """(n, 3) radiosity of the exact dense system, channel by channel."""
    n = len(F)
    return np.stack([np.linalg.solve(np.eye(n) - rho[:, c:c + 1] * F, E[:, c]) for c in range(3)], axis=1)


def lux(F, B, patches):
    """Illuminance in lux (683 lm/W x luminance-weighted H = F B) on ``patches``."""
    return photometric(F[patches] @ B, "lux")


def light_spec(**target):
    return {"emitters": [{"name": "light", "material": "light", "max": 1000.0}],
            "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance_lux", **target}]}


def test_single_emitter_min_goal_is_goal_over_response(case):
    scene, fac, F = case
    r = design(fac, light_spec(min=300.0))
    assert r.feasible and r.report["status"] == "optimal"
    lamp = scene.material == scene.material_names.index("light")
    E1 = np.zeros((scene.n_patches, 3))
    E1[lamp] = 1.0
    floor = np.flatnonzero(scene.group == scene.groups.index("floor"))
    response = lux(F, dense_solve(F, fac.reflectance, E1), floor).min()   # lux per unit intensity
    exact = 300.0 / response
    assert r.intensity["light"] == pytest.approx(exact, rel=1e-6)
    area = scene.areas[lamp].sum()
    assert r.report["emitters"][0]["power_W"] == pytest.approx(exact * area * photometric(np.ones(3)), rel=1e-6)
    assert r.report["evaluations"] == 1


def test_constraints_hold_in_an_independent_full_solve(case):
    scene, fac, F = case
    spec = {"emitters": [{"name": "light", "material": "light", "max": 500.0},
                         {"name": "red_wall", "group": "left", "max": 5.0, "color": [1.0, 0.2, 0.2]}],
            "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance_lux", "min": 250.0, "uniformity": 0.4},
                        {"name": "back", "group": "back", "quantity": "radiosity", "max": 1.5},
                        {"name": "tall", "group": "tall_block", "quantity": "irradiance", "mean": 1.0}]}
    r = design(fac, spec)
    assert r.feasible, r.report["message"]
    B = dense_solve(F, fac.reflectance, r.exitance)
    sel = {g: np.flatnonzero(scene.group == scene.groups.index(g)) for g in ("floor", "back", "tall_block")}
    floor = lux(F, B, sel["floor"])
    w = scene.areas[sel["floor"]] / scene.areas[sel["floor"]].sum()
    rtol = 1e-6
    assert floor.min() >= 250.0 * (1 - rtol)
    assert floor.min() / (w @ floor) >= 0.4 * (1 - rtol)
    assert photometric(B[sel["back"]]).max() <= 1.5 * (1 + rtol)
    tall = photometric(F[sel["tall_block"]] @ B)
    wt = scene.areas[sel["tall_block"]] / scene.areas[sel["tall_block"]].sum()
    assert wt @ tall >= 1.0 * (1 - rtol)
    # the report's own verification agrees with the dense one
    v = r.report["verified"]
    assert v["goals_met"] and v["max_relative_deviation"] < 1e-6
    assert v["targets"][0]["min"] == pytest.approx(floor.min(), rel=1e-6)
    # least power: some goal is active (otherwise less light would do)
    ach = {t["name"]: t["achieved"] for t in r.report["targets"]}
    assert (ach["floor"]["min"] == pytest.approx(250.0, rel=1e-6)
            or ach["floor"]["uniformity"] == pytest.approx(0.4, rel=1e-6)
            or ach["tall"]["mean"] == pytest.approx(1.0, rel=1e-6)
            or ach["back"]["max"] == pytest.approx(1.5, rel=1e-6))


def test_irradiance_of_black_patches_from_form_factors(case):
    """rho = 0 makes (B - E) / rho meaningless; the form-factor rows give H = F B exactly."""
    scene, fac, F = case
    floor = np.flatnonzero(scene.group == scene.groups.index("floor"))
    rho = fac.reflectance.copy()
    rho[floor] = 0.0
    black = fac.with_reflectance(rho)
    r = design(black, light_spec(min=100.0))
    assert r.feasible
    B = dense_solve(F, rho, r.exitance)
    assert lux(F, B, floor).min() == pytest.approx(100.0, rel=1e-6)


def test_least_squares_recovers_the_intensities_behind_the_means(case):
    """Means measured (densely) under known intensities are fitted exactly by those intensities."""
    scene, fac, F = case
    truth = {"light": 20.0, "short": 2.0}
    emitters = [{"name": "light", "material": "light", "max": 1000.0},
                {"name": "short", "group": "short_block", "max": 1000.0, "color": [0.2, 0.4, 1.0]}]
    E = np.zeros((scene.n_patches, 3))
    E[scene.material == scene.material_names.index("light")] = truth["light"]
    E[scene.group == scene.groups.index("short_block")] = truth["short"] * np.array([0.2, 0.4, 1.0])
    B = dense_solve(F, fac.reflectance, E)
    means = {}
    for g in ("floor", "ceiling"):
        p = np.flatnonzero(scene.group == scene.groups.index(g))
        means[g] = float(scene.areas[p] @ lux(F, B, p) / scene.areas[p].sum())
    spec = {"emitters": emitters, "objective": "least_squares",
            "targets": [{"name": g, "group": g, "quantity": "irradiance_lux", "mean": m} for g, m in means.items()]}
    r = design(fac, spec)
    assert r.report["status"] == "optimal"
    assert r.intensity["light"] == pytest.approx(truth["light"], rel=1e-6)
    assert r.intensity["short"] == pytest.approx(truth["short"], rel=1e-6)
    assert r.report["objective"]["value"] < 1e-12


def test_infeasible_names_the_conflicting_goals(case):
    scene, fac, F = case
    spec = light_spec(min=300.0)
    spec["targets"] += [{"name": "left", "group": "left", "quantity": "radiosity", "max": 1e-3},
                        {"name": "ceiling", "group": "ceiling", "quantity": "radiosity", "max": 1e6}]
    r = design(fac, spec)
    assert not r.feasible and r.report["status"] == "infeasible"
    assert sorted(r.report["conflicts"]) == ["floor.min", "left.max"]
    assert "floor.min" in r.report["message"] and "left.max" in r.report["message"]
    assert r.exitance is None and r.report["emitters"][0]["intensity"] is None
    json.loads(r.to_json())
    from hfrad.errors import InputError
    from hfrad.inverse.emission import emission_settings
    with pytest.raises(InputError, match="no feasible design to write as an emission file"):
        emission_settings(r, scene)
    # the emitter's own bound can be one side of the conflict
    weak = light_spec(min=300.0)
    weak["emitters"][0]["max"] = 0.01
    assert sorted(design(fac, weak).report["conflicts"]) == ["floor.min", "light.max"]
    # a goal the fixed background light alone breaks conflicts with nothing else
    dark = light_spec(min=1.0)
    dark["emitters"][0] = {"name": "short", "group": "short_block", "max": 10.0}
    dark["targets"].append({"name": "ceiling", "group": "ceiling", "quantity": "irradiance", "max": 1e-6})
    r = design(fac, dark)
    assert r.report["conflicts"] == ["ceiling.max"] and "on its own" in r.report["message"]


@pytest.mark.parametrize("change, field", [
    (lambda s: s["emitters"][0].update(material="nonesuch"), "emitters[0].material"),
    (lambda s: s["emitters"][0].update(max=-1.0), "emitters[0].max"),
    (lambda s: s["targets"][0].update(quantity="luminance"), "targets[0].quantity"),
    (lambda s: s["targets"][0].update(group="attic"), "targets[0].group"),
    (lambda s: s["targets"][0].update(minimum=3), "targets[0].minimum"),
    (lambda s: s["targets"][0].update(uniformity=1.5), "targets[0].uniformity"),
    (lambda s: s["targets"][0].update(min=10.0, max=5.0), "targets[0].min"),
    (lambda s: s["emitters"][0].update(color=[0, 0]), "emitters[0].color"),
    (lambda s: s.update(objective="max_power"), "objective"),
    (lambda s: s.update(objective="least_squares"), "objective"),
    (lambda s: s.update(emitters=[]), "emitters"),
])
def test_malformed_spec_names_the_field(case, change, field):
    spec = light_spec(min=1.0)
    change(spec)
    with pytest.raises(SpecError) as err:
        parse_spec(spec, case[0])
    assert f"{field}:" in str(err.value)


def test_emission_file_reproduces_the_design(case):
    from hfrad.inverse.emission import emission_settings
    from hfrad.io.emission import emission_overrides
    from hfrad.scene.load import set_emission

    scene, fac, F = case
    spec = light_spec(min=100.0)
    spec["emitters"].append({"name": "blue_block", "group": "short_block", "max": 5.0, "color": [0.1, 0.2, 1.0]})
    spec["background"] = "none"
    r = design(fac, spec)
    settings = emission_settings(r, scene)
    assert np.array_equal(set_emission(scene, emission_overrides(settings)).emission, r.exitance)
    spec["emitters"][1] = {"name": "two", "patches": [0, 1], "max": 5.0}
    with pytest.raises(SpecError, match="one material or group name"):
        emission_settings(design(fac, spec), scene)


def test_unknown_design_method_is_refused_before_any_solve(case, monkeypatch):
    import sys

    from hfrad.errors import InputError

    module = sys.modules["hfrad.inverse.design"]     # (hfrad.inverse.design is also the function)

    scene, fac, F = case
    monkeypatch.setattr(module, "response", lambda *a, **k: pytest.fail("solved before refusing the method"))
    with pytest.raises(InputError, match="method must be 'auto', 'forward' or 'adjoint', got 'both'"):
        design(fac, light_spec(min=1.0), method="both")


def test_overlapping_emitters_are_refused(case):
    spec = light_spec(min=1.0)
    spec["emitters"].append({"name": "again", "material": "light"})
    with pytest.raises(SpecError, match=r"emitters\[1\].*already selected by emitters\[0\]"):
        parse_spec(spec, case[0])


def test_cli_exit_codes(case, tmp_path):
    scene, fac, F = case
    hfr = tmp_path / "cornell.hfr"
    hfrad.save(fac, hfr)
    runner = CliRunner()

    def run(spec, *extra):
        path = tmp_path / "spec.json"
        path.write_text(json.dumps(spec))
        return runner.invoke(app, ["design", str(path), str(hfr), *map(str, extra)])

    out, png = tmp_path / "result.json", tmp_path / "design.png"
    em = tmp_path / "emission.json"
    ok = run(light_spec(min=300.0), "-o", out, "--render", png, "--width", 48, "--height", 32, "--quiet",
             "--emission-out", em, "--falsecolor", "--show", "irradiance")
    assert ok.exit_code == 0, ok.output
    result = json.loads(out.read_text())
    assert result["feasible"] and result["verified"]["goals_met"] and png.stat().st_size > 0
    lamp = json.loads(em.read_text())["emitters"][0]
    assert lamp["name"] == "light" and lamp["exitance"][0] == pytest.approx(result["emitters"][0]["intensity"])
    relit = runner.invoke(app, ["solve", str(hfr), "-o", str(tmp_path / "b.npz"), "--emission-file", str(em)])
    assert relit.exit_code == 0, relit.output
    for key in ("emitters", "targets", "evaluations", "time_s", "objective"):
        assert key in result
    bad = light_spec(min=300.0)
    bad["emitters"][0]["max"] = 0.01
    infeasible = run(bad, "-o", tmp_path / "r2.json", "--quiet")
    assert infeasible.exit_code == 1 and "light.max" in infeasible.output
    assert json.loads((tmp_path / "r2.json").read_text())["feasible"] is False
    malformed = light_spec(min=300.0)
    malformed["targets"][0]["quantity"] = "lux"
    err = run(malformed, "-o", tmp_path / "r3.json")
    assert err.exit_code == 2 and "targets[0].quantity" in err.output and "Traceback" not in err.output
    assert not (tmp_path / "r3.json").exists()
    for bad_option in (["-o", tmp_path / "r.txt"], ["-o", out, "--emission-out", tmp_path / "e.txt"],
                       ["-o", out, "--render", png, "--show", "luminance"],
                       ["-o", out, "--render", png, "--camera", "nowhere"]):
        bad_run = run(light_spec(min=1.0), *bad_option)
        assert bad_run.exit_code == 2 and "Traceback" not in bad_run.output, bad_option
    by_patches = light_spec(min=1.0)
    by_patches["emitters"][0] = {"name": "two", "patches": [0, 1], "max": 100.0}
    refused = run(by_patches, "-o", tmp_path / "r4.json", "--emission-out", em)
    assert refused.exit_code == 2 and "emitters[0]" in refused.output and not (tmp_path / "r4.json").exists()


def test_batches_of_emitters_give_the_same_response(case):
    """Many emitters are solved in several batches (bounded memory) with the same result."""
    from hfrad.inverse.transfer import response

    scene, fac, F = case
    spec = parse_spec({"emitters": [{"name": f"p{i}", "patches": [int(i)]} for i in range(0, 40, 3)],
                       "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance", "min": 0.1}]},
                      scene)
    whole = response(fac, spec)
    done = []
    pieces = response(fac, spec, batch_bytes=2 * scene.n_patches * 3 * 8 * 4, progress=lambda d, t: done.append(d))
    # 14 emitters and the background (the scene's own light): 15 right-hand sides, 4 per batch
    assert done == [4, 8, 12, 15] and whole.evaluations == pieces.evaluations == 15
    np.testing.assert_allclose(pieces.matrix[0], whole.matrix[0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(pieces.offset[0], whole.offset[0], rtol=1e-12, atol=0)


def test_toml_spec_and_the_office_example(tmp_path):
    from pathlib import Path

    office = Path(__file__).resolve().parent.parent / "examples" / "office"
    scene = hfrad.load_scene(str(office / "office.obj"))
    spec = parse_spec(office / "spec.json", scene)
    assert [e.name for e in spec.emitters] == [f"lum_{k}" for k in range(1, 7)]
    desk = spec.targets[0]
    assert (scene.material[desk.patches] == scene.material_names.index("desk")).all()
    assert (scene.group[desk.patches] == scene.groups.index("desk_1")).all()
    toml = tmp_path / "spec.toml"
    toml.write_text('objective = "min_power"\n[[emitters]]\nmaterial = "luminaire"\nmax = 60\n'
                    '[[targets]]\nmaterial = "desk"\nquantity = "irradiance_lux"\nmin = 500\n')
    parsed = parse_spec(toml, scene)
    assert parsed.emitters[0].max == 60.0 and parsed.targets[0].min == 500.0
    toml.write_text('[[emitters]]\nmaterial = "luminaire"\nmax = -60\n[[targets]]\nmaterial = "desk"\n')
    with pytest.raises(SpecError, match=r"spec.toml: emitters\[0\].max"):
        parse_spec(toml, scene)


def test_adjoint_rows_equal_the_forward_response(case):
    """Transposed solves give the same rows as forward solves (radiosity, irradiance, black patches, means)."""
    from hfrad.inverse.transfer import adjoint_response, response

    scene, fac, F = case
    floor = np.flatnonzero(scene.group == scene.groups.index("floor"))
    rho = fac.reflectance.copy()
    rho[floor[:5]] = 0.0                                       # some black patches: H = F B rows
    black = fac.with_reflectance(rho)
    spec = parse_spec({
        "emitters": [{"name": "light", "material": "light"}, {"name": "tall", "group": "tall_block"},
                     {"name": "left", "group": "left", "color": [0.9, 0.1, 0.1]}],
        "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance_lux", "min": 1.0},
                    {"name": "back", "group": "back", "quantity": "radiosity", "max": 9.0},
                    {"name": "short", "group": "short_block", "quantity": "irradiance", "mean": 1.0},
                    {"name": "ceiling", "group": "ceiling", "quantity": "radiosity"}]}, scene)
    fwd, adj = response(black, spec), adjoint_response(black, spec)
    assert adj.rows == ["patches", "patches", "mean", "none"] and adj.method == "adjoint"
    assert adj.evaluations == len(floor) + int((scene.group == scene.groups.index("back")).sum()) + 1
    for j in (0, 1):
        np.testing.assert_allclose(adj.matrix[j], fwd.matrix[j], rtol=1e-9, atol=1e-12 * np.abs(fwd.matrix[j]).max())
        np.testing.assert_allclose(adj.offset[j], fwd.offset[j], rtol=1e-9, atol=1e-12 * np.abs(fwd.offset[j]).max())
    w = fwd.weight[2]
    np.testing.assert_allclose(adj.matrix[2][0], w @ fwd.matrix[2], rtol=1e-9)
    np.testing.assert_allclose(adj.offset[2][0], w @ fwd.offset[2], rtol=1e-9)
    assert adj.matrix[3].shape == (0, 3)


def test_many_emitters_few_goals_take_the_adjoint(case):
    """'Painting with light': every ceiling patch an emitter, two mean goals: 2 + 1 solves, not 30+."""
    scene, fac, F = case
    ceiling = np.flatnonzero(scene.group == scene.groups.index("ceiling"))
    spec = {"emitters": [{"name": f"c{i}", "patches": [int(i)], "max": 50.0} for i in ceiling],
            "targets": [{"name": "floor", "group": "floor", "quantity": "irradiance_lux", "mean": 300.0},
                        {"name": "tall", "group": "tall_block", "quantity": "irradiance_lux", "mean": 150.0}],
            "background": "none"}
    auto = design(fac, spec)
    forward = design(fac, spec, method="forward")
    assert auto.report["method"] == "adjoint" and auto.report["evaluations"] == 3
    assert forward.report["evaluations"] == len(ceiling)
    assert auto.feasible and auto.report["verified"]["goals_met"]
    assert auto.report["verified"]["max_relative_deviation"] < 1e-9
    assert auto.report["total_power_W"] == pytest.approx(forward.report["total_power_W"], rel=1e-7)
    B = dense_solve(F, fac.reflectance, auto.exitance)
    floor = np.flatnonzero(scene.group == scene.groups.index("floor"))
    assert scene.areas[floor] @ lux(F, B, floor) / scene.areas[floor].sum() >= 300.0 * (1 - 1e-6)


@pytest.mark.slow
def test_office_example_reproduces_its_result():
    """examples/office: the committed result.json is what the README's commands give (to 1%)."""
    from pathlib import Path

    office = Path(__file__).resolve().parent.parent / "examples" / "office"
    fac = hfrad.factorize(hfrad.load_scene(str(office / "office.obj"), patches=3000), eps=0.01)
    r = design(fac, office / "spec.json")
    committed = json.loads((office / "result.json").read_text())
    assert r.feasible and r.report["verified"]["goals_met"] and r.report["evaluations"] == 7
    assert r.report["total_power_W"] == pytest.approx(committed["total_power_W"], rel=0.01)
