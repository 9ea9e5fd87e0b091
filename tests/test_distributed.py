"""The Dask backend: the same factorization as the local path, on LocalClusters, despite a killed worker."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from hfrad.distributed import SchedulerUnreachableError, connect, factorize_distributed
from hfrad.distributed import tasks
from hfrad.distributed.tasks import Job
from hfrad.factorize.hf import HFStream, counter_tree
from hfrad.pipeline import factorize
from hfrad.scene.load import load_scene

EPS = 0.02


@pytest.fixture(scope="module")
def cornell():
    """A 1,000-patch Cornell box and its local (in-process, streaming) factorization."""
    scene = load_scene("cornell", patches=1000)
    return scene, factorize(scene, eps=EPS, block_size=64, reciprocity=False)   # every pair, as on Dask


def _assert_same_factorization(dist, local, scene):
    """Same rank and error as the local path; radiosity within the reported error of the local result."""
    assert dist.rank == local.rank
    assert dist.relative_error <= EPS
    assert dist.relative_error == pytest.approx(local.relative_error, rel=1e-4)
    B, B_local = dist.solve(scene.emission), local.solve(scene.emission)
    diff = np.linalg.norm(B - B_local, axis=0) / np.linalg.norm(B_local, axis=0)
    # the same tree with the same truncations: equal up to rounding, far inside the eq. 5 bound
    assert (diff <= 1e-4).all(), diff
    assert (diff <= dist.error_bound).all()


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 13])
def test_counter_tree_is_hfstream(m, monkeypatch):
    """The task tree (leaf/merge/root pieces run in counter_tree order) gives HFStream's factorization."""
    rng = np.random.default_rng(m)
    n, b = 40, 7
    A = rng.standard_normal((n, 6)) @ rng.standard_normal((6, m * b)) + 1e-3 * rng.standard_normal((n, m * b))
    stream = HFStream(n, m, eps=0.05, dtype=np.float64)
    for j in range(m):
        stream.push(A[:, j * b:(j + 1) * b])
    expected = stream.finish()

    # "F" is A itself: the leaves read its columns instead of computing form factors
    monkeypatch.setattr(tasks, "column_block", lambda scene, cols, **kw: A[:, cols].copy())
    job = Job(scene=None, perm=np.arange(m * b), rows_rho=np.ones((n, 1)), block_size=b, n_blocks=m,
              dtype="float64", eps=0.05, relative=True, leaf_share=0.5, samples=0, ray_budget=None,
              task_threads=None, token="t")
    parts = {j: tasks.leaf_task(job, j) for j in range(m)}
    for i, (left, right) in enumerate(counter_tree(m)):
        parts[m + i] = tasks.merge_task(job, m + i, parts.pop(left), parts.pop(right))
    (root,) = parts.values()
    got, records = tasks.root_task(job, root)
    assert got.rank == expected.rank and got.achieved_error == pytest.approx(expected.achieved_error, rel=1e-12)
    assert np.allclose(got.Q @ got.V.T, expected.Q @ expected.V.T, atol=1e-12)
    assert np.linalg.norm(A - got.Q @ got.V.T) <= 0.05 * np.linalg.norm(A)
    assert len(records) == 2 * m - 1 and len(counter_tree(m)) == m - 1


def test_in_process_cluster_matches_local(cornell):
    scene, local = cornell
    seen = []
    with connect(workers=2, processes=False) as cluster:
        records = []
        dist = factorize_distributed(scene, scheduler=cluster, eps=EPS, block_size=64, records=records,
                                     progress=lambda done, total: seen.append((done, total)))
    _assert_same_factorization(dist, local, scene)
    m = -(-scene.n_patches // 64)
    assert seen[-1] == (m, m)
    assert dist.params["backend"] == "dask" and dist.params["workers"] == 2
    assert dist.params["form_factors"] == local.params["form_factors"]
    assert local.params["backend"] == "local"
    info = dist.lowrank.info
    assert info["n_blocks"] == m and info["tasks"] == 2 * m - 1 == len(records)
    assert info["time_formfactors"] > 0 and info["time_precompute"] > 0
    assert {r["kind"] for r in records} == {"leaf", "merge"}


def test_interrupt_cancels_the_run(cornell):
    """Ctrl-C (KeyboardInterrupt in the progress callback) stops the run and leaves no task behind."""
    scene, _ = cornell

    def interrupt(done, total):
        if done >= 2:
            raise KeyboardInterrupt

    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(KeyboardInterrupt):
            factorize_distributed(scene, scheduler=cluster, eps=EPS, block_size=64, progress=interrupt)
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
def process_cluster():
    """Two worker processes on 127.0.0.1 (a LocalCluster with a nanny that restarts killed workers)."""
    with connect(workers=2) as cluster:
        assert cluster.address.startswith("tcp://127.0.0.1")
        yield cluster


def test_worker_processes_match_local_despite_a_killed_worker(cornell, process_cluster):
    """Kill one worker process (SIGKILL) mid-run: Dask re-runs its tasks and the result is still the local one."""
    scene, local = cornell
    client = process_cluster.client
    pids = client.run(os.getpid)  # {worker address: pid}
    victim = sorted(pids.items())[0]
    killed = []

    def kill_once(done, total):
        if done >= 3 and not killed:
            os.kill(victim[1], signal.SIGKILL)
            killed.append(done)

    dist = factorize_distributed(scene, scheduler=process_cluster, eps=EPS, block_size=64, progress=kill_once)
    assert killed and killed[0] < -(-scene.n_patches // 64), "the worker must die while blocks remain"
    _assert_same_factorization(dist, local, scene)
    assert victim[0] not in client.run(os.getpid)  # that worker really is gone (its nanny started a new one)


def test_refuses_workers_too_small_for_one_leaf(cornell, monkeypatch):
    from hfrad.distributed.cluster import Cluster
    from hfrad.distributed.sizing import leaf_bytes
    from hfrad.errors import MemoryLimitError

    scene, _ = cornell
    monkeypatch.setattr(Cluster, "worker_memory_limits", lambda self: [leaf_bytes(scene.n_patches, 64)])
    with connect(workers=1, processes=False) as cluster:
        with pytest.raises(MemoryLimitError, match="one leaf task needs about"):
            factorize_distributed(scene, scheduler=cluster, eps=EPS, block_size=64)
