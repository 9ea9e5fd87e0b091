"""Plans a designer can read (hfrad.lighting.plan): luminaires, desks, the grid's extent and metre ticks."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.lighting import Luminaire, Photometry, plan_image, rectangle_grid
from hfrad.lighting.plan import DESK_COLOR, LEFT, LUMINAIRE_COLOR, TOP, PlanFrame, extent, tick_step
from hfrad.scene.scene import Material, Scene


def _photometry(size):
    v = np.arange(0.0, 90.5, 0.5)
    return Photometry("C", [0.0], v, (1000 * np.cos(np.radians(v)))[None, :], size=size, name="test")


def _desk_scene():
    # a floor at y = 0 over [0, 4] x [0, 3] and a desk top at y = 0.75 over [1, 2] x [1, 1.6], facing up
    V = np.array([(0, 0, 0), (0, 0, 3), (4, 0, 3), (4, 0, 0),
                  (1, 0.75, 1), (1, 0.75, 1.6), (2, 0.75, 1.6), (2, 0.75, 1)], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return Scene(V, F, np.array([0, 0, 1, 1]), (Material("floor", (0.3,) * 3), Material("desk", (0.5,) * 3)))


def _frame_of(grid, luminaires, desks):
    """The frame plan_image uses (its pixel mapping), rebuilt from the same pieces."""
    ppc = max(4, min(40, 480 // max(grid.shape)))
    x0, z0 = grid.origin
    rect = (x0, z0, x0 + grid.shape[0] * grid.spacing, z0 + grid.shape[1] * grid.spacing)
    box = extent(rect, luminaires, desks)
    return PlanFrame(box[0], box[1], grid.spacing / ppc, LEFT, 36 + TOP), rect


def test_luminaires_desks_extent_and_ticks_are_drawn():
    from hfrad.lighting.plan import desk_outlines

    grid = rectangle_grid((0.5, 3.5), (0.5, 2.5), 0.8, 0.25, name="plane")
    lums = [Luminaire(_photometry((0.6, 0.6, 0.0)), np.array([1.0, 2.7, 1.0]), name="panel"),
            Luminaire(_photometry((-0.15, 0.0, 0.0)), np.array([3.0, 2.7, 2.0]), name="down")]
    scene = _desk_scene()
    lux = np.linspace(100, 500, len(grid))
    img = plan_image(grid, lux, luminaires=lums, scene=scene)
    bare = plan_image(grid, lux)
    frame, rect = _frame_of(grid, lums, desk_outlines(scene, 0.8))
    magenta = (img == LUMINAIRE_COLOR).all(axis=2)
    assert not (bare == LUMINAIRE_COLOR).all(axis=2).any()
    for lum in lums:                                              # a dot of the marker colour at each position
        c, r = (int(round(v)) for v in frame.pixel(lum.position[0], lum.position[2]))
        assert magenta[r - 1:r + 2, c - 1:c + 2].all(), lum.name
    # the panel's 0.6 m outline: marker colour 0.3 m either side of its centre, on the centre row
    c, r = frame.pixel([0.7, 1.3], [1.0, 1.0])
    for cc in c:
        assert magenta[int(round(r[0])), int(round(cc)) - 1:int(round(cc)) + 2].any()
    # the desk top's outline (only on the picture with the scene), its corners at (1, 1) and (2, 1.6) m
    grey = (img == DESK_COLOR).all(axis=2)
    cs, rs = frame.pixel([1.5, 1.5, 1.0], [1.0, 1.6, 1.3])
    bare_grey = (bare == DESK_COLOR).all(axis=2)
    for cc, rr in zip(cs, rs):
        near = np.s_[int(round(rr)) - 1:int(round(rr)) + 2, int(round(cc)) - 1:int(round(cc)) + 2]
        assert grey[near].any() and not bare_grey[near].any()
    # the grid's extent in white, and metre ticks (grey) left of the plan at whole metres
    white = (img == 255).all(axis=2)
    (c0, c1), (r0, r1) = frame.pixel([rect[0], rect[2]], [rect[1], rect[3]])
    assert white[int(round(r0)), int(c0) + 5:int(c1) - 5].mean() > 0.9
    step = tick_step(max(rect[2] - rect[0], rect[3] - rect[1]) + 0.5)
    assert step == 0.5
    _, rt = frame.pixel(0.0, 1.0)
    assert (img[int(round(rt)), LEFT - 4:LEFT] == 200).all()


def test_tick_steps():
    assert [tick_step(s) for s in (1.0, 5.0, 12.0, 30.0, 100.0)] == [0.1, 0.5, 1.0, 5.0, 10.0]
    with pytest.raises(Exception):
        plan_image(rectangle_grid((0, 1), (0, 1), 0.8, 0.5), np.ones(3))


def test_a_luminaire_that_is_off_gets_a_hollow_ring():
    grid = rectangle_grid((0.5, 3.5), (0.5, 2.5), 0.8, 0.25, name="plane")
    on = Luminaire(_photometry((0.0, 0.0, 0.0)), np.array([1.0, 2.7, 1.0]), name="a")
    lums = [on, on.replace(position=np.array([3.0, 2.7, 2.0]), name="b", dimming=0.0)]
    img = plan_image(grid, np.full(len(grid), 300.0), luminaires=lums)
    frame, _ = _frame_of(grid, lums, [])
    magenta = (img == LUMINAIRE_COLOR).all(axis=2)
    (ca, cb), (ra, rb) = (np.rint(v).astype(int) for v in frame.pixel([1.0, 3.0], [1.0, 2.0]))
    assert magenta[ra, ca] and not magenta[rb, cb]          # a dot where on, hollow where off
    assert magenta[rb - 3:rb + 4, cb - 3:cb + 4].sum() >= 8   # the ring


def test_the_next_rooms_luminaires_and_desks_stay_off_the_plan():
    grid = rectangle_grid((0.5, 3.5), (0.5, 2.5), 0.8, 0.25, name="plane")
    here = Luminaire(_photometry((0.6, 0.6, 0.0)), np.array([1.0, 2.7, 1.0]), name="here")
    there = here.replace(position=np.array([8.0, 2.7, 1.0]), name="there")     # 4.5 m past the grid
    lux = np.full(len(grid), 300.0)
    both = plan_image(grid, lux, luminaires=[here, there])
    alone = plan_image(grid, lux, luminaires=[here])
    assert both.shape == alone.shape                       # the plan does not stretch to the far one
    assert (both == LUMINAIRE_COLOR).all(axis=2).sum() == (alone == LUMINAIRE_COLOR).all(axis=2).sum()
