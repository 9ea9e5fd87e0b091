"""Luminaires, direct light, sensors, the gather operator and relighting, against closed forms.

Known answers: a point source above a plane (E = I(theta) cos(theta) / d^2), a
Lambertian disk above a point (E = M r^2 / (r^2 + h^2)) as emitting patches
through the gather operator and as an IES luminaire with a round opening, and
the furnace (B = E / (1 - rho); irradiance inside = B; a luminaire's flux
conserved). Relighting by superposition is checked against a direct solve.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import hfrad
from hfrad.errors import FileFormatError, InputError
from hfrad.lighting import (LayoutError, LightingModel, Luminaire, Photometry, caster_for, direct_illuminance,
                            floor_grid, gather_operator, grid_stats, parse_layout, read_layout, read_sensors,
                            rectangle_grid, save_plan, write_csv, write_sensors)
from hfrad.lighting.sensors import SensorSet
from hfrad.render.falsecolor import LUMINOUS_EFFICACY
from hfrad.render.tonemap import LUMINANCE_WEIGHTS
from hfrad.scene.scene import Material, Scene


def _rotational(fn, step=0.5, size=(0.0, 0.0, 0.0)) -> Photometry:
    v = np.arange(0, 180 + step / 2, step)
    return Photometry("C", [0.0], v, fn(v)[None, :], size=size, name="test")


def _downlight(v):
    return np.where(v <= 90, 1200 * np.cos(np.radians(v)) ** 3 + 100 * np.cos(np.radians(v)), 0.0)


def _floor(half=10.0, y=0.0) -> Scene:
    V = [(-half, y, -half), (-half, y, half), (half, y, half), (half, y, -half)]
    return Scene(np.array(V, float), np.array([[0, 1, 2], [0, 2, 3]]), np.zeros(2, int),
                 (Material("floor", (0.5, 0.5, 0.5)),))


def test_luminance_weights_match_the_renderer():
    from hfrad.lighting.luminaire import _Y
    np.testing.assert_array_equal(_Y, LUMINANCE_WEIGHTS)


def test_point_source_above_a_plane_inverse_square_cosine():
    """E = I(theta) cos(theta) / d^2 within 0.5% (observed ~1e-5: the 0.5-degree table's interpolation)."""
    ph = _rotational(_downlight)
    lum = Luminaire(ph, [0.3, 2.5, -0.2])
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-4, 4, 200), np.zeros(200), rng.uniform(-4, 4, 200)])
    N = np.tile([0.0, 1.0, 0.0], (200, 1))
    E = direct_illuminance([lum], P, N, caster=caster_for(_floor()))[:, 0]
    v = P - lum.position
    d = np.linalg.norm(v, axis=1)
    cos = 2.5 / d
    exact = _downlight(np.degrees(np.arccos(cos))) * cos / d ** 2
    np.testing.assert_allclose(E, exact, rtol=5e-3)
    assert np.max(np.abs(E / exact - 1)) < 3e-4                      # observed 1.4e-4


def test_luminaire_aim_and_rotation():
    """Aimed along +x, C0 turned 90 degrees: the C90 plane's peak lands where expected."""
    g = np.arange(0, 91, 1.0)
    h = np.array([0.0, 90.0])
    cd = np.vstack([100 * np.ones_like(g), 100 + 900 * (g == 30)])   # a spike at C90, gamma 30
    ph = Photometry("C", h, g, cd)
    lum = Luminaire(ph, [0, 0, 0], aim=[1, 0, 0], rotation=0.0)
    F = lum.frame
    np.testing.assert_allclose(F[:, 2], [-1, 0, 0])                  # local up = -aim
    np.testing.assert_allclose(F[:, 0] @ F[:, 1], 0, atol=1e-15)
    # the direction at gamma 30 in the C90 plane, in scene coordinates
    d_local = np.array([0.0, math.sin(math.radians(30)), -math.cos(math.radians(30))])
    assert lum.intensity(F @ d_local) == pytest.approx(1000.0)
    turned = lum.replace(rotation=90.0)
    # after a 90-degree turn the old C90 direction is C180 (= C0 by the quadrant symmetry): 100 cd
    assert turned.intensity(F @ d_local) == pytest.approx(100.0)
    np.testing.assert_allclose(turned.frame[:, 0], F[:, 1], atol=1e-12)


def test_lambertian_disk_luminaire_above_a_point():
    """I = I0 cos(gamma) over a round opening of radius r: E = I0 / (r^2 + h^2) below its centre."""
    r, I0 = 0.3, 1000.0
    ph = _rotational(lambda v: np.where(v <= 90, I0 * np.cos(np.radians(v)), 0.0), size=(-2 * r, 0.0, 0.0))
    lum = Luminaire(ph, [0, 1.0, 0])
    for h in (0.2, 0.5, 1.0):
        P = np.array([[0.0, 1.0 - h, 0.0]])
        E = direct_illuminance([lum], P, [[0, 1, 0]], spacing=r / 12)[0, 0]
        assert E == pytest.approx(I0 / (r * r + h * h), rel=5e-3)
    # far away (beyond 5 sizes) the point-source law holds
    E = direct_illuminance([lum], [[0, -4.0, 0]], [[0, 1, 0]])[0, 0]
    assert E == pytest.approx(I0 / 25.0, rel=1e-9)


def _disk_scene(r=0.5, h=1.0, sides=96, M=3.0) -> Scene:
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    rim = np.column_stack([r * np.cos(a), np.full(sides, h), r * np.sin(a)])
    V = np.vstack([[0, h, 0], rim])
    faces = np.array([[0, 1 + k, 1 + (k + 1) % sides] for k in range(sides)])
    scene = Scene(V, faces, np.zeros(sides, int), (Material("disk", (0.0, 0.0, 0.0), (M, M, M)),))
    if scene.normals[0, 1] > 0:                                        # face the point below
        scene = Scene(V, faces[:, ::-1], np.zeros(sides, int), scene.materials)
    return scene


def test_lambertian_disk_above_a_point_through_the_gather_operator():
    """Emitting patches of exitance M, point at depth h: E = M r^2 / (r^2 + h^2) (r of the polygon's area)."""
    scene = _disk_scene()
    r2 = scene.areas.sum() / math.pi
    P = np.array([[0.0, 1.0 - h, 0.0] for h in (0.25, 0.5, 1.0)])
    G = gather_operator(scene, P, np.tile([0.0, 1.0, 0.0], (3, 1)))
    H = G.apply(np.full(scene.n_patches, 3.0))
    exact = 3.0 * r2 / (r2 + np.array([0.25, 0.5, 1.0]) ** 2)
    np.testing.assert_allclose(H, exact, rtol=1e-5)                   # float32 G: observed ~1e-7


@pytest.fixture(scope="module")
def furnace():
    scene = hfrad.load_scene("furnace", patches=200)
    return hfrad.factorize(scene, eps=1e-4)


def test_furnace_sensors_see_b_equals_e_over_one_minus_rho(furnace):
    model = LightingModel(furnace, [], background="scene")
    rng = np.random.default_rng(3)
    P = rng.uniform(0.2, 0.8, (40, 3))
    N = rng.normal(size=(40, 3))
    resp = model.sensors(SensorSet("inside", P, N))
    expected = LUMINOUS_EFFICACY * 1.0 / (1 - 0.5)                    # E = 1 W/m^2 grey, rho = 0.5
    np.testing.assert_allclose(resp.illuminance(np.zeros(0)), expected, rtol=2e-3)
    np.testing.assert_allclose(model.background_radiosity, 2.0, rtol=2e-3)


def test_furnace_luminaire_flux_is_conserved(furnace):
    """All of a luminaire's flux lands on the walls; the radiosity's power is rho Phi / (1 - rho)."""
    ph = _rotational(_downlight)
    lum = Luminaire(ph, [0.5, 0.7, 0.45])
    model = LightingModel(furnace, [lum], background="none")
    A = furnace.scene.areas
    phi = ph.flux()
    assert A @ model.patch_direct[:, 0] == pytest.approx(phi, rel=0.02)
    power = LUMINOUS_EFFICACY * (A @ model.radiosity_basis[:, 0, 0])
    assert power == pytest.approx(0.5 * (A @ model.patch_direct[:, 0]) / 0.5, rel=2e-3)


@pytest.fixture(scope="module")
def cornell():
    scene = hfrad.load_scene("cornell", patches=300)
    return hfrad.factorize(scene, eps=1e-3)


def test_relighting_is_superposition_of_one_batched_solve(cornell):
    ph = _rotational(_downlight)
    lums = [Luminaire(ph, [x, 1.9, z], color=c, name=f"L{i}") for i, (x, z, c) in
            enumerate([(-0.5, -0.5, [1, 1, 1]), (0.5, 0.3, [1, 0.8, 0.6]), (0.0, 0.5, [0.6, 0.8, 1])])]
    model = LightingModel(cornell, lums, background="scene")
    assert model.timings["right_hand_sides"] == 4                     # 3 luminaires + the scene's light
    grid = rectangle_grid((-0.9, 0.9), (-0.9, 0.9), 1.3, 0.25)
    resp = model.sensors(grid)
    w = np.array([0.3, 1.0, 0.55])
    # the same state from scratch: one solve of its first-bounce emission, direct recomputed
    rho = cornell.reflectance
    H = model.patch_direct @ w                                        # unit-free: each column at dimming 1
    E = sum(w[l] * rho * model.patch_direct[:, l:l + 1] / LUMINOUS_EFFICACY * lums[l].color for l in range(3))
    B = cornell.solve(E + cornell.scene.emission)
    np.testing.assert_allclose(model.radiosity(w), B, rtol=5e-5)      # float32 factors: observed 1.2e-5
    direct = direct_illuminance([l.replace(dimming=1.0) for l in lums], grid.points, grid.normals,
                                caster=model.caster) @ w
    lux = direct + LUMINOUS_EFFICACY * (resp.gather.apply(B) @ LUMINANCE_WEIGHTS)
    np.testing.assert_allclose(resp.illuminance(w), lux, rtol=5e-5)
    assert H.shape == (cornell.n_patches,)
    # a lower wall reflectance: with_reflectance re-solves the same L columns
    darker = model.with_reflectance(cornell.reflectance * 0.5)
    lower = darker.sensors(grid, gather=resp.gather).illuminance(w)
    assert (lower <= resp.illuminance(w) + 1e-9).all() and lower.mean() < resp.illuminance(w).mean()


def test_grid_stats_csv_and_plan_image(tmp_path, cornell):
    grid = rectangle_grid((-1, 1), (-1, 1), 0.8, 0.25, name="plane")
    assert grid.shape == (8, 8) and len(grid) == 64 and grid.spacing == 0.25
    lux = np.linspace(100, 400, 64)
    st = grid_stats(lux)
    assert st["average"] == pytest.approx(250) and st["minimum"] == 100 and st["U0"] == pytest.approx(0.4)
    write_csv(tmp_path / "g.csv", grid, lux)
    rows = (tmp_path / "g.csv").read_text().splitlines()
    assert len(rows) == 65 and rows[0].startswith("grid,x,y,z") and float(rows[-1].split(",")[-1]) == 400
    save_plan(tmp_path / "g.png", grid, lux)
    from PIL import Image
    img = np.asarray(Image.open(tmp_path / "g.png"))
    assert img.shape[2] == 3 and img.shape[1] > img.shape[0] - 22     # plan plus a colour bar on its right
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50            # a ramp of colours, not one flat fill
    with pytest.raises(InputError, match="not a grid"):
        save_plan(tmp_path / "s.png", SensorSet("s", [[0, 0, 0]], [[0, 1, 0]]), [1.0])


def test_floor_grid_follows_an_l_shaped_outline():
    # an L: [0,2] x [0,1] plus [0,1] x [1,2] in plan (x, z), facing up
    V = np.array([(0, 0, 0), (0, 0, 1), (2, 0, 1), (2, 0, 0), (0, 0, 2), (1, 0, 2), (1, 0, 1)], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 6]])
    scene = Scene(V, F, np.zeros(4, int), (Material("floor", (0.3, 0.3, 0.3)),))
    g = floor_grid(scene, 0.8, 0.25)
    assert len(g) == 8 * 4 + 4 * 4                                    # 3 m^2 at 0.0625 m^2 a cell
    assert np.allclose(g.points[:, 1], 0.8)
    assert not ((g.points[:, 0] > 1) & (g.points[:, 2] > 1)).any()
    # a 0.25 m border zone follows the L: cells within 0.25 m of any wall, the inner corner's too, go
    inner = floor_grid(scene, 0.8, 0.25, margin=0.25)
    x, z = inner.points[:, 0], inner.points[:, 2]
    assert len(inner) > 0 and (x >= 0.25).all() and (z >= 0.25).all() and (x <= 1.75).all()
    assert not ((x > 0.75) & (z > 0.75)).any()                        # 0.25 m from the inner corner's walls
    with pytest.raises(InputError, match="not in the scene"):
        floor_grid(scene, 0.8, 0.25, material="carpet")


def test_sensor_file_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    s = SensorSet("pts", rng.normal(size=(17, 3)), rng.normal(size=(17, 3)))
    write_sensors(tmp_path / "pts.txt", s)
    back = read_sensors(tmp_path / "pts.txt")
    np.testing.assert_array_equal(back.points, s.points)
    np.testing.assert_array_equal(back.normals, s.normals)
    (tmp_path / "bad.txt").write_text("# header\n0 0 0 0 1 0\n\n1 2 3 0 1\n")
    with pytest.raises(FileFormatError, match="bad.txt:4: expected six"):
        read_sensors(tmp_path / "bad.txt")
    (tmp_path / "zero.txt").write_text("0 0 0 0 0 0\n")
    with pytest.raises(FileFormatError, match="zero.txt:1:.*zero"):
        read_sensors(tmp_path / "zero.txt")


def test_layout_file_defaults_paths_and_errors(tmp_path):
    ies = ("IESNA:LM-63-2002\n[TEST] t\nTILT=NONE\n1 1000 1 3 1 1 2 0 0 0\n1 1 20\n0 45 90\n0\n300 200 0\n")
    (tmp_path / "lamps").mkdir()
    (tmp_path / "lamps" / "d.ies").write_text(ies)
    layout = {"defaults": {"photometry": "lamps/d.ies", "max": 2.0},
              "luminaires": [{"name": "A", "position": [0, 2, 0]},
                             {"name": "B", "position": [1, 2, 0], "dimming": 0.5, "rotation": 45,
                              "color": [1, 0.5, 0.25]}]}
    (tmp_path / "layout.json").write_text(json.dumps(layout))
    lums = read_layout(tmp_path / "layout.json")
    assert [l.name for l in lums] == ["A", "B"] and lums[1].dimming == 0.5 and lums[0].max == 2.0
    assert lums[0].photometry is lums[1].photometry                    # read once
    assert float(lums[1].color @ LUMINANCE_WEIGHTS) == pytest.approx(1.0)
    with pytest.raises(LayoutError, match=r"luminaires\[1\]: no position"):
        parse_layout({"defaults": {"photometry": lums[0].photometry}, "luminaires": [{"position": [0, 0, 0]}, {}]})
    with pytest.raises(LayoutError, match=r"luminaires\[0\].aimm: unknown key"):
        parse_layout({"luminaires": [{"aimm": [0, -1, 0]}]})
    with pytest.raises(LayoutError, match="aim"):
        parse_layout({"luminaires": [{"photometry": lums[0].photometry, "position": [0, 0, 0], "aim": [0, 0, 0]}]})


_DOWNLIGHT_IES = """IESNA:LM-63-2002\r
[TEST] T-1\r
[LUMCAT] DL-1\r
TILT=NONE\r
1 2000 1.0 7 1 1 2 -0.1 -0.1 0.0\r
1.0 1.0 18\r
0 15 30 45 60 75 90\r
0\r
900 860 740 560 340 140 0\r
"""


def _layout(tmp_path) -> dict:
    (tmp_path / "dl.ies").write_text(_DOWNLIGHT_IES)
    lums = [{"name": f"L{i}", "position": [x, 1.95, z]}
            for i, (x, z) in enumerate([(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)])]
    return {"defaults": {"photometry": "dl.ies", "max": 2.0}, "luminaires": lums}


def test_design_lighting_meets_grid_goals_at_least_power(tmp_path, cornell):
    from hfrad.inverse.luminaires import design_lighting
    spec = {"luminaires": _layout(tmp_path),
            "grids": [{"name": "plane", "rectangle": [[-0.9, 0.9], [-0.9, 0.9]], "height": 1.3, "spacing": 0.2,
                       "mean": 150, "uniformity": 0.5}]}
    from hfrad.inverse.luminaires import parse_lighting_spec
    parsed = parse_lighting_spec(spec, cornell.scene, base=tmp_path)
    r = design_lighting(cornell, parsed)
    assert r.feasible, r.report["message"]
    a = r.report["grids"][0]["achieved"]
    assert a["average"] >= 150 * (1 - 1e-4) and a["U0"] >= 0.5 * (1 - 1e-4)
    v = r.report["verified"]
    assert v["goals_met"] and v["max_relative_deviation"] < 1e-3
    # least power: the average is binding (a uniform 1% cut of every dimming breaks it)
    lux = r.responses[0].illuminance(0.99 * r.dimming)
    assert lux.mean() < 150
    assert r.report["total_power_W"] == pytest.approx(18 * r.dimming.sum())
    # an impossible goal is reported, not raised
    spec["grids"][0]["mean"] = 1e6
    bad = design_lighting(cornell, parse_lighting_spec(spec, cornell.scene, base=tmp_path),
                          model=r.model, responses=r.responses)
    assert not bad.feasible and bad.report["conflicts"]


def test_cli_lux_and_design_with_luminaires(tmp_path, cornell):
    from tests.conftest import run_cli
    hfr = cornell.save(tmp_path / "box.hfr")
    (tmp_path / "layout.json").write_text(json.dumps(_layout(tmp_path)))
    sensors = SensorSet("pts", [[0, 0.5, 0], [0.3, 1.0, -0.2]], [[0, 1, 0], [0, 1, 0]])
    write_sensors(tmp_path / "pts.txt", sensors)
    res = run_cli("lux", hfr, "--layout", tmp_path / "layout.json", "--floor", "white", "--height", "1.3",
                  "--spacing", "0.25", "--sensors", tmp_path / "pts.txt", "-o", tmp_path / "lux.json",
                  "--csv", tmp_path / "lux.csv", "--plan", tmp_path / "plan.png", "--quiet")
    assert res.exit_code == 0, res.output
    out = json.loads((tmp_path / "lux.json").read_text())
    assert [g["name"] for g in out["grids"]] == ["workplane", "pts"] and out["grids"][0]["average"] > 0
    rows = (tmp_path / "lux.csv").read_text().splitlines()
    assert len(rows) == 1 + out["grids"][0]["sensors"] + 2
    assert (tmp_path / "plan.png").stat().st_size > 1000
    spec = {"luminaires": "layout.json", "grids": [{"name": "plane", "floor": "white", "height": 1.3,
                                                    "spacing": 0.25, "mean": 100, "uniformity": 0.4}]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    res = run_cli("design", tmp_path / "spec.json", hfr, "-o", tmp_path / "d.json", "--plan", tmp_path / "d.png",
                  "--quiet")
    assert res.exit_code == 0, res.output
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["feasible"] and d["grids"][0]["achieved"]["average"] >= 100 * (1 - 1e-4)
    spec["grids"][0]["spacing"] = -1
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    res = run_cli("design", tmp_path / "spec.json", hfr, "-o", tmp_path / "d.json", "--quiet")
    assert res.exit_code == 2 and "grids[0].spacing" in res.output


def test_layout_files_that_cannot_be_read_are_one_clear_error(tmp_path):
    """A layout nested 100,000 deep raised RecursionError (an internal error at the CLI); Latin-1 text a
    UnicodeDecodeError. Both are now LayoutError naming the file, as design specs are."""
    from hfrad.lighting.luminaire import read_layout

    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(LayoutError, match=r"deep.json: not valid JSON: JSON nested too deeply"):
        read_layout(deep)
    latin = tmp_path / "latin.toml"
    latin.write_bytes("name = 'Büro'".encode("latin-1"))
    with pytest.raises(LayoutError, match=r"latin.toml: not valid TOML"):
        read_layout(latin)
    with pytest.raises(FileNotFoundError, match="no such layout file"):
        read_layout(tmp_path / "missing.json")
