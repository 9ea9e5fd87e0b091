"""Duplicate, overlapping and face-to-face faces (issue 10 item 2, issue 46 item 3): found,
merged or cut to one layer, reported."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hfrad.formfactors import form_factor_matrix
from hfrad.scene.cleanup import find_face_problems, merge_duplicates, resolve_overlaps
from hfrad.scene.load import load_scene

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/scenes is absent (only in the developers' checkout)")

# A closed unit cube (12 triangles, inward normals) plus broken copies of its floor:
# face 13 repeats face 1 rotated, face 14 repeats face 2 through separate but equal vertices
# (welding), face 15 is face 1 reversed (touches it face to face), face 16 overlaps the
# floor half-way (coplanar overlap, same orientation).
CUBE = """mtllib m.mtl
v 0 0 0
v 1 0 0
v 1 0 1
v 0 0 1
v 0 1 0
v 1 1 0
v 1 1 1
v 0 1 1
v 1 0 1
v 0 0 1
v 0.5 0 0
v 0.5 0 1
usemtl floor
f 1 4 3
f 1 3 2
usemtl wall
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 4 8 7
f 4 7 3
f 1 5 8
f 1 8 4
f 2 3 7
f 2 7 6
usemtl floor
f 4 3 1
f 1 9 2
usemtl wall
f 1 3 4
usemtl floor
f 11 12 9
"""


@pytest.fixture
def cube_obj(tmp_path: Path) -> Path:
    (tmp_path / "m.mtl").write_text("newmtl floor\nKd 0.5 0.5 0.5\nnewmtl wall\nKd 0.5 0.5 0.5\nKe 1 1 1\n")
    path = tmp_path / "cube.obj"
    path.write_text(CUBE)
    return path


def test_duplicates_overlaps_and_facing_are_found(cube_obj):
    raw = load_scene(cube_obj, keep_duplicates=True)
    report = find_face_problems(raw)
    assert report.duplicates.tolist() == [[0, 12], [1, 13]]  # rotated copy; copy through equal positions
    assert report.facing.tolist() == [[0, 14], [14, 15]]  # the reversed copy touches face 1 and the half-floor
    assert report.overlaps.tolist() == [[0, 15], [1, 15]]  # the half-floor overlaps both floor triangles
    summary = report.summary(raw)
    assert summary["duplicates"]["materials"] == ["floor"]
    assert summary["facing"]["materials"] == ["floor", "wall"]


def test_duplicates_are_merged_with_a_warning(cube_obj):
    s = load_scene(cube_obj)
    assert s.n_patches == 16 - 2 - 1  # and the half-floor, covered wholly by the floor, dropped
    assert any(w.startswith("merged 2 duplicate faces") and "floor" in w for w in s.warnings)
    assert any("2 pairs of coplanar faces overlap" in w and "dropped 1 covered wholly" in w for w in s.warnings)
    assert not len(find_face_problems(s).overlaps)
    assert any("2 pairs of faces touch face to face" in w for w in s.warnings)
    kept = load_scene(cube_obj, keep_duplicates=True)
    assert kept.n_patches == 16 and any(w.startswith("kept 2 duplicate") for w in kept.warnings)
    assert any("counted twice (--keep-duplicates)" in w for w in kept.warnings)
    # a clean scene passes untouched (same object, no warning)
    clean = load_scene("cornell")
    assert merge_duplicates(clean) is clean


def test_merged_cube_rows_sum_to_one(cube_obj, tmp_path):
    text = "\n".join(line for line in CUBE.splitlines() if line not in ("f 1 3 4", "f 11 12 9"))
    (tmp_path / "dup.obj").write_text(text + "\n")
    merged = load_scene(tmp_path / "dup.obj", max_edge=0.5)
    sums = form_factor_matrix(merged).sum(axis=1)
    assert np.abs(sums - 1).max() < 0.03
    doubled = load_scene(tmp_path / "dup.obj", max_edge=0.5, keep_duplicates=True)
    assert form_factor_matrix(doubled).sum(axis=1).max() > 1.3  # the floor counted twice


def _floor_twice(tmp_path: Path, other: str) -> Path:
    """The closed cube with its floor laid a second time as ``other`` faces (coplanar, same side)."""
    text = "\n".join(line for line in CUBE.splitlines() if line not in ("f 1 3 4", "f 11 12 9", "f 4 3 1", "f 1 9 2"))
    (tmp_path / "m.mtl").write_text("newmtl floor\nKd 0.5 0.5 0.5\nnewmtl wall\nKd 0.5 0.5 0.5\nKe 1 1 1\n")
    path = tmp_path / "twice.obj"
    path.write_text(text + "\n" + other + "\n")
    return path


def test_overlapping_floor_cut_to_one_layer_exact_areas(tmp_path):
    # a second floor (the square's other diagonal) and a triangle of area 0.5 from x = 0.5 to 1.5,
    # a quarter of it (0.125) past the square's edge: the union is 1.125 m^2
    path = _floor_twice(tmp_path, "v 1.5 0 0.5\nusemtl floor\nf 1 4 2\nf 2 4 3\nf 11 12 13")
    raw = load_scene(path, keep_duplicates=True)
    report = find_face_problems(raw)
    assert len(report.overlaps) >= 4 and not len(report.duplicates)
    cut, counts = resolve_overlaps(raw, report.overlaps)
    floor = cut.material == cut.material_index("floor")
    assert cut.areas[floor].sum() == pytest.approx(1.0 + 0.125, abs=1e-12)
    assert not len(find_face_problems(cut).overlaps)
    assert counts["dropped"] == 2 and counts["cut"] == 1  # the square's copies go, the triangle keeps its outside part
    assert (cut.normals[floor] @ np.array([0.0, 1.0, 0.0]) > 0.999).all()  # orientation kept
    assert cut.total_area == pytest.approx(raw.total_area - 1.0 - 0.375, abs=1e-12)


def test_floor_laid_twice_rows_sum_to_one(tmp_path):
    # the same floor triangulated along the other diagonal: no duplicate, two overlapping layers
    path = _floor_twice(tmp_path, "usemtl floor\nf 1 4 2\nf 2 4 3")
    resolved = load_scene(path, max_edge=0.5)
    sums = form_factor_matrix(resolved).sum(axis=1)
    assert np.abs(sums - 1).max() < 0.03
    layered = load_scene(path, max_edge=0.5, keep_duplicates=True)
    assert form_factor_matrix(layered).sum(axis=1).max() > 1.3  # the floor counted twice


@needs_shared
def test_public_scenes_have_one_layer_after_loading():
    for name in ("sibenik/sibenik.obj", "sponza-dabrovic/sponza.obj"):
        raw = load_scene(SHARED / name, keep_duplicates=True, allow_missing_materials=True)
        s = load_scene(SHARED / name, allow_missing_materials=True)
        assert len(find_face_problems(raw).overlaps) > 100, name
        assert not len(find_face_problems(s).overlaps), name
        # cutting keeps the union: the area lost is at most the overlapping faces' own area
        assert 0 < raw.total_area - s.total_area < 0.05 * raw.total_area, name
        assert any("resolved, each overlap kept once" in w for w in s.warnings), name


def test_info_reports_faces_and_flag(cube_obj):
    from typer.testing import CliRunner

    from hfrad.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["info", str(cube_obj), "--json"])
    assert result.exit_code == 0, result.output
    faces = json.loads(result.output)["face_problems"]
    assert (faces["duplicates"]["count"], faces["overlaps"]["count"], faces["facing"]["count"]) == (2, 2, 2)
    assert faces["merged"] is True
    kept = json.loads(runner.invoke(app, ["info", str(cube_obj), "--json", "--keep-duplicates"]).output)
    assert kept["patches"] == 16 and kept["face_problems"]["merged"] is False
    assert faces["overlaps"]["resolved"] == {"cut": 0, "dropped": 1, "pieces": 0}  # the half-floor
    assert "resolved" not in kept["face_problems"]["overlaps"]
    text = " ".join(runner.invoke(app, ["info", str(cube_obj)]).output.split())  # unwrapped
    assert "2 duplicates (merged)" in text and "2 coplanar overlapping pairs (cut 0 faces, dropped 1)" in text


@needs_shared
def test_mcguire_cornell_duplicates_merged():
    path = SHARED / "cornell-box" / "CornellBox-Original.obj"
    s = load_scene(path, patches=800)
    assert any("merged 4 duplicate faces" in w and "shortBox" in w and "tallBox" in w for w in s.warnings)
    sums = form_factor_matrix(s).sum(axis=1)
    # the box is not quite closed (the light hangs 1 cm under the ceiling), so rows may fall
    # short of 1, but no row may exceed it: with the duplicates kept they reach 1.45
    assert sums.max() < 1.02
    doubled = load_scene(path, patches=800, keep_duplicates=True)
    assert form_factor_matrix(doubled).sum(axis=1).max() > 1.3


def test_energy_warning_names_the_cause_left_after_cleaning():
    from hfrad.formfactors.energy import energy_problems
    from hfrad.scene.builtin import cornell_box
    from hfrad.scene.cluster import cluster
    from hfrad.scene.patches import subdivide

    plain = cornell_box()
    sums = np.ones(plain.n_patches)
    sums[0] = 1.2
    (message,) = energy_problems(plain, sums)
    assert "--keep-duplicates" in message and "cut through each other" in message
    clustered = cluster(subdivide(cornell_box(), patches=400), patches=100)
    sums = np.ones(clustered.n_patches)
    sums[3] = 1.2
    (message,) = energy_problems(clustered, sums)
    assert "curved cluster" in message and f"{clustered.non_flatness.max():.2f} from flat" in message


def test_is_closed_counts_every_edge_twice():
    """A mesh is closed when every edge has exactly two faces: a box and a sphere are, a cut box
    (a hole), a box with a face repeated (an edge of three faces) or two coincident boxes are not;
    two separate boxes are."""
    import trimesh
    from types import SimpleNamespace

    from hfrad.formfactors.energy import is_closed

    box = np.asarray(trimesh.creation.box().faces)
    sphere = np.asarray(trimesh.creation.icosphere(2).faces)
    cut = np.asarray(trimesh.creation.box().slice_plane([0, 0, 0], [0, 0, 1]).faces)
    closed = [box, sphere, np.vstack([box, box + 8])]
    open_ = [cut, np.vstack([box, box[:1]]), np.vstack([box, box]), np.zeros((0, 3), int)]
    assert [is_closed(SimpleNamespace(occluder_faces=f)) for f in closed] == [True] * 3
    assert [is_closed(SimpleNamespace(occluder_faces=f)) for f in open_] == [False] * 4
