"""Multi-process form factors and the one-ray rule for pairs that cannot matter."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hfrad.formfactors import form_factor_matrix, iter_column_blocks
from hfrad.formfactors.blocks import make_engine
from hfrad.formfactors.budget import FEW_RAYS_FACTOR, REFINE_FACTOR, one_ray_threshold, ray_budget
from hfrad.formfactors.parallel import ProcessEngine, column_block
from hfrad.formfactors.budget import RayBudget
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation


@pytest.fixture(scope="module")
def scene():
    return subdivide(cornell_box(), patches=700)


def _blocks(scene, processes, budget=None, dtype=np.float32):
    order = zorder_permutation(scene.centroids)
    out = [b for _, _, b in iter_column_blocks(scene, 96, order=order, dtype=dtype, processes=processes,
                                               ray_budget=budget)]
    return order, np.concatenate(out, axis=1)


def test_processes_give_the_same_blocks_as_one_process(scene):
    thr = ray_budget(scene, 0.02)
    assert 0 < thr.one_ray_below < thr.few_rays_below
    order, single = _blocks(scene, 1, thr)
    _, multi = _blocks(scene, 2, thr)
    np.testing.assert_array_equal(multi, single)
    # and the plain function the Dask backend calls, in this process
    cols = order[96:192]
    # which computes every row; the pass copies the rows of earlier blocks by reciprocity, in float32
    # here: equal to a float32 rounding (observed 1.2e-7 relative)
    np.testing.assert_allclose(column_block(scene, cols, order=order, ray_budget=thr), single[:, 96:192],
                               rtol=2.5e-7, atol=0)


def test_process_engine_counts_rays_and_pairs(scene):
    order = zorder_permutation(scene.centroids)
    engine = make_engine(scene, processes=2, block_size=128)
    assert isinstance(engine, ProcessEngine)
    blocks = list(engine.iter_blocks(order, [order[:128], order[128:200]]))
    assert [b.shape for b in blocks] == [(scene.n_patches, 128), (scene.n_patches, 72)]
    assert engine.pairs == scene.n_patches * 200 and engine.rays > 0
    # lent blocks: one array reused for the pass, the same numbers while each is lent
    lent = engine.iter_blocks(order, [order[:128], order[128:200]], lend=True)
    first = next(lent)
    np.testing.assert_array_equal(first, blocks[0])
    second = next(lent)
    np.testing.assert_array_equal(second, blocks[1])
    assert np.shares_memory(first, second)       # the first is gone once the next is asked for
    lent.close()
    np.testing.assert_array_equal(second, blocks[1])   # still readable after the pass ended


def test_one_ray_rule_stays_within_its_share(scene):
    dense = form_factor_matrix(scene)
    tol = 0.05
    thr = one_ray_threshold(scene, tol)
    assert thr > 0
    _, few = _blocks(scene, 1, RayBudget(one_ray_below=thr), dtype=np.float64)
    order = zorder_permutation(scene.centroids)
    exact = dense[np.ix_(order, order)]
    diff = np.linalg.norm(few - exact) / np.linalg.norm(exact)
    assert 0 < diff <= tol  # bound: every changed entry moves by at most F_ij
    # reciprocity survives: the rule is decided on A_i F_ij = A_j F_ji
    a = scene.areas[order][:, None] * few
    np.testing.assert_allclose(a, a.T, rtol=1e-12, atol=1e-18)


def test_few_rays_rule_stays_within_its_share(scene):
    """Flagged pairs below few_rays_below get 4 rays, not 16: fewer rays, F within the rule's share."""
    tol = 0.01
    budget = ray_budget(scene, tol)
    only_few = RayBudget(few_rays_below=budget.few_rays_below)
    order = zorder_permutation(scene.centroids)
    counts = {}
    blocks = {}
    for label, b in (("all", None), ("few", only_few)):
        engine = make_engine(scene, ray_budget=b)
        blocks[label] = np.concatenate([F for F in engine.iter_blocks(order, [order[:350], order[350:]])], axis=1)
        counts[label] = engine.rays
        engine.close()
    assert counts["few"] < 0.97 * counts["all"]  # observed 0.951
    diff = np.linalg.norm(blocks["few"] - blocks["all"]) / np.linalg.norm(blocks["all"])
    # the pairs below the threshold hold FEW_RAYS_FACTOR * tol of ||F||_F and each moves by at most
    # F_ij (the bound); 4 rays instead of 16 move them far less
    print(f"few-rays rule: {counts['few'] / counts['all']:.3f} of the rays, F moved {diff:.2e}")
    # observed 1.1e-3 (conference room, 20K patches: ~0.1 of the share too)
    assert 0 < diff <= 0.1 * FEW_RAYS_FACTOR * tol, diff
    a = scene.areas[order][:, None] * blocks["few"]
    np.testing.assert_allclose(a, a.T, rtol=1e-12, atol=1e-18)


def test_second_round_rules_stay_within_their_share(scene):
    """Pairs below refine_below get no second visibility round, those below large_below 64 rays
    instead of 256: fewer rays, F within the rules' share, the closed box's rows still close."""
    tol = 0.01   # the one-ray share at eps 0.04
    full = ray_budget(scene, tol)
    assert full.few_rays_below < full.refine_below < full.large_below
    order = zorder_permutation(scene.centroids)
    blocks, rays = {}, {}
    for label, b in (("first rules", dataclasses.replace(full, refine_below=0.0, large_below=0.0)), ("all", full)):
        engine = make_engine(scene, ray_budget=b)
        blocks[label] = np.concatenate([F for F in engine.iter_blocks(order, [order[:350], order[350:]])], axis=1)
        rays[label] = engine.rays
        engine.close()
    share = rays["all"] / rays["first rules"]
    diff = np.linalg.norm(blocks["all"] - blocks["first rules"]) / np.linalg.norm(blocks["first rules"])
    worst = {k: np.abs(F.sum(axis=1) - 1).max() for k, F in blocks.items()}
    print(f"second-round rules: {share:.3f} of the rays, F moved {diff:.2e}, worst rows {worst}")
    assert share < 0.92   # observed 0.843
    # the pairs below refine_below hold REFINE_FACTOR * tol of ||F||_F, and each moves by at most F_ij;
    # observed 1.8e-3, ~0.02 of that bound
    assert 0 < diff <= 0.1 * REFINE_FACTOR * tol, diff
    # rows of the closed box (area light included) sum to 1 with every second round, and still do
    assert worst["all"] < worst["first rules"] + 1e-3, worst   # observed 4.26e-3 against 4.18e-3
    a = scene.areas[order][:, None] * blocks["all"]
    np.testing.assert_allclose(a, a.T, rtol=1e-12, atol=1e-18)


def test_bad_process_count(scene):
    with pytest.raises(ValueError, match="processes"):
        make_engine(scene, processes=0)


def test_a_script_without_main_guard_fails_clearly(tmp_path):
    """Spawned workers re-run an unguarded script and die: the parent raises WorkerError, not hang."""
    import subprocess
    import sys
    from pathlib import Path

    import hfrad

    script = tmp_path / "unguarded.py"
    script.write_text("from hfrad.scene.load import load_scene\n"
                      "from hfrad.pipeline import LocalBackend, factorize\n"
                      "factorize(load_scene('cornell', patches=200), eps=0.1, backend=LocalBackend(processes=2))\n")
    src = str(Path(hfrad.__file__).resolve().parents[1])
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=240,
                         env={**__import__("os").environ, "PYTHONPATH": src})
    assert run.returncode != 0
    assert "WorkerError" in run.stderr and "__main__" in run.stderr, run.stderr[-2000:]
