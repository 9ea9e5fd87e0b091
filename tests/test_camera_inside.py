"""The inside view (issue 46 item 2): a camera within a building's largest enclosed space."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.render import Camera
from hfrad.render.raycast import trace_camera
from hfrad.scene.scene import Material, Scene

HALL = np.array([10.0, 3.0, 4.0])  # a long hall: x is its length


def _box(size: np.ndarray, *, open_top: bool = False) -> Scene:
    """An axis-aligned box [0, size] of 12 triangles facing inwards (no top when ``open_top``)."""
    import trimesh

    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation(size / 2)
    faces = np.asarray(mesh.faces)[:, ::-1]  # trimesh faces outwards; a room faces in
    if open_top:
        tri = np.asarray(mesh.vertices)[faces]
        faces = faces[~np.isclose(tri[:, :, 1], size[1]).all(axis=1)]
    return Scene(vertices=np.asarray(mesh.vertices, float), faces=faces, material=np.zeros(len(faces), int),
                 materials=(Material("wall", (0.5, 0.5, 0.5)),))


def test_inside_view_stands_in_the_hall_and_looks_down_its_length():
    hall = _box(HALL)
    assert np.einsum("pd,pd->p", hall.normals, HALL / 2 - hall.centroids).min() > 0  # faces in
    cam = Camera.inside(hall)
    p, t = np.array(cam.position), np.array(cam.target)
    assert (p > 0).all() and (p < HALL).all() and (t > 0).all() and (t < HALL).all()
    forward = (t - p) / np.linalg.norm(t - p)
    assert abs(forward[0]) > 0.9  # along the 10 m length, not across the 4 m width or up the 3 m height
    # every pixel sees a wall (nothing escapes from inside a closed room)
    face, _, _ = trace_camera(hall, cam, 64, 48)
    assert (face >= 0).all()
    # the spec it prints reads back as the same camera
    again = Camera.parse(cam.spec(), hall.bounds)
    np.testing.assert_allclose(again.position, cam.position, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(again.target, cam.target, rtol=1e-3, atol=1e-3)
    assert again.fov == cam.fov
    assert Camera.parse("inside", hall.bounds, scene=hall) == cam


def test_open_scene_has_no_inside_and_inside_falls_back_to_auto():
    floor = Scene(vertices=np.array([[0.0, 0, 0], [0, 0, 1], [1, 0, 1], [1, 0, 0]]),
                  faces=np.array([[0, 1, 2], [0, 2, 3]]), material=np.zeros(2, int),
                  materials=(Material("floor", (0.5, 0.5, 0.5)),))
    assert Camera.inside(floor) is None
    assert Camera.parse("inside", floor.bounds, scene=floor) == Camera.auto(floor.bounds)
    # a hall without a ceiling is still a room from low down (the opening is a small solid angle there)
    cam = Camera.inside(_box(HALL, open_top=True))
    assert cam is not None and (np.array(cam.position) < HALL).all() and (np.array(cam.position) > 0).all()


def test_info_prints_a_camera_to_paste():
    from typer.testing import CliRunner

    from hfrad.cli import app

    result = CliRunner().invoke(app, ["info", "cornell", "--json"])
    assert result.exit_code == 0, result.output
    import json

    spec = json.loads(result.output)["camera_inside"]
    cam = Camera.parse(spec, np.zeros((2, 3)))
    assert (np.abs(np.array(cam.position)[[0, 2]]) < 1).all() and 0 < cam.position[1] < 2  # inside the 2 m box
    with pytest.raises(Exception):
        Camera.parse("inside-out", np.zeros((2, 3)))


def test_first_view_goes_inside_a_building_but_not_into_the_cornell_box():
    from hfrad.scene.builtin import cornell_box

    box = cornell_box()  # one-sided walls facing in: the three-quarter view sees in through their backs
    assert Camera.first_view(box) == Camera.auto(box.bounds)
    assert Camera.parse("auto", box.bounds, scene=box) == Camera.auto(box.bounds)
    # a building: the hall's walls plus an outer shell 0.3 m away facing out, which hides the inside
    hall = _box(HALL)
    shell = _box(HALL + 0.6)
    vertices = np.vstack([hall.vertices, shell.vertices - 0.3])
    faces = np.vstack([hall.faces, shell.faces[:, ::-1] + len(hall.vertices)])
    building = Scene(vertices=vertices, faces=faces, material=np.zeros(len(faces), int), materials=hall.materials)
    cam = Camera.first_view(building)
    assert cam != Camera.auto(building.bounds) and cam == Camera.inside(building)
    assert ((np.array(cam.position) > 0) & (np.array(cam.position) < HALL)).all()
