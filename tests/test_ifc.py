"""IFC building models (hfrad.scene.ifc, hfrad.lighting.spaces): a two-room storey made with
ifcopenshell.api, its materials and element kinds, IfcSpace work planes, and the same illuminance as
the same triangles read from an OBJ file."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("ifcopenshell", reason="IFC tests need ifcopenshell (pip install 'hfrad[buildings]')")

import hfrad  # noqa: E402
from hfrad.errors import InputError, SceneError  # noqa: E402
from hfrad.lighting import LightingModel, parse_layout  # noqa: E402
from hfrad.lighting.spaces import space_grids  # noqa: E402
from ifc_building import CEILING, WALL, build_building  # noqa: E402

IES = "examples/office/luminaires/downlight-150.ies"
ROOM = (4.0, 3.0)
HEIGHT = 2.8


@pytest.fixture(scope="module")
def storey(tmp_path_factory):
    """The two-room storey: walls, slab, ceilings, two windows, a door, a desk per room, two spaces."""
    return build_building(tmp_path_factory.mktemp("ifc") / "storey.ifc", rooms=(2, 1), room=ROOM, height=HEIGHT,
                          desks=1)


@pytest.fixture(scope="module")
def scene(storey):
    return hfrad.load_scene(storey)


def test_materials_come_from_styles_or_listed_class_defaults(scene):
    mats = {m.name: m for m in scene.materials}
    assert mats["Wall paint"].reflectance == pytest.approx((0.6,) * 3)          # the model's surface style
    assert mats["Glazing"].transmittance == pytest.approx((0.8,) * 3)          # transparency 0.8: a window
    assert mats["Glazing"].reflectance == pytest.approx((0.08,) * 3)
    assert mats["floor"].reflectance == (0.2,) * 3 and mats["ceiling"].reflectance == (0.7,) * 3
    assert mats["door"].reflectance == (0.4,) * 3
    assert mats["Desk"].reflectance == pytest.approx((0.45, 0.4, 0.35))
    listed = " ".join(scene.warnings)
    for name, classes in [("floor", "IfcSlab"), ("ceiling", "IfcCovering"), ("door", "IfcDoor")]:
        assert f"'{name}'" in listed and classes in listed


def test_every_class_default_when_the_model_has_no_style(tmp_path):
    plain = hfrad.load_scene(build_building(tmp_path / "plain.ifc", rooms=(1, 1), desks=1, styles=False))
    mats = {m.name: m for m in plain.materials}
    assert set(mats) == {"wall", "floor", "ceiling", "window", "furniture"}
    assert [mats[k].reflectance[0] for k in ("wall", "floor", "ceiling", "furniture")] == [0.5, 0.2, 0.7, 0.4]
    assert mats["window"].transmittance == (0.78,) * 3 and mats["window"].reflectance == (0.08,) * 3
    listed = [w for w in plain.warnings if w.startswith("no surface style")]
    assert len(listed) == 5 and any("IfcFurniture faces use the hfrad default 'furniture'" in w for w in listed)


def test_element_kinds_and_geometry(scene):
    groups = [scene.groups[g] for g in np.unique(scene.group)]
    for cls, count in [("IfcWall", 5), ("IfcWindow", 2), ("IfcDoor", 1), ("IfcSlab", 1), ("IfcCovering", 2),
                       ("IfcFurniture", 2)]:
        assert sum(cls in g for g in groups) == count, cls
    assert not any("IfcSpace" in g or "IfcOpeningElement" in g for g in groups)
    # y-up: the storey stands on y = 0 (the slab below it) and is HEIGHT + CEILING tall
    lo, hi = scene.bounds
    assert lo[1] == pytest.approx(-0.2) and hi[1] == pytest.approx(HEIGHT + CEILING)
    # the windows (1.5 x 1.2 m, two sides each) are glazing facing north and south (z in hfrad's frame)
    glazing = scene.material == scene.material_names.index("Glazing")
    big = glazing & (scene.areas > 0.1)
    assert scene.areas[big].sum() == pytest.approx(2 * 2 * 1.5 * 1.2, rel=1e-9)
    assert np.allclose(np.abs(scene.normals[big][:, 2]), 1.0)
    # the floor is the slab's top (the coverings are all ceiling: their tops are no floor)
    floor = scene.material == scene.material_names.index("floor")
    assert scene.areas[floor].sum() == pytest.approx((2 * ROOM[0] + 3 * WALL) * (ROOM[1] + 2 * WALL), rel=1e-9)
    ceiling = scene.material == scene.material_names.index("ceiling")
    ceiling_area = 2 * ROOM[0] * ROOM[1] * 2 + 2 * (ROOM[0] + ROOM[1]) * 2 * CEILING   # two coverings + the slab's
    assert scene.areas[ceiling].sum() == pytest.approx(ceiling_area + (2 * ROOM[0] + 3 * WALL) * (ROOM[1] + 2 * WALL),
                                                       rel=1e-9)
    # the openings are cut: the south wall lost two windows' area on each side
    south = [k for k, g in enumerate(scene.groups) if "Wall S0" in g][0]
    length = 2 * ROOM[0] + 3 * WALL
    sides = (scene.group == south) & (np.abs(scene.normals[:, 2]) > 0.99)
    assert scene.areas[sides].sum() == pytest.approx(2 * (length * HEIGHT - 2 * 1.5 * 1.2), rel=1e-9)


def test_info_lists_windows_and_defaults(storey):
    from typer.testing import CliRunner

    from hfrad.cli import app

    out = CliRunner().invoke(app, ["info", str(storey), "--json"])
    assert out.exit_code == 0, out.output
    summary = json.loads(out.output)
    assert summary["glazing"]["materials"] == ["Glazing"] and summary["glazing"]["treatment"]
    assert any("hfrad default 'door'" in w for w in summary["warnings"])


def test_space_grids_follow_each_room(storey, scene):
    grids = space_grids(storey, spacing=0.25, scene=scene)
    assert [g.name for g in grids] == ["Room 0.0.0", "Room 0.1.0"]
    for g, x0 in zip(grids, (WALL, 2 * WALL + ROOM[0])):
        assert len(g) == 16 * 12                                  # 4 m / 0.25 by 3 m / 0.25
        assert np.allclose(g.points[:, 1], 0.8)                   # 0.8 m above the floor (y = 0)
        assert g.points[:, 0].min() == pytest.approx(x0 + 0.125) and g.points[:, 0].max() == pytest.approx(x0 + 3.875)
        assert np.allclose(g.normals, [0, 1, 0])
    coarse = space_grids(storey, spacing=0.5, height=0.75, margin=0.5, scene=scene)
    assert len(coarse[0]) == 6 * 4 and np.allclose(coarse[0].points[:, 1], 0.75)


def test_space_grids_refused_when_they_cannot_apply(tmp_path, storey, scene):
    small = hfrad.load_scene(storey, unit_scale=0.5)
    with pytest.raises(InputError, match="unit-scale"):
        space_grids(storey, scene=small)
    empty = build_building(tmp_path / "none.ifc", rooms=(1, 1))
    import ifcopenshell

    f = ifcopenshell.open(str(empty))
    for space in f.by_type("IfcSpace"):
        f.remove(space)
    f.write(str(tmp_path / "nospace.ifc"))
    with pytest.raises(InputError, match="no IfcSpace"):
        space_grids(tmp_path / "nospace.ifc")


def test_not_an_ifc_file_is_refused_in_one_line(tmp_path):
    bad = tmp_path / "bad.ifc"
    bad.write_text("ISO-10303-21;\nthis is not a model\n")
    with pytest.raises(SceneError, match="bad.ifc: not a readable IFC file"):
        hfrad.load_scene(bad)


def _write_obj(scene, folder):
    """The scene's triangles as OBJ + MTL (y-up already: no turn), written independently of hfrad."""
    lines = ["mtllib same.mtl"]
    lines += [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in scene.vertices]
    for k, f in enumerate(scene.faces):
        lines += [f"usemtl m{scene.material[k]}", f"f {f[0] + 1} {f[1] + 1} {f[2] + 1}"]
    (folder / "same.obj").write_text("\n".join(lines) + "\n")
    (folder / "same.mtl").write_text("".join(f"newmtl m{k}\nKd {' '.join(repr(float(x)) for x in m.reflectance)}\n"
                                             for k, m in enumerate(scene.materials)))
    return folder / "same.obj"


def test_ifc_and_the_same_geometry_as_obj_give_the_same_lux(tmp_path, storey, scene):
    import os

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    layout = parse_layout({"luminaires": [
        {"name": f"down_{i}", "photometry": os.path.join(root, IES),
         "position": [WALL + i * (ROOM[0] + WALL) + ROOM[0] / 2, HEIGHT - 0.01, -(WALL + ROOM[1] / 2)]}
        for i in range(2)]}, base=tmp_path)
    obj = hfrad.load_scene(_write_obj(scene, tmp_path))
    assert obj.n_patches == scene.n_patches
    grids = space_grids(storey, spacing=0.5, scene=scene)
    lux = []
    for s in (scene, obj):
        model = LightingModel(hfrad.factorize(s, eps=0.02), layout)
        lux.append(np.concatenate([model.sensors(g).illuminance(model.dimming) for g in grids]))
    assert lux[0].min() > 20                                     # lit: a downlight per room
    np.testing.assert_allclose(lux[0], lux[1], rtol=1e-9)
    # the two rooms mirror each other about the door wall: the same light, to the factorization's accuracy
    a, b = lux[0][:len(grids[0])], lux[0][len(grids[0]):]
    assert a.mean() == pytest.approx(b.mean(), rel=0.02)


def test_design_spec_grid_of_a_space(storey, scene):
    from hfrad.inverse.luminaires import SpecError, parse_lighting_spec

    spec = {"luminaires": {"luminaires": [{"name": "d", "photometry": IES, "position": [2.2, 2.79, -1.7]}]},
            "grids": [{"space": "Room 0.1.0", "height": 0.8, "spacing": 0.5, "mean": 300}]}
    parsed = parse_lighting_spec(spec, scene, base=".")
    assert len(parsed.grids[0].sensors) == 8 * 6
    spec["grids"][0]["space"] = "Attic"
    with pytest.raises(SpecError, match="no IfcSpace named 'Attic'.*Room 0.0.0, Room 0.1.0"):
        parse_lighting_spec(spec, scene, base=".")


def test_lux_cli_lays_the_space_grids_without_a_layout_of_grids(tmp_path, storey):
    import os

    from typer.testing import CliRunner

    from hfrad.cli import app

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"luminaires": [{"name": "d", "photometry": os.path.join(root, IES),
                                                  "position": [2.2, 2.79, -1.7]}]}))
    hfr = tmp_path / "storey.hfr"
    run = CliRunner().invoke(app, ["precompute", str(storey), "--eps", "0.05", "-o", str(hfr), "-q"])
    assert run.exit_code == 0, run.output
    out = tmp_path / "lux.json"
    run = CliRunner().invoke(app, ["lux", str(hfr), "--layout", str(layout), "--spacing", "0.5", "-o", str(out), "-q"])
    assert run.exit_code == 0, run.output
    grids = json.loads(out.read_text())["grids"]
    assert [g["name"] for g in grids] == ["Room 0.0.0", "Room 0.1.0"]
    assert grids[0]["sensors"] == 48 and grids[0]["average"] > 5 * grids[1]["average"]   # the lit room, the door shut


def test_enormous_models_are_refused_before_the_geometry(storey, monkeypatch):
    import hfrad.scene.ifc as ifc

    monkeypatch.setattr(ifc, "MAX_ELEMENTS", 10)
    with pytest.raises(SceneError, match=r"storey.ifc: \d+ building elements; hfrad reads at most 10"):
        hfrad.load_scene(storey)
    monkeypatch.setattr(ifc, "MAX_ELEMENTS", 10**6)
    monkeypatch.setattr(ifc, "MAX_TRIANGLES", 20)
    with pytest.raises(SceneError, match=r"more than 20 triangles \(at #\d+ Ifc"):
        hfrad.load_scene(storey)


def test_an_element_without_geometry_is_named_by_its_entity_id(tmp_path, storey):
    import ifcopenshell
    import ifcopenshell.api.root

    f = ifcopenshell.open(str(storey))
    wall = f.by_type("IfcWall")[0]
    ghost = ifcopenshell.api.root.create_entity(f, ifc_class="IfcWall", name="Ghost")
    rep = f.createIfcProductDefinitionShape(None, None, [f.createIfcShapeRepresentation(
        wall.Representation.Representations[0].ContextOfItems, "Body", "SweptSolid", [])])
    ghost.Representation = rep
    f.write(str(tmp_path / "ghost.ifc"))
    scene = hfrad.load_scene(tmp_path / "ghost.ifc")
    assert any(f"#{ghost.id()} IfcWall 'Ghost'" in w and "no geometry" in w for w in scene.warnings)


def test_a_moved_ifc_file_is_named_when_its_spaces_are_wanted(tmp_path, scene):
    from hfrad.lighting.spaces import scene_ifc

    moved = scene.replace(name=str(tmp_path / "gone.ifc"))
    assert scene_ifc(moved) is None
    with pytest.raises(InputError, match="gone.ifc, which is not found from here: give --spaces"):
        scene_ifc(moved, strict=True)
    assert scene_ifc(scene.replace(name="room.obj"), strict=True) is None
