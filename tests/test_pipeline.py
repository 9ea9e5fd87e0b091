"""The whole precomputation: scene -> form factors -> HF -> Woodbury, against exact answers."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import Interrupt, interrupt_at

from hfrad import Checkpoint, PrecomputeOptions
from hfrad import factorize, factorize_matrix
from hfrad.formfactors import form_factor_matrix
from hfrad.scene.load import load_scene
from hfrad.scene.zorder import patch_order


@pytest.fixture(scope="module")
def cornell():
    """A ~1,500-patch Cornell box, its dense F and the exact radiosity (LAPACK solve per channel)."""
    scene = load_scene("cornell", patches=1500)
    F = form_factor_matrix(scene)
    n = scene.n_patches
    exact = np.stack([np.linalg.solve(np.eye(n) - scene.reflectance[:, c, None] * F, scene.emission[:, c])
                      for c in range(3)], axis=1)
    return scene, F, exact


def _relative_error(B, exact):
    return np.linalg.norm(B - exact, axis=0) / np.linalg.norm(exact, axis=0)


def test_furnace_through_the_pipeline():
    scene = load_scene("furnace", max_edge=0.2)
    fac = factorize(scene, eps=0.02, options=PrecomputeOptions(block_size=64))
    B = fac.solve(scene.emission)
    rho = scene.reflectance[0, 0]
    assert np.allclose(B, scene.emission / (1 - rho), rtol=0.01)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_cornell_error_and_its_figures(cornell, dtype):
    scene, F, exact = cornell
    fac = factorize(scene, eps=0.02, dtype=dtype, options=PrecomputeOptions(block_size=128))
    assert fac.relative_error <= 0.02
    B = fac.solve(scene.emission)
    err = _relative_error(B, exact)
    w = np.sqrt(scene.areas)[:, None]
    err_a = np.linalg.norm(w * (B - exact), axis=0) / np.linalg.norm(w * exact, axis=0)
    figure = fac.residual(scene.emission, B, form_factors=F)
    print(f"\n{dtype}: n={fac.n_patches} rank={fac.rank} achieved={fac.relative_error:.4f} "
          f"radiosity error={err} area-norm error={err_a} residual bound={figure.bound} "
          f"a-priori bound={fac.error_bound()}")
    assert (err < 6e-3).all(), err                                     # observed 1.7-1.9e-3
    assert (err_a <= fac.error_bound()).all()                            # guaranteed, loose
    assert (err_a <= figure.bound).all() and (figure.bound < 10 * err_a).all()   # guaranteed, ~5x


def test_out_of_core_equals_in_core(cornell):
    scene, F, exact = cornell
    perm = patch_order(scene.centroids, "zorder")
    # one_ray_tol=0: every pair gets all its rays, so the streamed F is the dense F exactly
    streamed = factorize(scene, eps=0.02, dtype="float64",
                         options=PrecomputeOptions(block_size=128, one_ray_tol=0))
    in_core = factorize_matrix(F, scene.reflectance, eps=0.02, block_size=128, dtype=np.float64, order=perm)
    assert streamed.rank == in_core.rank
    B1, B2 = streamed.solve(scene.emission), in_core.solve(scene.emission)
    assert np.allclose(B1, B2, rtol=1e-8, atol=1e-10 * np.abs(B2).max())


def test_order_changes_speed_not_answer(cornell):
    scene, F, exact = cornell
    for order in ("random", "hilbert"):
        fac = factorize(scene, eps=0.02, order=order, options=PrecomputeOptions(block_size=128))
        err = _relative_error(fac.solve(scene.emission), exact)
        assert (err < 6e-3).all(), (order, err)                        # observed 1.6-2.0e-3


def test_checkpoint_resumes_without_redoing_blocks(tmp_path):
    scene = load_scene("cornell", patches=600)
    full = factorize(scene, eps=0.02, dtype="float64", options=PrecomputeOptions(block_size=64))
    ckpt = tmp_path / "run.partial"
    stop_after_four = interrupt_at(4)

    with pytest.raises(Interrupt):
        factorize(scene, eps=0.02, dtype="float64", status=stop_after_four,
                  checkpoint=Checkpoint(ckpt, interval=0.0), options=PrecomputeOptions(block_size=64))
    assert ckpt.exists()
    pushed = []
    resumed = factorize(scene, eps=0.02, dtype="float64", status=lambda info: pushed.append(info["blocks"]),
                        checkpoint=ckpt, options=PrecomputeOptions(block_size=64))
    n_blocks = -(-scene.n_patches // 64)
    assert pushed == list(range(4, n_blocks + 1))  # the checkpoint held 3 blocks (saved before the 4th)
    assert not ckpt.exists()
    assert resumed.rank == full.rank
    assert np.allclose(resumed.solve(scene.emission), full.solve(scene.emission), rtol=1e-10)
    # a checkpoint from other parameters is refused, not silently mixed in
    with pytest.raises(Interrupt):
        factorize(scene, eps=0.02, dtype="float64", status=stop_after_four,
                  checkpoint=Checkpoint(ckpt, interval=0.0), options=PrecomputeOptions(block_size=64))
    with pytest.raises(ValueError, match="another scene or other parameters"):
        factorize(scene, eps=0.05, dtype="float64", checkpoint=ckpt, options=PrecomputeOptions(block_size=64))


@pytest.mark.parametrize("kwargs, match", [
    ({"eps": 0.0}, "eps must be in"),
    ({"eps": 1.0}, "eps must be in"),
    ({"options": PrecomputeOptions(block_size=10_000)}, "block size"),
    ({"dtype": "int8"}, "dtype"),
    ({"order": "spiral"}, "order must be one of"),
])
def test_bad_arguments(kwargs, match):
    scene = load_scene("furnace")
    with pytest.raises(ValueError, match=match):
        factorize(scene, **kwargs)


def test_checkpoints_cost_a_bounded_share_of_the_run(tmp_path, monkeypatch):
    """A checkpoint that is slow to write is written less often (at most ~1/CHECKPOINT_COST_RATIO of the time)."""
    import time

    import hfrad.precompute.local as local

    writes = []

    def slow_save(stream, path, key=""):
        time.sleep(0.05)
        writes.append(stream.blocks_done)

    monkeypatch.setattr(local, "save_checkpoint", slow_save)
    scene = load_scene("cornell", patches=600)
    kw = dict(eps=0.05, dtype="float64", options=PrecomputeOptions(block_size=32))
    t = time.perf_counter()
    factorize(scene, checkpoint=Checkpoint(tmp_path / "run.partial", interval=1e-9), **kw)
    seconds = time.perf_counter() - t
    n_blocks = -(-scene.n_patches // 32)
    # one write per 50 x 0.05 s = 2.5 s of run at most (the first comes after the first block)
    assert 1 <= len(writes) <= 1 + seconds / (local.CHECKPOINT_COST_RATIO * 0.05)
    writes.clear()
    factorize(scene, checkpoint=Checkpoint(tmp_path / "run.partial", interval=0.0), **kw)        # 0: after every block but the last
    assert writes == list(range(1, n_blocks))
