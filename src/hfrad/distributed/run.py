"""The precomputation on a Dask cluster: the HF tree as a task graph.

Leaves (column block generation + truncated SVD) are independent tasks;
sibling merges form a tree reduction of depth ceil(log2 m). The tree is the
one :class:`~hfrad.lowrank.hf.HFStream` builds (:func:`~hfrad.lowrank.hf.counter_tree`)
with the same truncations and error budget, so the result has the same
meaning as the local path (one pass over F, achieved error <= eps) and equals
it up to rounding.
"""

from __future__ import annotations

import collections
import time
import uuid
from pathlib import Path

import dask
from distributed.scheduler import KilledWorker

from ..errors import MemoryLimitError
from ..lowrank.hf import counter_tree
from ..memory import human
from ..progress import ProgressCallback, report
from ..solve.assemble import PrecomputeOptions, assemble
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from . import sizing, store
from .cluster import Cluster, WorkerLostError, connect
from .tasks import Job, leaf_task, load_task, merge_task, root_task

_POLL_SECONDS = 0.2


def factorize_distributed(scene, options: PrecomputeOptions, *, scheduler=None, workers: int | None = None,
                          task_threads: int | None = None, connect_timeout: float | None = None,
                          checkpoint=None, progress: ProgressCallback = None, status=None,
                          records: list | None = None) -> HFactorization:
    """Precompute a scene on a Dask cluster: what :func:`hfrad.factorize` does, as Dask tasks.

    Users call ``hfrad.factorize(scene, scheduler=..., workers=...)``, which validates
    the options and comes here; this is the backend.

    Parameters
    ----------
    scene : Scene
    options : PrecomputeOptions
        From :func:`hfrad.solve.assemble.precompute_options` (the local path's; the
        reciprocity copy is not used here: every pair is computed).
    scheduler : str, distributed.Client or Cluster, optional
        ``tcp://HOST:PORT`` of a running scheduler, a connected Client, or a
        :class:`~hfrad.distributed.cluster.Cluster` from :func:`~hfrad.distributed.connect`.
    workers : int, optional
        Instead of ``scheduler``: start a LocalCluster of this many worker processes.
    task_threads : int, optional
        Numba threads of the form-factor kernel per task (default: this machine's
        cores shared among a LocalCluster's workers; the workers' own setting,
        NUMBA_NUM_THREADS, on a scheduler). BLAS runs one thread per task.
    connect_timeout : float, seconds, optional
        Default: Dask's ``distributed.comm.timeouts.connect``.
    checkpoint : path, optional
        A folder for the finished subtrees' factors (:mod:`hfrad.distributed.store`),
        reachable at this path from every worker; a rerun with the same scene and
        options skips what it holds. Left in place (the caller deletes it once the
        result is saved: :func:`hfrad.distributed.store.remove_folder`).
    progress : callable (done, total), optional
        Leaves (column blocks) done.
    status : callable (dict), optional
        Called with ``blocks``, ``rank`` (summed over the finished nodes not yet
        merged, as the local path's stack) and ``elapsed`` when they change.
    records : list, optional
        Filled with one dict per task of the tree (kind, node, rank, columns,
        rows, seconds, form-factor and SVD seconds, ranks merged, worker, resumed):
        the measured per-task costs behind docs/cluster.md's model.

    Returns
    -------
    HFactorization or NearFieldFactorization
        As the local path's (:func:`hfrad.solve.assemble.assemble`); ``params`` and
        ``lowrank.info`` record ``backend="dask"``, the number of workers and the
        seconds per stage (summed over tasks, plus wall time).

    Raises
    ------
    SchedulerUnreachableError
        The scheduler cannot be reached (names the address).
    MemoryLimitError
        A worker's memory limit is below what one leaf needs.
    WorkerLostError
        A task took down ``distributed.scheduler.allowed-failures`` workers in a row.
    InputError
        Neither/both of scheduler and workers; a checkpoint of another input.

    Notes
    -----
    The scene travels to each worker once (scattered); each worker builds its
    Embree scene once; a block never leaves its worker, only its factors, its
    statistics (n x 22 floats) and its near entries do. A worker lost mid-run costs
    only its tasks: Dask recomputes them from the graph. Memory per worker:
    :func:`hfrad.distributed.sizing.worker_bytes`.
    """
    if not isinstance(options, PrecomputeOptions):
        raise TypeError("options must come from hfrad.solve.assemble.precompute_options "
                        "(or call hfrad.factorize(scene, scheduler=..., workers=...))")
    options = options.replace(reciprocity=False)   # every pair is computed on the workers
    if isinstance(scheduler, Cluster):
        return _run(scheduler, scene, options, task_threads, checkpoint, progress, status, records)
    with connect(scheduler, workers=workers, timeout=connect_timeout) as cluster:
        return _run(cluster, scene, options, task_threads, checkpoint, progress, status, records)


def _check_worker_memory(cluster: Cluster, n: int, block_size: int) -> None:
    """Refuse a run no worker can hold a leaf of (it would be killed, retried and killed again)."""
    need = sizing.PROCESS_BYTES + sizing.ENGINE_BYTES_PER_PATCH * n + sizing.leaf_bytes(n, block_size)
    limits = [x for x in cluster.worker_memory_limits() if x > 0]
    if limits and min(limits) < need:
        raise MemoryLimitError(
            f"one leaf task needs about {human(need)} but a worker of {cluster.address} may use only "
            f"{human(min(limits))}; use a smaller --block, fewer patches, or workers with more memory "
            "(dask worker --memory-limit)")


def task_order(m: int) -> list[tuple[str, int, tuple]]:
    """The tree's tasks in the order HFStream runs them: ("leaf", j, ()) or ("merge", node, (left, right))."""
    merges = counter_tree(m)
    done, out, pending = set(), [], 0
    for j in range(m):
        out.append(("leaf", j, ()))
        done.add(j)
        while pending < len(merges) and all(c in done for c in merges[pending]):
            out.append(("merge", m + pending, merges[pending]))
            done.add(m + pending)
            pending += 1
    return out


def _submit(client, job_future, m: int, token: str, saved: set):
    """Submit leaves and merges in the order HFStream would run them; returns (root future, parents, resumed).

    A node in ``saved`` (a checkpoint's) is read back by a load task and nothing below it is submitted.
    """
    order = task_order(m)
    parents = {c: node for kind, node, children in order for c in children}
    skipped = set()   # nodes below a saved one
    for kind, node, children in reversed(order):   # parents before their children
        if node in saved or node in skipped:
            skipped.update(children)
    futures, resumed = {}, []
    for kind, node, children in order:
        if node in skipped:
            continue
        if node in saved:
            futures[node] = client.submit(load_task, job_future, node, key=f"hfrad-load-{node}-{token}", pure=False)
            resumed.append(node)
        elif kind == "leaf":
            futures[node] = client.submit(leaf_task, job_future, node, key=f"hfrad-leaf-{node}-{token}", pure=False)
        else:
            # a merge goes in as soon as both children are in: Dask then runs it before later leaves
            # (earlier submissions first, merges preferred), which keeps few nodes resident
            left, right = children
            futures[node] = client.submit(merge_task, job_future, node, futures.pop(left), futures.pop(right),
                                          children, key=f"hfrad-merge-{node}-{token}", pure=False, priority=1)
    (last,) = futures.values()  # the root: only it is held, so finished parts are freed as they merge
    root = client.submit(root_task, job_future, last, key=f"hfrad-root-{token}", pure=False, priority=2)
    return root, parents, resumed


class _Tracker:
    """Blocks done and the current rank, from the tasks' progress events (duplicates from retries ignored)."""

    def __init__(self, m: int) -> None:
        self.m, self.parents = m, {}
        self.events: collections.deque = collections.deque()
        self.rank_of: dict[int, int] = {}
        self.leaves_done: set[int] = set()
        self.executions = 0

    def handler(self, event) -> None:  # runs on the client's event-loop thread
        self.events.append(event[1] if isinstance(event, tuple) else event)

    def drain(self) -> bool:
        changed = False
        while self.events:
            msg = self.events.popleft()
            node = int(msg["node"])
            if msg["kind"] == "resumed":
                self.leaves_done.update(int(j) for j in msg["leaves"])
            else:
                self.executions += 1
                if node < self.m:
                    self.leaves_done.add(node)
            self.rank_of[node] = int(msg["rank"])
            changed = True
        return changed

    @property
    def blocks(self) -> int:
        return len(self.leaves_done)

    @property
    def rank(self) -> int:
        return sum(k for node, k in self.rank_of.items() if self.parents.get(node) not in self.rank_of)


def _run(cluster: Cluster, scene, options: PrecomputeOptions, task_threads, checkpoint, progress, status,
         records_out) -> HFactorization:
    from ..formfactors.visibility import DEFAULT_SAMPLES

    client = cluster.client
    n, block_size, m = options.n, options.block_size, options.n_blocks
    _check_worker_memory(cluster, n, block_size)
    saved = set()
    if checkpoint is not None:
        checkpoint = str(Path(checkpoint).resolve())
        saved = store.open_folder(checkpoint, options.key(scene))
    token = uuid.uuid4().hex[:12]
    job = Job(scene=scene, options=options, rows_rho=options.rows_rho(scene), weights=options.stats_weights(scene),
              samples=DEFAULT_SAMPLES if options.samples is None else options.samples,
              ray_budget=options.ray_budget(scene),
              task_threads=task_threads if task_threads is not None else cluster.task_threads, token=token,
              checkpoint=checkpoint)
    t0 = time.perf_counter()
    [job_future] = client.scatter([job], broadcast=True, hash=False)  # the scene travels once per worker
    time_scatter = time.perf_counter() - t0
    tracker = _Tracker(m)
    client.subscribe_topic(job.topic, tracker.handler)  # before the first task can report
    try:
        root, tracker.parents, resumed = _submit(client, job_future, m, token, saved)
        report(progress, 0, m)
        while not root.done():
            time.sleep(_POLL_SECONDS)
            if tracker.drain():
                report(progress, tracker.blocks, m)
                if status is not None:
                    status({"blocks": tracker.blocks, "rank": tracker.rank, "elapsed": time.perf_counter() - t0})
        t_gather = time.perf_counter()
        lowrank, records, stats_state, near = root.result()
        time_gather = time.perf_counter() - t_gather
        tracker.drain()
    except KilledWorker as exc:
        client.cancel([job_future])
        raise WorkerLostError(
            f"{exc}: a task took down {dask.config.get('distributed.scheduler.allowed-failures')} workers in a "
            f"row, usually a worker out of memory; each worker needs about "
            f"{human(sizing.worker_bytes(n, block_size, sizing.rank_guess(n, options.eps)))} here "
            "(docs/cluster.md, 'Memory per worker')") from None
    except BaseException:
        client.cancel([job_future])  # Ctrl-C or a failure: stop the cluster's work on this run
        raise
    finally:
        client.unsubscribe_topic(job.topic)
    wall = time.perf_counter() - t0
    report(progress, m, m)
    del job_future
    lowrank.info.update(_info(records, m, options, cluster, time_scatter, time_gather, wall,
                              tracker.executions, len(resumed)))
    if records_out is not None:
        records_out.extend(records)
    stats = PassStatistics.from_state({**stats_state, "weights": job.weights})
    return assemble(scene, options, lowrank, stats, near,
                    backend={"backend": "dask", "workers": cluster.n_workers})


def _info(records, m, options, cluster, time_scatter, time_gather, wall, executions, resumed) -> dict:
    """Per-stage seconds (summed over the tasks of the final tree) and the run's shape, for the .hfr.

    ``task_executions`` counts the tasks' progress reports: above ``tasks_run`` when
    Dask re-ran tasks of a lost worker (a report still in flight at the end is missed).
    ``tasks_resumed``: nodes read back from a checkpoint (their subtrees were not run).
    """
    leaves = sorted((r for r in records if r["kind"] == "leaf"), key=lambda r: r["node"])
    merges = [r for r in records if r["kind"] == "merge"]
    time_ff = sum(r["formfactors"] for r in leaves)
    time_leaf = sum(r["svd"] for r in leaves)
    time_merge = sum(r["seconds"] for r in merges)
    return {"backend": "dask", "workers": cluster.n_workers, "scheduler": cluster.address,
            "cluster": cluster.kind, "n_blocks": m, "leaf_ranks": [r["rank"] for r in leaves],
            "dtype": options.dtype, "leaf_share": options.leaf_share,
            "time_formfactors": time_ff, "time_leaf": time_leaf, "time_merge": time_merge,
            "time_total": time_leaf + time_merge, "time_scatter": time_scatter, "time_gather": time_gather,
            "time_precompute": wall, "tasks": len(records),
            "tasks_run": sum(1 for r in records if not r.get("resumed")), "tasks_resumed": resumed,
            "task_executions": executions}
