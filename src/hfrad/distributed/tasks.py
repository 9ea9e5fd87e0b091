"""What runs on the Dask workers: one leaf per column block, one merge per tree node.

A task returns a :class:`Part`: the HF node (``U``, ``s``, ``V`` and the error
bookkeeping of :mod:`hfrad.factorize.hf`) plus the records of the tasks below
it. The n x b form-factor block of a leaf is made, compressed and dropped inside
the task, so only its factors (n x k_j and b x k_j) ever leave the worker.

Everything here trusts its input: :func:`hfrad.distributed.factorize_distributed`
validated it on the client.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field

import numpy as np

from ..factorize.hf import ErrorBudget, compress_leaf, merge_nodes, root_lowrank
from ..factorize.lowrank import LowRank
from ..formfactors.parallel import column_block
from ..formfactors.visibility import RayBudget


@dataclass(frozen=True)
class Job:
    """Everything a task needs, scattered to the workers once per run.

    Attributes
    ----------
    scene : Scene
        The patches; each worker process builds its form-factor engine and
        Embree scene from it once (:func:`hfrad.formfactors.parallel.column_block`).
    perm : (n,) int64
        Internal (Z-)order: internal index t holds user patch ``perm[t]``.
    rows_rho : (n, 1) of ``dtype``
        ``rho_max`` in internal order: a block of G is ``rows_rho * F[perm][:, cols]``.
    block_size, n_blocks : int
    dtype : str
        Working precision of the factors ("float32" or "float64").
    eps, relative, leaf_share
        The error budget, as in :class:`~hfrad.factorize.hf.HFStream`.
    samples : int
        Visibility rays per pair.
    ray_budget : RayBudget or None
        Fewer rays for weak pairs (the local path's thresholds).
    task_threads : int or None
        Threads of the numba kernel inside one task (None: the worker's setting).
    token : str
        Names this run (task keys, the progress topic).
    """

    scene: object
    perm: np.ndarray
    rows_rho: np.ndarray
    block_size: int
    n_blocks: int
    dtype: str
    eps: float
    relative: bool
    leaf_share: float
    samples: int
    ray_budget: RayBudget | None
    task_threads: int | None
    token: str

    @property
    def budget(self) -> ErrorBudget:
        return ErrorBudget(self.eps, self.relative, max(self.n_blocks, 1), self.leaf_share)

    @property
    def topic(self) -> str:
        """The Dask event topic the tasks of this run report to."""
        return f"hfrad-progress-{self.token}"


@dataclass
class Part:
    """A factored column range and the records of the tasks that made it.

    ``records`` has one dict per task in the subtree: ``kind`` ("leaf" or
    "merge"), ``node``, ``rank``, ``columns``, ``rows``, ``seconds`` (task wall time),
    ``cpu`` (CPU seconds of the worker process during the task: with one task at a
    time, the task's own, and not inflated by other processes competing for the
    cores), ``formfactors``, ``svd`` and ``cpu_formfactors`` seconds (leaves),
    ``ranks_in`` (merges), ``worker``.
    """

    node: object
    records: list = field(default_factory=list)


@contextlib.contextmanager
def _threads(count: int | None):
    """``count`` numba threads for this task's form-factor kernel (None: the worker's setting).

    BLAS stays at one thread, as in the local path: Dask's nanny starts workers
    with OPENBLAS_NUM_THREADS=1, and a multi-threaded BLAS beside busy cores
    spin-waits (10-50x slower small SVDs, see hfrad.pipeline).
    """
    if count is None:
        yield
        return
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(count, numba.config.NUMBA_NUM_THREADS)))  # thread-local in numba
    try:
        yield
    finally:
        numba.set_num_threads(before)


def _announce(job: Job, message: dict) -> None:
    """Tell the client a node is done (progress only; a lost message costs nothing)."""
    try:
        from distributed import get_worker

        get_worker().log_event(job.topic, message)
    except (ImportError, ValueError):  # not running on a worker (direct calls in tests)
        pass


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return "local"


def leaf_task(job: Job, j: int) -> Part:
    """Leaf ``j``: compute the column block ``G[:, cols_j]`` of ``G = diag(rho_max) F`` and compress it.

    Returns the truncated SVD of the block (n x k_j, k_j, b x k_j), never the block.
    The block is the local path's, value for value (same engine, threshold and
    dtype). Peak memory: the float64 block (8 n b bytes), its ``dtype`` copies
    and the SVD's workspace, about 25 n b bytes with float32 factors.
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    cols = job.perm[j * job.block_size:(j + 1) * job.block_size]
    with _threads(job.task_threads):
        A = job.rows_rho * column_block(job.scene, cols, order=job.perm, samples=job.samples,
                                        ray_budget=job.ray_budget, dtype=job.dtype)
    t1, cpu1 = time.perf_counter(), time.process_time()
    node = compress_leaf(A, job.budget, j)
    del A
    t2 = time.perf_counter()
    rank = int(node.s.size)
    _announce(job, {"node": j, "kind": "leaf", "rank": rank})
    return Part(node, [{"kind": "leaf", "node": j, "rank": rank, "columns": int(len(cols)),
                        "rows": int(job.perm.size), "seconds": t2 - t0, "formfactors": t1 - t0,
                        "svd": t2 - t1, "cpu": time.process_time() - cpu0, "cpu_formfactors": cpu1 - cpu0,
                        "worker": _worker_name()}])


def merge_task(job: Job, node_id: int, left: Part, right: Part) -> Part:
    """Merge two sibling parts (``left`` covers the earlier columns) within the node's error share.

    Peak memory about ``7 n (k_left + k_right)`` words: both children's U, the
    orthogonalised block, and the merged U with its two products.
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    node = merge_nodes(left.node, right.node, job.budget, f"merge node {node_id}")
    seconds = time.perf_counter() - t0
    rank = int(node.s.size)
    _announce(job, {"node": node_id, "kind": "merge", "rank": rank})
    own = {"kind": "merge", "node": node_id, "rank": rank, "rows": int(job.perm.size),
           "columns": int(node.V.shape[0]), "ranks_in": [int(left.node.s.size), int(right.node.s.size)],
           "seconds": seconds, "cpu": time.process_time() - cpu0, "worker": _worker_name()}
    return Part(node, left.records + right.records + [own])


def root_task(job: Job, root: Part) -> tuple[LowRank, list]:
    """``Q V^T`` of the root with its achieved error (``Q`` and ``V`` are n x k), and all task records."""
    return root_lowrank(root.node, job.eps, job.relative), root.records
