"""The reciprocity copy on Dask (hfrad.distributed.tiles): group-pair tiles computed once, used by both groups.

Checked against things we did not write: the blocks F[:, J_j] that the engine computes whole (every
pair), reciprocity A_i F_ij = A_j F_ji, the count of pairs by formula, and the Dask run without the copy.
"""

from __future__ import annotations

import numpy as np
import pytest

from hfrad import DaskBackend, PrecomputeOptions
from hfrad.distributed import connect, tiles
from hfrad.distributed.run import make_job
from hfrad.distributed.tasks import _block, group_block, tile_task
from hfrad.formfactors.parallel import column_block
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene
from hfrad.precompute.options import plan_precompute

EPS = 0.02
NEAR = 32


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell", patches=600)


@pytest.mark.parametrize("n, b, g, band", [(512, 64, 2, 3), (612, 64, 2, 4), (612, 64, 3, 1), (600, 50, 4, 0)])
def test_pairs_computed_by_formula(n, b, g, band):
    """Every pair is computed once or copied from a computed one; a full band halves the pairs (plus
    half the diagonal cells): (g b)^2 G (G - 1) / 2 + sum_J diagonal_pairs(J) when b g divides n."""
    plan = tiles.TilePlan(n=n, block_size=b, group=g, band=band)
    G = plan.groups
    covered = np.zeros((n, n), np.int64)       # times each pair (row, col) is computed, copies counted apart
    copied = np.zeros((n, n), bool)
    for J in range(G):
        cols = plan.rows(J)
        covered[plan.own_rows(J), cols] += 1
        calls = []                        # the diagonal tile: computed cells and their copies
        D = tiles.diagonal_tile(plan, J, np.ones(n), lambda r, c: calls.append((r, c)) or np.ones((r.stop - r.start,
                                                                                               c.stop - c.start)))
        for r, c in calls:
            covered[r, c] += 1
            copied[c, r] = r != c
        assert D.shape == (cols.stop - cols.start,) * 2
        direct, copies = plan.partners(J)
        for K in copies:
            copied[plan.rows(K), cols] = True
    for I, J in plan.tiles():
        covered[plan.rows(I), plan.rows(J)] += 1
    assert covered.sum() == plan.pairs_computed()
    assert np.array_equal(covered + copied, np.ones((n, n), np.int64))     # each pair exactly once
    assert np.array_equal(copied.T & copied, np.zeros_like(copied))           # a copy's source is computed
    if band == G - 1 and n % (g * b) == 0:
        cell = b // tiles.DIAGONAL_CUTS        # the diagonal tile: (w^2 + sum of cells^2) / 2
        assert plan.pairs_computed() == (g * b) ** 2 * G * (G - 1) // 2 + G * ((g * b) ** 2 + g * b * cell) // 2
    if band == 0:
        assert not plan.tiles() and plan.pairs_computed() == n * n - sum(
            (plan.rows(J).stop - plan.rows(J).start) ** 2 - plan.diagonal_pairs(J) for J in range(G))


def test_band_fits_the_budget():
    """The band grows with the budget, never beyond G - 1, and its waiting tiles fit the budget."""
    G, w, s, W = 40, 512, 4, 4
    tile = w * w * s
    bands = [tiles.band_for(G, w, s, W, budget) for budget in (0, tile, 10 * tile, 100 * tile, 10**6 * tile)]
    assert bands == sorted(bands) and bands[0] == 0 and bands[-1] == G - 1
    for budget, band in zip((tile, 10 * tile, 100 * tile), bands[1:4]):
        assert tiles.tile_bytes_per_worker(G, band, w, s, W) <= budget
        assert tiles.tile_bytes_per_worker(G, band + 1, w, s, W) > budget
    # (resident / W + 2 band) tiles: 2 tiles per band step at least
    assert tiles.tile_bytes_per_worker(G, 3, w, s, W) == (tiles.resident_tiles(G, 3, W) / W + 6) * tile
    # the default group keeps the tile tasks per leaf bounded (full band)
    for m in (16, 160, 645, 3907):
        g = tiles.default_group(m, m * 256, 256, 4)
        G = -(-m // g)
        assert G * (G - 1) / 2 <= tiles.TILE_TASKS_PER_LEAF * m or (2 * g * 256) ** 2 * 4 > tiles.TILE_BYTES
        assert g * 256 >= tiles.MIN_GROUP_COLUMNS
        assert g * 256 == tiles.MIN_GROUP_COLUMNS or \
            (-(-m // (g // 2))) * (-(-m // (g // 2)) - 1) / 2 > tiles.TILE_TASKS_PER_LEAF * m


@pytest.mark.parametrize("dtype, tol", [("float64", 1e-15), pytest.param("float32", 2e-7, marks=pytest.mark.slow)])
def test_copied_blocks_equal_computed_blocks(dtype, tol):
    """Each block assembled from its own rows and the tiles (direct and transposed, area-scaled) equals
    the block the engine computes whole: the computed and direct rows bit for bit, the copied rows to
    rounding (observed: float64 2.7e-16 of the block's largest entry, 1.0e-15 entry by entry, from the
    reciprocity of the kernel and visibility; float32 9.6e-8, one float32 rounding more)."""
    scene = load_scene("cornell", patches=300)     # 5 groups of 2 blocks of 32
    options = plan_precompute(scene, EPS, dtype=dtype, options=PrecomputeOptions(block_size=32))
    job = make_job(scene, options, None, "test")
    plan = tiles.TilePlan(n=options.n, block_size=32, group=2, band=2)
    made = {(I, J): tile_task(job, plan, I, J) for I, J in plan.tiles()}
    areas = np.asarray(scene.areas, np.float64)[job.perm]
    worst = 0.0
    for J in range(plan.groups):
        direct, copies = plan.partners(J)
        own = plan.own_rows(J)
        diag = tiles.diagonal_tile(plan, J, areas, lambda r, c: _block(job, r, c))
        for j in plan.blocks_of(J):
            F = group_block(job, plan, J, j, own, areas, {I: made[(I, J)] for I in direct},
                            {K: made[(J, K)] for K in copies}, diag)
            whole = column_block(scene, job.perm[j * 32:(j + 1) * 32], order=job.perm, samples=job.samples,
                                 ray_budget=job.ray_budget, dtype=dtype)
            assert F.dtype == whole.dtype
            exact = np.zeros(plan.n, bool)
            exact[own] = True
            for I in direct:
                exact[plan.rows(I)] = True
            assert np.array_equal(F[exact], whole[exact])
            worst = max(worst, float(np.abs(F.astype(np.float64) - whole).max() / np.abs(whole).max()))
    assert 0 < worst <= tol


@pytest.mark.slow
def test_dask_copy_equals_dask_without_and_local(cornell):
    """Two in-process workers: the run with the copy computes about half the pairs and gives the
    factorization of the run without it (same rank, error figures to 1e-5, radiosity to 1e-5) and of the
    local path (which copies other rows: its own mirror). Merges whole, as the local path's (the panelled
    merges round differently: test_distributed.py compares those)."""
    from hfrad.distributed import DaskTuning, factorize_distributed

    scene = cornell
    n = scene.n_patches
    with connect(workers=2, processes=False) as cluster:
        records = []
        runs = [factorize_distributed(scene, plan_precompute(scene, EPS, near_field=NEAR, reciprocity=r,
                                                             options=PrecomputeOptions(block_size=64)),
                                      DaskBackend(scheduler=cluster, records=records if r else None),
                                      tuning=DaskTuning(panel_leaves=10**9, tile_group=2))    # 5 groups of 2 blocks
                for r in (True, False)]
    copy, plain = runs
    local = factorize(scene, eps=EPS, near_field=NEAR, options=PrecomputeOptions(block_size=64))
    info = copy.lowrank.info
    assert plain.lowrank.info["pairs_computed"] == n * n and plain.lowrank.info["tile_tasks"] == 0
    plan = tiles.TilePlan(n=n, block_size=64, group=info["tile_group"], band=info["tile_band"])
    assert info["tile_band"] == plan.groups - 1        # the budget holds every tile at this size
    assert info["pairs_computed"] == plan.pairs_computed()
    # half the pairs, plus half of the diagonal cells (b / DIAGONAL_CUTS wide): ~ 1/2 + cell / (2 n)
    assert info["pairs_computed"] / n**2 == pytest.approx(0.5 + 64 / tiles.DIAGONAL_CUTS / (2 * n), rel=0.02)
    assert info["tile_tasks"] == len(plan.tiles()) == sum(1 for r in records if r["kind"] == "tile")
    assert copy.params["reciprocity"] is True
    for other in (plain, local):
        assert copy.rank == other.rank
        assert copy.relative_error == pytest.approx(other.relative_error, rel=1e-5)
        assert np.allclose(copy.error_estimate().bound, other.error_estimate().bound, rtol=1e-3)
        B, B_other = copy.solve(scene.emission), other.solve(scene.emission)
        diff = np.linalg.norm(B - B_other, axis=0) / np.linalg.norm(B_other, axis=0)
        # float32 blocks: a copied entry is one float32 rounding off the computed one; observed ~1e-6
        assert (diff <= 1e-5).all(), diff


@pytest.mark.slow
def test_resume_with_the_copy(cornell, tmp_path):
    """A run with the copy stopped after a few leaves resumes from its checkpoint: resumed groups are not
    recomputed, their partners compute those rows themselves, and the result is the uninterrupted one."""
    scene = cornell
    folder = tmp_path / "run.parts"
    m = -(-scene.n_patches // 64)

    def stop_after_four(done, total):
        if done >= 4:
            raise KeyboardInterrupt

    with connect(workers=1, processes=False) as cluster:
        whole = factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=cluster),
                          options=PrecomputeOptions(block_size=64))
        with pytest.raises(KeyboardInterrupt):
            factorize(scene, eps=EPS, near_field=NEAR, progress=stop_after_four,
                      backend=DaskBackend(scheduler=cluster), checkpoint=folder,
                      options=PrecomputeOptions(block_size=64))
        assert any(folder.glob("node-*.sha256"))
        resumed = factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=cluster),
                            checkpoint=folder, options=PrecomputeOptions(block_size=64))
    info = resumed.lowrank.info
    assert info["tasks_resumed"] >= 1 and info["tasks_run"] < 2 * m - 1
    assert info["pairs_computed"] < whole.lowrank.info["pairs_computed"]
    assert resumed.rank == whole.rank
    assert resumed.relative_error == pytest.approx(whole.relative_error, rel=1e-5)
    B, B_whole = resumed.solve(scene.emission), whole.solve(scene.emission)
    diff = np.linalg.norm(B - B_whole, axis=0) / np.linalg.norm(B_whole, axis=0)
    assert (diff <= 1e-5).all(), diff
