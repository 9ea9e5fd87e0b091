"""The Dask backend: the same factorization and .hfr as the local path, on LocalClusters, despite a killed
worker or a lost client."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from hfrad import Checkpoint, DaskBackend, LocalBackend, PrecomputeOptions
from hfrad.distributed import SchedulerUnreachableError, connect
from hfrad.distributed import tasks
from hfrad.distributed.run import task_order
from hfrad.distributed.tasks import Job
from hfrad.lowrank.hf import HFStream, counter_tree
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene
from hfrad.precompute.assemble import far_block
from hfrad.solve.stats import PassStatistics

EPS = 0.02
NEAR = 32        # near field forced on at this size ("auto" turns it on from 2,000 patches)


@pytest.fixture(scope="module")
def cornell():
    """A 600-patch Cornell box and its local (in-process, streaming) factorization with the near field."""
    scene = load_scene("cornell", patches=600)
    # reciprocity=False: every pair computed; the Dask runs below copy by group-pair tiles
    # (hfrad.distributed.tiles) unless told not to: the same F to rounding
    return scene, factorize(scene, eps=EPS, near_field=NEAR, backend=LocalBackend(reciprocity=False),
                            options=PrecomputeOptions(block_size=64))


def _assert_same_factorization(dist, local, scene):
    """Same class, rank and error figures as the local path; radiosity equal up to rounding."""
    assert type(dist) is type(local)
    assert dist.rank == local.rank
    assert dist.relative_error <= EPS
    assert dist.relative_error == pytest.approx(local.relative_error, rel=1e-4)
    est, est_local = dist.error_estimate(), local.error_estimate()
    assert (est.kind, est.norm) == (est_local.kind, est_local.norm) == ("probes", "area")
    # the probed residual G - N - Q V^T is small beside G: float32 rounding of Q (merges on other BLAS
    # threads) shows in it at ~1e-4 relative (observed 1.2e-4 at 600 patches)
    assert np.allclose(est.bound, est_local.bound, rtol=1e-3)
    B, B_local = dist.solve(scene.emission), local.solve(scene.emission)
    diff = np.linalg.norm(B - B_local, axis=0) / np.linalg.norm(B_local, axis=0)
    # the same blocks and the same tree with the same truncations: equal up to rounding
    assert (diff <= 1e-4).all(), diff
    # the per-solve figure: the same sampled rows of F, kept by either backend's pass
    (_, err), (_, err_local) = dist.solve(scene.emission, return_error=True), local.solve(scene.emission,
                                                                                         return_error=True)
    assert err.kind == err_local.kind == "sampled" and err.rows == err_local.rows
    assert np.allclose(err.bound, err_local.bound, rtol=1e-3), (err.bound, err_local.bound)
    # the adjoint's own rows (drawn by 1/A), its first-bounce norms and the gain's power step too
    (_, err), (_, err_local) = (f.solve(scene.emission, trans="T", return_error=True) for f in (dist, local))
    assert err.kind == err_local.kind == "sampled" and err.rows == err_local.rows
    assert np.allclose(err.bound, err_local.bound, rtol=1e-3), (err.bound, err_local.bound)


def _job(A, m, b, n):
    from hfrad.precompute.assemble import PrecomputePlan

    options = PrecomputePlan(n=m * b, eps=0.05, relative=True, block_size=b, dtype="float64", samples=0,
                                order="input", perm=np.arange(m * b), leaf_share=0.5, one_ray_tol=0.0,
                                near_entries=0, near_radius=0.0, reciprocity=False, form_factors={})
    return Job(scene=None, options=options, rows_rho=np.ones((n, 1)), weights=None, samples=0, ray_budget=None,
               task_threads=None, token="t")


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 13])
def test_counter_tree_is_hfstream(m, monkeypatch):
    """The task tree (leaf/merge/root pieces run in counter_tree order) gives HFStream's factorization."""
    rng = np.random.default_rng(m)
    n, b = 7 * m, 7
    A = rng.standard_normal((n, 6)) @ rng.standard_normal((6, m * b)) + 1e-3 * rng.standard_normal((n, m * b))
    stream = HFStream(n, m, eps=0.05, dtype=np.float64)
    stats = PassStatistics(n)
    for j in range(m):   # as the local pipeline pushes a block: its norms from the pass over it
        G, norm2, block_norm2 = far_block(stats, j * b, (j + 1) * b, A[:, j * b:(j + 1) * b], np.ones((n, 1)))
        stream.push(G, norm2=norm2, block_norm2=block_norm2)
    expected = stream.finish()

    # "F" is A itself: the leaves read its columns instead of computing form factors
    monkeypatch.setattr(tasks, "column_block", lambda scene, cols, **kw: A[:, cols].copy())
    job = _job(A, m, b, n)
    parts = {j: tasks.leaf_task(job, j) for j in range(m)}
    for i, (left, right) in enumerate(counter_tree(m)):
        parts[m + i] = tasks.merge_task(job, m + i, parts.pop(left), parts.pop(right))
    (root,) = parts.values()
    got, records, stats, near = tasks.root_task(job, root)
    assert got.rank == expected.rank and got.achieved_error == pytest.approx(expected.achieved_error, rel=1e-12)
    assert np.allclose(got.Q @ got.V.T, expected.Q @ expected.V.T, atol=1e-12)
    assert np.linalg.norm(A - got.Q @ got.V.T) <= 0.05 * np.linalg.norm(A)
    assert len(records) == 2 * m - 1 and len(counter_tree(m)) == m - 1
    # the statistics summed over the tree are those of the whole matrix (rows_rho = 1: G = F = A)
    assert np.allclose(stats["row_sums"], A.sum(axis=1)) and np.allclose(stats["col_sums"], A.sum(axis=0))
    from hfrad.solve.stats import probe_vectors
    assert np.allclose(stats["sketch"], A @ probe_vectors(None, m * b))


@pytest.mark.parametrize("dtype, panel_count", [(np.float64, 1), (np.float64, 3), (np.float32, 4)])
def test_panelled_merge_is_the_serial_merge(dtype, panel_count):
    """A merge by row panels (Gram per panel, small step, forming) gives merge_nodes' node: same rank and
    discard, the same U S V^T, orthonormal factors."""
    from hfrad.distributed import panels
    from hfrad.lowrank.hf import ErrorBudget, compress_leaf, merge_nodes

    rng = np.random.default_rng(panel_count)
    n, b = 301, 40
    A = (rng.standard_normal((n, 12)) @ rng.standard_normal((12, 2 * b))
         + 1e-2 * rng.standard_normal((n, 2 * b))).astype(dtype)
    budget = ErrorBudget(0.05, True, 2, 0.5)
    left, right = compress_leaf(A[:, :b].copy(), budget, 0), compress_leaf(A[:, b:].copy(), budget, 1)
    serial = merge_nodes(left, right, budget, "test")
    rows = list(zip(*(lambda x: (x[:-1], x[1:]))(panels.panel_bounds(n, panel_count))))
    G = sum(panels.panel_gram(left.U[a:c], right.U[a:c], slab=50) for a, c in rows)
    out = panels.merge_small(G, tasks.node_meta(left), tasks.node_meta(right), budget.merge(left.norm2 + right.norm2))
    U = np.concatenate([panels.panel_form(left.U[a:c], right.U[a:c], out["B"], dtype, slab=50) for a, c in rows])
    V = np.concatenate([panels.chunk_update(left.V, out["W1"]), panels.chunk_update(right.V, out["W2"])])
    s, meta = out["meta"]["s"], out["meta"]
    # observed: float64 discard 2e-11 relative, product 2e-15, orthogonality 3e-15; float32 1.3e-6, 8e-7, 4e-7
    tol = 1e-12 if dtype == np.float64 else 2e-5
    assert s.size == serial.s.size > 0 and U.dtype == V.dtype == dtype
    assert meta["discarded2"] == pytest.approx(serial.discarded2, rel=100 * tol)
    assert meta["slack2"] == pytest.approx(serial.slack2, rel=100 * tol, abs=tol * left.norm2)
    assert np.abs((U * s) @ V.T - (serial.U * serial.s) @ serial.V.T).max() <= 10 * tol * np.abs(A).max()
    assert np.abs(U.T @ U - np.eye(s.size)).max() <= 10 * tol and np.abs(V.T @ V - np.eye(s.size)).max() <= 10 * tol


def test_task_order_skips_saved_subtrees():
    """A saved node replaces its whole subtree: the tasks submitted are the saved nodes and what lies above them."""
    order = task_order(8)
    assert [node for _, node, _ in order] == [0, 1, 8, 2, 3, 9, 10, 4, 5, 11, 6, 7, 12, 13, 14]
    assert [c for kind, node, c in order if kind == "merge"] == counter_tree(8)


def test_in_process_cluster_matches_local(cornell):
    scene, local = cornell
    seen = []
    with connect(workers=2, processes=False) as cluster:
        records = []
        dist = factorize(scene, eps=EPS, near_field=NEAR, progress=lambda done, total: seen.append((done, total)),
                         backend=DaskBackend(scheduler=cluster, records=records),
                         options=PrecomputeOptions(block_size=64))
    _assert_same_factorization(dist, local, scene)
    m = -(-scene.n_patches // 64)
    assert seen[-1] == (m, m)
    assert dist.params["backend"] == "dask" and dist.params["workers"] == 2
    assert local.params["backend"] == "local"
    assert dist.params["reciprocity"] and not local.params["reciprocity"]   # as asked; the rest is the same
    assert {k: v for k, v in dist.params.items() if k not in ("backend", "workers", "reciprocity")} == \
        {k: v for k, v in local.params.items() if k not in ("backend", "reciprocity")}
    info = dist.lowrank.info
    tree = [r for r in records if r["kind"] in ("leaf", "merge")]
    assert info["n_blocks"] == m and info["tasks"] == 2 * m - 1 == len(tree) == info["tasks_run"]
    assert info["time_formfactors"] > 0 and info["time_precompute"] > 0
    assert info["near_nnz"] == local.lowrank.info["near_nnz"] > 0
    # two workers: merges over more than ceil(m / 2) = 5 blocks (the 8-block node and the root) run by row panels
    assert info["panel_leaves"] == 5 and info["row_panels"] == 2 and info["panelled_merges"] == 2
    assert {r["kind"] for r in records} == {"leaf", "merge", "slice", "gram", "form", "chunk", "tile"}
    assert info["tile_tasks"] > 0 and info["pairs_computed"] < scene.n_patches ** 2


def _datasets(path):
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        attrs = dict(f.attrs)
    return out, attrs


def test_both_backends_write_the_same_hfr(cornell, tmp_path):
    """The .hfr of either backend holds the same fields; they differ only in backend, workers, timings."""
    import json

    from hfrad.solve.hfr import save_hfr

    scene, local = cornell
    with connect(workers=1, processes=False) as cluster:
        dist = factorize(scene, eps=EPS, near_field=NEAR,
                         backend=DaskBackend(scheduler=cluster, reciprocity=False),
                         options=PrecomputeOptions(block_size=64))
    save_hfr(local, tmp_path / "local.hfr")
    save_hfr(dist, tmp_path / "dask.hfr")
    (d_local, a_local), (d_dask, a_dask) = _datasets(tmp_path / "local.hfr"), _datasets(tmp_path / "dask.hfr")
    assert sorted(d_local) == sorted(d_dask)
    assert "factors/near_data" in d_dask and "stats/sketch" in d_dask
    for name, x in d_local.items():
        y = d_dask[name]
        assert x.shape == y.shape and x.dtype == y.dtype, name
        if x.dtype.kind in "iub" and not name.endswith("codes"):   # perm, N's pattern
            assert np.array_equal(x, y), name
        else:
            # the blocks are equal bit for bit (N, row and column sums: exactly); the merges run on other
            # BLAS threads and the sketch is summed in another order (rounding). Observed, as a share of
            # the field's largest value: Q 2e-5, V 2.8e-4 (trailing singular vectors), K^-1 4e-6, sketch
            # 2e-16; 16-bit codes of Z_c apart by up to 4 (of 32,767)
            rel = {"factors/V": 2e-3, "factors/near_solution_codes": 5e-4}.get(name, 1e-4)
            assert np.abs(x.astype(np.float64) - y).max() <= rel * max(float(np.abs(x).max()), 1e-30), name
    p_local, p_dask = json.loads(a_local.pop("parameters")), json.loads(a_dask.pop("parameters"))
    assert (p_local.pop("backend"), p_dask.pop("backend"), p_dask.pop("workers")) == ("local", "dask", 1)
    assert p_local == p_dask
    i_local, i_dask = json.loads(a_local.pop("lowrank_info")), json.loads(a_dask.pop("lowrank_info"))
    for key in ("near_nnz", "near_radius", "solver", "n_blocks", "dtype", "leaf_share"):
        assert i_local[key] == i_dask[key], key
    assert set(a_local) == set(a_dask)
    for key in set(a_local) - {"timings"}:
        x, y = a_local[key], a_dask[key]
        if "sha256" in key or "digest" in key:
            continue   # checksums of contents that differ in timings and rounding
        if isinstance(x, (str, bytes, bool, np.bool_)) or np.asarray(x).dtype.kind in "iuSUO":
            assert np.array_equal(x, y), key
        else:   # achieved error, norm, sigma_max, error bound
            assert np.allclose(x, y, rtol=1e-3), key


def _wait_until_no_task_runs(client, timeout: float = 120.0) -> None:
    """Until no worker executes a task (cancelled ones included), at most ``timeout`` seconds."""
    t0 = time.perf_counter()
    while any(client.run(lambda dask_worker: len(dask_worker.state.executing)).values()):
        assert time.perf_counter() - t0 < timeout, "a cancelled task still runs"
        time.sleep(0.05)


def test_rerun_skips_the_saved_subtrees(cornell, tmp_path):
    """Finished parts persist in the checkpoint folder: a rerun after a lost client runs only what is missing."""
    scene, local = cornell
    folder = tmp_path / "run.parts"
    m = -(-scene.n_patches // 64)

    def stop_after_four(done, total):
        if done >= 4:
            raise KeyboardInterrupt   # the client goes away; finished parts stay on disk

    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(KeyboardInterrupt):
            factorize(scene, eps=EPS, near_field=NEAR, progress=stop_after_four,
                      backend=DaskBackend(scheduler=cluster), checkpoint=folder,
                      options=PrecomputeOptions(block_size=64))
        assert any(folder.glob("node-*.sha256"))
        # a cancelled task that had started runs on (Dask cannot stop a running thread) and may save a merge
        # and drop its children's parts: wait for it, as a user rerunning later would
        _wait_until_no_task_runs(cluster.client)
        resumed = factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=cluster),
                            checkpoint=Checkpoint(folder, keep=True), options=PrecomputeOptions(block_size=64))
        info = resumed.lowrank.info
        assert info["tasks_resumed"] >= 1 and info["tasks_run"] < 2 * m - 1
        _assert_same_factorization(resumed, local, scene)
        # run once more, deleting nothing: everything is read back, no leaf or merge runs
        again = factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=cluster),
                          checkpoint=folder, options=PrecomputeOptions(block_size=64))
    assert again.lowrank.info["tasks_run"] == 0 and again.lowrank.info["tasks_resumed"] == 1
    _assert_same_factorization(again, local, scene)
    assert not folder.exists()   # deleted once complete (keep_checkpoint=False)


def test_checkpoint_of_other_options_is_refused(cornell, tmp_path):
    from hfrad.errors import InputError

    scene, _ = cornell
    folder = tmp_path / "run.parts"
    folder.mkdir()
    (folder / "key").write_text("another run\n")
    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(InputError, match="another scene or other parameters"):
            factorize(scene, eps=EPS, backend=DaskBackend(scheduler=cluster), checkpoint=folder,
                      options=PrecomputeOptions(block_size=64))


def test_interrupt_cancels_the_run(cornell):
    """Ctrl-C (KeyboardInterrupt in the progress callback) stops the run and leaves no task behind."""
    scene, _ = cornell

    def interrupt(done, total):
        if done >= 2:
            raise KeyboardInterrupt

    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(KeyboardInterrupt):
            factorize(scene, eps=EPS, near_field=NEAR, progress=interrupt, backend=DaskBackend(scheduler=cluster),
                      options=PrecomputeOptions(block_size=64))
        deadline = time.monotonic() + 10
        while cluster.client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) \
                and time.monotonic() < deadline:
            time.sleep(0.1)
        assert cluster.client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) == 0


def test_unreachable_scheduler_names_the_address():
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    with pytest.raises(SchedulerUnreachableError, match=address):
        with connect(address, timeout=1):
            pass


def test_scheduler_or_workers_not_both():
    with pytest.raises(ValueError, match="not both"):
        with connect("tcp://127.0.0.1:1", workers=2):
            pass
    with pytest.raises(ValueError, match="positive integer"):
        with connect(workers=0):
            pass


@pytest.fixture(scope="module")
def _process_cluster():
    with connect(workers=2) as cluster:
        assert cluster.address.startswith("tcp://127.0.0.1")
        yield cluster


@pytest.fixture
def process_cluster(_process_cluster):
    """Two worker processes on 127.0.0.1 (a LocalCluster with a nanny that restarts killed workers), both
    registered: after the kill test the nanny's new worker may still be joining when the next test starts."""
    _process_cluster.client.wait_for_workers(2, timeout=60)
    return _process_cluster


def test_worker_processes_match_local_despite_a_killed_worker(cornell, process_cluster, monkeypatch):
    """One worker process dies (SIGKILL) in its first leaf: Dask re-runs its tasks (leaves and reciprocity
    tiles) and the result is still the local one.

    The victim kills itself when it reaches its first leaf's factorization (``leaf_from_block``, replaced in
    that process only), so the death comes while blocks remain however fast the machine is: a kill sent
    from the progress callback came after the last block on a fast one.
    """
    from hfrad.distributed import tiles

    monkeypatch.setattr(tiles, "MIN_GROUP_COLUMNS", 128)   # groups of 2 blocks: 5 group tasks for 2 workers
    scene, local = cornell
    client = process_cluster.client
    pids = client.run(os.getpid)  # {worker address: pid}
    victim = sorted(pids.items())[0]

    def die_in_the_first_leaf():
        from hfrad.distributed import tasks

        def leaf_from_block(*args, **kwargs):
            os.kill(os.getpid(), signal.SIGKILL)
        tasks.leaf_from_block = leaf_from_block

    client.run(die_in_the_first_leaf, workers=[victim[0]])
    dist = factorize(scene, eps=EPS, near_field=NEAR, backend=DaskBackend(scheduler=process_cluster),
                     options=PrecomputeOptions(block_size=64))
    _assert_same_factorization(dist, local, scene)
    assert victim[0] not in client.run(os.getpid)  # that worker really died (its nanny started a new one)


def test_panelled_merges_on_worker_processes_equal_serial_merges(cornell, process_cluster):
    """Two single-thread worker processes: every merge by row panels (none holds a whole U) against every
    merge whole: the same rank, error figures and Q V^T; each panel task saw only its panel's rows."""
    from hfrad.distributed import DaskTuning, factorize_distributed
    from hfrad.precompute.options import plan_precompute

    scene, _ = cornell
    options = plan_precompute(scene, EPS, near_field=NEAR, options=PrecomputeOptions(block_size=64),
                              reciprocity=False)
    runs = {}
    for panel_leaves in (1, 10**9):
        records = []
        runs[panel_leaves] = factorize_distributed(scene, options, DaskBackend(scheduler=process_cluster, records=records),
                                                   tuning=DaskTuning(panel_leaves=panel_leaves, row_panels=3)), records
    (whole, whole_records), (split, split_records) = runs[10**9], runs[1]
    m = options.n_blocks
    assert whole.lowrank.info["panelled_merges"] == 0 and split.lowrank.info["panelled_merges"] == m - 1
    # float32 factors; observed: error figures 2.4e-8 and 1.9e-5 apart (relative), Q V^T 1.7e-6 of its largest entry
    assert split.rank == whole.rank
    assert split.relative_error == pytest.approx(whole.relative_error, rel=1e-6)
    assert np.allclose(split.error_estimate().bound, whole.error_estimate().bound, rtol=2e-4)
    QV, QV_whole = split.lowrank.Q @ split.lowrank.V.T, whole.lowrank.Q @ whole.lowrank.V.T
    assert np.abs(QV - QV_whole).max() <= 2e-5 * np.abs(QV_whole).max()
    panel_rows = {r["rows"] for r in split_records if r["kind"] in ("gram", "form")}
    assert max(panel_rows) <= -(-scene.n_patches // 3)
    assert {r["worker"] for r in split_records if r["kind"] == "gram"} == set(process_cluster.client.nthreads())


def test_refuses_workers_too_small_for_one_leaf(cornell, monkeypatch):
    from hfrad.distributed.connection import Cluster
    from hfrad.distributed.sizing import leaf_bytes
    from hfrad.errors import MemoryLimitError

    scene, _ = cornell
    monkeypatch.setattr(Cluster, "worker_memory_limits", lambda self: [leaf_bytes(scene.n_patches, 64)])
    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(MemoryLimitError, match="one leaf task needs about"):
            factorize(scene, eps=EPS, backend=DaskBackend(scheduler=cluster),
                      options=PrecomputeOptions(block_size=64))


def test_a_damaged_checkpoint_part_is_refused(tmp_path):
    """A saved part reads back as written; a flipped byte fails its checksum, naming the file."""
    from hfrad.distributed import store
    from hfrad.errors import FileFormatError
    from hfrad.lowrank.hf import _Node

    rng = np.random.default_rng(1)
    node = _Node(2, rng.standard_normal((30, 4)), np.arange(4.0)[::-1].copy(), rng.standard_normal((12, 4)),
                 5.0, 0.25, 0.5)
    stats = {"row_sums": rng.random(30), "col_sums": rng.random(30), "sketch": rng.random((30, 20)),
             "probes": 20, "seed": 7}
    near = {"near_rows": np.array([0, 3]), "near_cols": np.array([1, 2]), "near_values": np.array([0.5, 0.25])}
    assert store.open_folder(tmp_path, "k") == set()
    store.save_part(tmp_path, 9, tasks.Part(node, [{"kind": "merge", "node": 9}], stats, near))
    assert store.open_folder(tmp_path, "k") == {9}
    got, got_stats, got_near, records = store.load_part(tmp_path, 9)
    assert np.array_equal(got.U, node.U) and np.array_equal(got.V, node.V) and got.level == 2
    assert (got.norm2, got.discarded2, got.slack2) == (5.0, 0.25, 0.5)
    assert np.array_equal(got_stats["sketch"], stats["sketch"]) and got_stats["seed"] == 7
    assert np.array_equal(got_near["near_values"], near["near_values"]) and records == [{"kind": "merge", "node": 9}]
    path = tmp_path / "node-9.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="node-9.npz"):
        store.load_part(tmp_path, 9)
    store.drop_part(tmp_path, 9)
    assert store.open_folder(tmp_path, "k") == set()


def test_root_share_per_worker_falls_as_one_over_workers():
    """worker_bytes: with W workers the root's merge costs each worker 6 n k s / W + 192 k^2 bytes, not 14 n k s."""
    from hfrad.distributed import sizing

    n, k = 1_000_000, 2_000
    assert sizing.root_worker_bytes(n, k, 1) == sizing.merge_bytes(n, k, k) == 14 * n * k * 4
    assert sizing.root_worker_bytes(n, k, 64) == 6 * n * k * 4 // 64 + 192 * k * k
    one = sizing.worker_bytes(n, 256, k, near_entries=120)
    many = sizing.worker_bytes(n, 256, k, near_entries=120, workers=64, transition_rank=k // 4)
    # the busiest of 64 workers holds the last whole merge (ranks k / 4: 14 n k s / 4 = 28 GB) and no longer
    # the 112 GB root merge: 33 GB against 137 GB
    assert many < 0.25 * one
    assert many > sizing.merge_bytes(n, k // 4, k // 4)
    assert many >= sizing.leaf_bytes(n, 256)
