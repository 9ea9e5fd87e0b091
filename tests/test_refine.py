"""Refinement where radiosity changes fast: conforming red-green splits (issue 11)."""

from __future__ import annotations

import numpy as np
import pytest

import hfrad
from conftest import run_cli
from hfrad.errors import InputError
from hfrad.scene.builtin import cornell_box, parallel_plates
from hfrad.scene.patches import subdivide
from hfrad.scene.refine import marks_from_radiosity, refine_patches
from hfrad.solve.refine import refine_by_radiosity
from test_conform import _edges, _t_junctions


@pytest.fixture(scope="module")
def coarse():
    return subdivide(cornell_box(), patches=400)


def test_red_green_split_stays_conforming(coarse):
    marked = np.random.default_rng(0).random(coarse.n_patches) < 0.15
    fine = refine_patches(coarse, marked)
    _, count = _edges(fine)
    assert (count == 2).all() and _t_junctions(fine) == 0  # the box stays closed, no T-junction
    for k in range(len(coarse.materials)):
        a0, a1 = coarse.areas[coarse.material == k].sum(), fine.areas[fine.material == k].sum()
        assert abs(a1 - a0) <= 1e-12 * a0 * fine.n_patches
    # each marked patch became 4, each neighbour 1, 2 (green) or 4 (red by closure)
    assert fine.n_patches >= coarse.n_patches + 3 * marked.sum()
    assert (fine.areas > 0).all()
    # orientation kept: every child faces the way its input face does
    base = cornell_box()
    assert ((fine.normals * base.normals[fine.parent]).sum(axis=1) > 1 - 1e-9).all()


def test_marks_follow_a_jump_only():
    s = subdivide(parallel_plates(1, 1, 1), max_edge=0.2)
    x = s.centroids[:, 0]
    B = np.where(x < 0.5, 10.0, 1.0)  # a step at x = 0.5 on both plates
    marked = marks_from_radiosity(s, B, 0.3)
    assert marked.any()
    # every marked patch touches the line x = 0.5 (within a patch size)
    assert np.abs(x[marked] - 0.5).max() < 0.2
    assert not marks_from_radiosity(s, np.ones(s.n_patches), 0.3).any()
    with pytest.raises(InputError, match="threshold"):
        marks_from_radiosity(s, B, 0.0)


def test_coarse_solve_refines_shadows_and_contact_lines():
    coarse = subdivide(cornell_box(), patches=300)
    fine, marked = refine_by_radiosity(coarse, 0.3)
    assert 0 < marked < coarse.n_patches
    _, count = _edges(fine)
    assert (count == 2).all()
    floor = coarse.groups.index("floor")
    # the floor (block shadows and contact lines) gains more than its share of new patches
    gain = np.bincount(fine.group, minlength=len(fine.groups)) / np.bincount(coarse.group, minlength=len(coarse.groups))
    assert gain[floor] > fine.n_patches / coarse.n_patches


def test_precompute_refine_option(tmp_path):
    path = tmp_path / "r.hfr"
    result = run_cli("precompute", "cornell", "--patches", "150", "--refine", "0.3", "--eps", "0.1", "-o", path)
    assert result.exit_code == 0, result.output
    assert "refined:" in result.output
    assert hfrad.load(path).n_patches > 150
    bad = run_cli("precompute", "cornell", "--patches", "150", "--refine", "-1", "-o", tmp_path / "b.hfr")
    assert bad.exit_code == 2 and "threshold" in bad.output
