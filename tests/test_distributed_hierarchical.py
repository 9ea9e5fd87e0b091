"""far_field="hierarchical" on Dask: the workers build the H-matrix's parts; the same blocks, the same answers."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

import hfrad
from hfrad import Checkpoint, DaskBackend
from hfrad.distributed import connect
from hfrad.distributed import hierarchical as dask_hierarchical
from hfrad.errors import AccuracyWarning
from hfrad.formfactors.bfloat16 import value_dtype
from hfrad.formfactors.engine import FormFactorEngine
from hfrad.formfactors.hmatrix import (HMatrixOptions, build_hmatrix, build_part, hmatrix_pairs, join_blocks,
                                       join_parts, split_into_parts)

EPS = 0.05
#: The build's counters that a split into parts must not change.
COUNTERS = ("far_blocks", "visible_blocks", "blocked_blocks", "mixed_blocks", "probed_blocks", "kernel_pairs",
            "exact_pairs", "blocked_pairs", "probe_rays", "near_pairs", "blocks", "storage_floats", "lowrank_blocks")


@pytest.fixture(scope="module")
def scene():
    return hfrad.load_scene("cornell", patches=600)


def _factorize(scene, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AccuracyWarning)
        return hfrad.factorize(scene, EPS, far_field="hierarchical", near_field=120, **kw)


@pytest.mark.parametrize("values", ["float32", "bfloat16"])
def test_parts_join_to_the_in_process_hmatrix(scene, values):
    """A block depends on its own node pair alone (hashed rays, its own cross approximation): any split of
    the pairs into parts, each built apart, joins to the in-process H-matrix entry for entry (its values
    float32 or bfloat16 alike); parts holding different kinds of values are refused."""
    options = HMatrixOptions(values=values)
    engine = FormFactorEngine(scene)
    try:
        whole = build_hmatrix(scene, engine, options)
        pairs = hmatrix_pairs(scene, options)
        built = [build_part(scene, engine, part, options) for part in split_into_parts(pairs, 5)]
        other = build_part(scene, engine, split_into_parts(pairs, 5)[0],
                           options.replace(values="bfloat16" if values == "float32" else "float32"))[0]
    finally:
        engine.close()
    with pytest.raises(ValueError, match="different dtypes"):
        join_blocks([other, copy.deepcopy(built[1][0])])
    joined = join_parts(pairs, [b for b, _ in built], [i for _, i in built], options, 0.0)
    assert joined.blocks.U.dtype == whole.blocks.U.dtype == value_dtype(values)
    assert np.array_equal(joined.to_dense(), whole.to_dense())
    assert {k: joined.info[k] for k in COUNTERS} == {k: whole.info[k] for k in COUNTERS}
    # near pairs split by their lower node: a pair and its mirror in one part
    lows = [set(np.minimum(part.near_r, part.near_c).tolist()) for part in split_into_parts(pairs, 5)]
    assert sum(len(low) for low in lows) == len(set().union(*lows))


def test_dask_build_gives_the_local_factorization(scene):
    """DaskBackend: the workers build the parts, the client factors; the same H-matrix counters, rank and
    certificate as in this process, radiosity equal to the products' rounding (their order of blocks)."""
    local = _factorize(scene)
    seen = []
    with connect(workers=2, processes=False) as cluster:
        dist = _factorize(scene, backend=DaskBackend(scheduler=cluster),
                          progress=lambda done, total: seen.append((done, total)))
    h, h_local = dist.lowrank.info["hierarchical"], local.lowrank.info["hierarchical"]
    assert {k: h[k] for k in COUNTERS} == {k: h_local[k] for k in COUNTERS}
    assert h["parts"] == 2 * dask_hierarchical.PARTS_PER_WORKER and (h["parts"], h["parts"]) in seen
    assert dist.params["backend"] == "dask" and dist.params["workers"] == 2 and local.params["backend"] == "local"
    assert dist.rank == local.rank
    assert h["certificate"]["error_estimate"] == pytest.approx(h_local["certificate"]["error_estimate"], rel=1e-4)
    B, B_local = dist.solve(scene.emission), local.solve(scene.emission)
    diff = np.linalg.norm(B - B_local, axis=0) / np.linalg.norm(B_local, axis=0)
    assert (diff <= 5e-6).all(), diff          # observed 6.2e-7 (1.3e-6 at 1,508 patches)


def test_dask_checkpoint_folder_resumes_without_the_cluster_build(scene, tmp_path, monkeypatch):
    """A Dask run's checkpoint names a folder: the built H-matrix is its one file, and a rerun loads it
    instead of building (the cluster is not asked for any part); deleted on completion unless kept."""
    folder = tmp_path / "run.partial.d"
    with connect(workers=1, processes=False) as cluster:
        first = _factorize(scene, backend=DaskBackend(scheduler=cluster),
                           checkpoint=Checkpoint(folder, interval=0, keep=True))
        assert (folder / dask_hierarchical.HMATRIX_FILE).is_file()

        def no_build(*args, **kwargs):
            raise AssertionError("the H-matrix was built again")

        monkeypatch.setattr(dask_hierarchical, "_build_on", no_build)
        statuses = []
        again = _factorize(scene, backend=DaskBackend(scheduler=cluster), status=statuses.append,
                           checkpoint=Checkpoint(folder, interval=0))
    assert any(s.get("resumed") for s in statuses)
    assert again.rank == first.rank
    assert np.array_equal(again.solve(scene.emission), first.solve(scene.emission))
    assert not folder.exists()
