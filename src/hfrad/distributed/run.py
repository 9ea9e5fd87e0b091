"""The precomputation on a Dask cluster: the HF tree as a task graph.

Leaves (column block generation + truncated SVD) are independent tasks;
sibling merges form a tree reduction of depth ceil(log2 m). The tree is the
one :class:`~hfrad.factorize.hf.HFStream` builds (:func:`~hfrad.factorize.hf.counter_tree`)
with the same truncations and error budget, so the result has the same
meaning as the local path (one pass over F, achieved error <= eps) and equals
it up to rounding.
"""

from __future__ import annotations

import collections
import math
import time
import uuid

import dask
import numpy as np
from distributed.scheduler import KilledWorker

from ..defaults import DEFAULT_BLOCK_SIZE
from ..errors import MemoryLimitError, SceneError
from ..factorize.hf import counter_tree
from ..formfactors.parallel import default_one_ray_tol
from ..memory import human
from ..progress import ProgressCallback, report
from ..scene.scene import Scene
from ..scene.zorder import patch_order
from ..solve.woodbury import HFactorization
from ..validation import check_factorize_options
from . import sizing
from .cluster import Cluster, WorkerLostError, connect
from .tasks import Job, leaf_task, merge_task, root_task

_POLL_SECONDS = 0.2


def factorize_distributed(scene, *, scheduler=None, workers: int | None = None, eps: float = 0.02,
                          relative: bool = True, block_size: int | None = None, dtype="float32",
                          samples: int | None = None, order: str = "zorder", leaf_share: float = 0.5,
                          one_ray_tol: float | None = None, task_threads: int | None = None, connect_timeout: float | None = None,
                          progress: ProgressCallback = None, status=None,
                          records: list | None = None) -> HFactorization:
    """Precompute a scene on a Dask cluster: form factors, HF and Woodbury, as :func:`hfrad.factorize`.

    Parameters
    ----------
    scene : Scene
    scheduler : str, distributed.Client or Cluster, optional
        ``tcp://HOST:PORT`` of a running scheduler, a connected Client, or a
        :class:`~hfrad.distributed.cluster.Cluster` from :func:`~hfrad.distributed.connect`.
    workers : int, optional
        Instead of ``scheduler``: start a LocalCluster of this many worker processes.
    eps, relative, block_size, dtype, samples, order, leaf_share, one_ray_tol
        As in :func:`hfrad.factorize` (same meaning, same defaults).
    task_threads : int, optional
        Numba threads of the form-factor kernel per task (default: this machine's
        cores shared among a LocalCluster's workers; the workers' own setting,
        NUMBA_NUM_THREADS, on a scheduler). BLAS runs one thread per task.
    connect_timeout : float, seconds, optional
        Default: Dask's ``distributed.comm.timeouts.connect``.
    progress : callable (done, total), optional
        Leaves (column blocks) done.
    status : callable (dict), optional
        Called with ``blocks``, ``rank`` (summed over the finished nodes not yet
        merged, as the local path's stack) and ``elapsed`` when they change.
    records : list, optional
        Filled with one dict per task of the tree (kind, node, rank, columns,
        rows, seconds, form-factor and SVD seconds, ranks merged, worker): the
        measured per-task costs behind docs/cluster.md's model.

    Returns
    -------
    HFactorization
        ``params`` and ``lowrank.info`` record ``backend="dask"``, the number of
        workers and the seconds per stage (summed over tasks, plus wall time).

    Raises
    ------
    SchedulerUnreachableError
        The scheduler cannot be reached (names the address).
    MemoryLimitError
        A worker's memory limit is below what one leaf needs.
    WorkerLostError
        A task took down ``distributed.scheduler.allowed-failures`` workers in a row.
    ValueError
        Bad options (as :func:`hfrad.factorize`), or neither/both of scheduler and workers.

    Notes
    -----
    The scene travels to each worker once (scattered); each worker builds its
    Embree scene once; a block never leaves its worker, only its factors do.
    A worker lost mid-run costs only its tasks: Dask recomputes them from the
    graph. Memory per worker: :func:`hfrad.distributed.sizing.worker_bytes`.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a hfrad Scene (see hfrad.load_scene); got {type(scene).__name__}")
    if scene.n_patches == 0:
        raise SceneError(f"{scene.name}: the scene has no patches")
    block_size = min(DEFAULT_BLOCK_SIZE, scene.n_patches) if block_size is None else block_size
    dt = check_factorize_options(scene.n_patches, eps, block_size, dtype, relative)
    options = {"eps": eps, "relative": relative, "block_size": block_size, "dtype": dt.name,
               "samples": samples, "order": order, "leaf_share": leaf_share,
               "one_ray_tol": default_one_ray_tol(eps, relative) if one_ray_tol is None else one_ray_tol}
    if isinstance(scheduler, Cluster):
        return _run(scheduler, scene, options, task_threads, progress, status, records)
    with connect(scheduler, workers=workers, timeout=connect_timeout) as cluster:
        return _run(cluster, scene, options, task_threads, progress, status, records)


def _check_worker_memory(cluster: Cluster, n: int, block_size: int) -> None:
    """Refuse a run no worker can hold a leaf of (it would be killed, retried and killed again)."""
    need = sizing.PROCESS_BYTES + sizing.ENGINE_BYTES_PER_PATCH * n + sizing.leaf_bytes(n, block_size)
    limits = [x for x in cluster.worker_memory_limits() if x > 0]
    if limits and min(limits) < need:
        raise MemoryLimitError(
            f"one leaf task needs about {human(need)} but a worker of {cluster.address} may use only "
            f"{human(min(limits))}; use a smaller --block, fewer patches, or workers with more memory "
            "(dask worker --memory-limit)")


def _submit(client, job_future, m: int, token: str):
    """Submit leaves and merges in the order HFStream would run them; returns (root future, parents)."""
    merges = counter_tree(m)
    parents = {}
    futures = {}
    pending = 0  # next merge to submit
    for j in range(m):
        futures[j] = client.submit(leaf_task, job_future, j, key=f"hfrad-leaf-{j}-{token}", pure=False)
        # a merge goes in as soon as both children are in: Dask then runs it before later leaves
        # (earlier submissions first, merges preferred), which keeps few nodes resident
        while pending < len(merges) and all(c in futures for c in merges[pending]):
            left, right = merges[pending]
            node = m + pending
            futures[node] = client.submit(merge_task, job_future, node, futures.pop(left), futures.pop(right),
                                          key=f"hfrad-merge-{node}-{token}", pure=False, priority=1)
            parents[left] = parents[right] = node
            pending += 1
    (last,) = futures.values()  # the root: only it is held, so finished parts are freed as they merge
    root = client.submit(root_task, job_future, last, key=f"hfrad-root-{token}", pure=False, priority=2)
    return root, parents


class _Tracker:
    """Blocks done and the current rank, from the tasks' progress events (duplicates from retries ignored)."""

    def __init__(self, m: int) -> None:
        self.m, self.parents = m, {}
        self.events: collections.deque = collections.deque()
        self.rank_of: dict[int, int] = {}
        self.executions = 0

    def handler(self, event) -> None:  # runs on the client's event-loop thread
        self.events.append(event[1] if isinstance(event, tuple) else event)

    def drain(self) -> bool:
        changed = False
        while self.events:
            msg = self.events.popleft()
            self.executions += 1
            self.rank_of[int(msg["node"])] = int(msg["rank"])
            changed = True
        return changed

    @property
    def blocks(self) -> int:
        return sum(1 for node in self.rank_of if node < self.m)

    @property
    def rank(self) -> int:
        return sum(k for node, k in self.rank_of.items() if self.parents.get(node) not in self.rank_of)


def _run(cluster: Cluster, scene, options: dict, task_threads, progress, status, records_out) -> HFactorization:
    from ..formfactors.parallel import ray_budget
    from ..formfactors.visibility import DEFAULT_SAMPLES

    client = cluster.client
    n, block_size, dt = scene.n_patches, options["block_size"], np.dtype(options["dtype"])
    m = math.ceil(n / block_size)
    _check_worker_memory(cluster, n, block_size)
    perm = patch_order(scene.centroids, options["order"])
    rho_max = scene.reflectance.max(axis=1)
    samples = DEFAULT_SAMPLES if options["samples"] is None else int(options["samples"])
    token = uuid.uuid4().hex[:12]
    job = Job(scene=scene, perm=np.asarray(perm, np.int64), rows_rho=rho_max[perm][:, None].astype(dt),
              block_size=int(block_size), n_blocks=m, dtype=dt.name, eps=float(options["eps"]),
              relative=bool(options["relative"]), leaf_share=float(options["leaf_share"]), samples=samples,
              ray_budget=ray_budget(scene, options["one_ray_tol"]) if samples else None,
              task_threads=task_threads if task_threads is not None else cluster.task_threads, token=token)
    t0 = time.perf_counter()
    [job_future] = client.scatter([job], broadcast=True, hash=False)  # the scene travels once per worker
    time_scatter = time.perf_counter() - t0
    tracker = _Tracker(m)
    client.subscribe_topic(job.topic, tracker.handler)  # before the first task can report
    try:
        root, tracker.parents = _submit(client, job_future, m, token)
        report(progress, 0, m)
        while not root.done():
            time.sleep(_POLL_SECONDS)
            if tracker.drain():
                report(progress, tracker.blocks, m)
                if status is not None:
                    status({"blocks": tracker.blocks, "rank": tracker.rank, "elapsed": time.perf_counter() - t0})
        t_gather = time.perf_counter()
        lowrank, records = root.result()
        time_gather = time.perf_counter() - t_gather
        tracker.drain()
    except KilledWorker as exc:
        client.cancel([job_future])
        raise WorkerLostError(
            f"{exc}: a task took down {dask.config.get('distributed.scheduler.allowed-failures')} workers in a "
            f"row, usually a worker out of memory; each worker needs about "
            f"{human(sizing.worker_bytes(n, block_size, sizing.rank_guess(n, job.eps)))} here "
            "(docs/cluster.md, 'Memory per worker')") from None
    except BaseException:
        client.cancel([job_future])  # Ctrl-C or a failure: stop the cluster's work on this run
        raise
    finally:
        client.unsubscribe_topic(job.topic)
    wall = time.perf_counter() - t0
    report(progress, m, m)
    del job_future
    lowrank.info.update(_info(records, m, dt, job.leaf_share, cluster, time_scatter, time_gather, wall,
                              tracker.executions))
    if records_out is not None:
        records_out.extend(records)
    from ..formfactors.kernel import settings as kernel_settings
    from ..formfactors.visibility import settings as visibility_settings

    # as the local path records them: the form-factor kernel's version and tolerances
    params = {**options, "form_factors": {**kernel_settings(), **visibility_settings()}, "backend": "dask",
              "workers": cluster.n_workers}
    return HFactorization(perm, lowrank.Q, lowrank.V, rho_max, scene.reflectance, lowrank, params=params,
                          scene=scene)


def _info(records, m, dt, leaf_share, cluster, time_scatter, time_gather, wall, executions) -> dict:
    """Per-stage seconds (summed over the tasks of the final tree) and the run's shape, for the .hfr.

    ``task_executions`` counts the tasks' progress reports: above ``tasks`` when
    Dask re-ran tasks of a lost worker (a report still in flight at the end is missed).
    """
    leaves = sorted((r for r in records if r["kind"] == "leaf"), key=lambda r: r["node"])
    merges = [r for r in records if r["kind"] == "merge"]
    time_ff = sum(r["formfactors"] for r in leaves)
    time_leaf = sum(r["svd"] for r in leaves)
    time_merge = sum(r["seconds"] for r in merges)
    return {"backend": "dask", "workers": cluster.n_workers, "scheduler": cluster.address,
            "cluster": cluster.kind, "n_blocks": m, "leaf_ranks": [r["rank"] for r in leaves],
            "dtype": dt.name, "leaf_share": leaf_share,
            "time_formfactors": time_ff, "time_leaf": time_leaf, "time_merge": time_merge,
            "time_total": time_leaf + time_merge, "time_scatter": time_scatter, "time_gather": time_gather,
            "time_precompute": wall, "tasks": len(records), "task_executions": executions}
