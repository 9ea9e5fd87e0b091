"""Column blocks, dense assembly, memory limit, on-disk cache, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from hfrad.errors import MemoryLimitError
from hfrad.formfactors import (BlockCache, CacheMismatchError, check_dense_memory, form_factor_matrix,
                               iter_column_blocks, row_sums)
from hfrad.scene.builtin import cornell_box
from hfrad.scene.patches import subdivide
from hfrad.scene.zorder import zorder_permutation


@pytest.fixture(scope="module")
def scene():
    return subdivide(cornell_box(), patches=300)


@pytest.fixture(scope="module")
def dense(scene):
    return form_factor_matrix(scene)


@pytest.mark.parametrize("kind", ["zorder", "random", "identity"])
def test_blocks_equal_the_permuted_dense_matrix(scene, dense, kind):
    n = scene.n_patches
    order = {"zorder": zorder_permutation(scene.centroids),
             "random": np.random.default_rng(0).permutation(n), "identity": None}[kind]
    perm = np.arange(n) if order is None else order
    seen = 0
    for start, stop, block in iter_column_blocks(scene, 64, order=order):
        assert block.shape == (n, stop - start)
        # the rows of earlier blocks are reciprocity copies A_j F_ji / A_i of pairs the dense matrix
        # computed as F_ij: equal to rounding (observed at most 6.1e-16 relative)
        np.testing.assert_allclose(block, dense[np.ix_(perm, perm[start:stop])], rtol=4e-15, atol=0)
        seen = stop
    assert seen == n


def test_float32_and_row_sums(scene, dense):
    F32 = form_factor_matrix(scene, dtype=np.float32)
    assert F32.dtype == np.float32
    np.testing.assert_allclose(F32, dense, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(row_sums(scene, block_size=100), dense.sum(axis=1), rtol=1e-12)


def test_memory_limit(scene):
    with pytest.raises(MemoryLimitError, match="iter_column_blocks"):
        form_factor_matrix(scene, max_bytes=1000)
    with pytest.raises(MemoryLimitError, match="hfrad precompute"):
        check_dense_memory(10 ** 8)


def test_bad_order(scene):
    with pytest.raises(ValueError, match="permutation"):
        next(iter_column_blocks(scene, order=np.zeros(scene.n_patches, int)))


def test_cache_round_trip_resume_and_mismatch(scene, dense, tmp_path):
    path = tmp_path / "ff.h5"
    order = zorder_permutation(scene.centroids)
    want = dense[np.ix_(order, order)]
    # interrupted run: two blocks, then the consumer stops
    gen = iter_column_blocks(scene, 64, order=order, cache=path)
    next(gen), next(gen)
    gen.close()
    assert not path.exists() and (tmp_path / "ff.h5.partial").exists()
    # resume: the stored blocks are read back, the rest computed, then renamed
    got = np.concatenate([b for _, _, b in iter_column_blocks(scene, 64, order=order, cache=path)], axis=1)
    # the resumed pass copies rows only from the blocks it computed: equal to the dense matrix to rounding
    np.testing.assert_allclose(got, want, rtol=4e-15, atol=0)
    assert path.exists() and not (tmp_path / "ff.h5.partial").exists()
    # complete cache: read without computing (engine untouched)
    from hfrad.formfactors.blocks import FormFactorEngine
    eng = FormFactorEngine(scene)
    again = np.concatenate([b for _, _, b in iter_column_blocks(scene, 64, order=order, cache=path,
                                                                engine=eng)], axis=1)
    np.testing.assert_array_equal(again, got)       # the cache holds what the pass gave, bit for bit
    assert eng.pairs == 0
    # mismatch: other parameters or another scene
    with pytest.raises(CacheMismatchError, match="samples"):
        next(iter_column_blocks(scene, 64, order=order, samples=1, cache=path))
    with pytest.raises(CacheMismatchError, match="scene_sha256"):
        next(iter_column_blocks(subdivide(cornell_box(), patches=200), 64, cache=BlockCache(path)))


def test_corrupt_partial_cache_is_discarded(scene, dense, tmp_path):
    path = tmp_path / "ff.h5"
    (tmp_path / "ff.h5.partial").write_bytes(b"not hdf5")
    with pytest.warns(UserWarning, match="discarding"):
        got = np.concatenate([b for _, _, b in iter_column_blocks(scene, 128, cache=path)], axis=1)
    np.testing.assert_allclose(got, dense, rtol=4e-15, atol=0)     # reciprocity copies: to rounding


def test_cli_writes_npz(tmp_path):
    import typer  # hard dependencies and hfrad's own modules are imported, never skipped
    from typer.testing import CliRunner

    from hfrad.cli import formfactors
    app = typer.Typer()
    formfactors.register(app)
    app.command("noop")(lambda: None)  # two commands keep the subcommand name
    out = tmp_path / "F.npz"
    res = CliRunner().invoke(app, ["formfactors", "cornell", "-o", str(out), "--patches", "200", "--quiet"])
    assert res.exit_code == 0, res.output
    data = np.load(out)
    n = len(data["area"])
    assert data["F"].shape == (n, n) and data["centroid"].shape == (n, 3) and data["normal"].shape == (n, 3)
    assert list(data["material_names"]) == ["white", "red", "green", "light"]
    assert data["material"].max() < 4
