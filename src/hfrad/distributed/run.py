"""The precomputation on a Dask cluster: the HF tree as a task graph.

Leaves (column block generation + truncated SVD) are independent tasks;
sibling merges form a tree reduction of depth ceil(log2 m). The merges covering
more than ``ceil(m / W)`` blocks (the top log2 W levels on W workers) run by
row panels spread over all workers (:mod:`hfrad.distributed.panels`), so no
worker holds a whole n x k factor of the top nodes. The tree is the
one :class:`~hfrad.lowrank.hf.HFStream` builds (:func:`~hfrad.lowrank.hf.counter_tree`)
with the same truncations and error budget, so the result has the same
meaning as the local path (one pass over F, achieved error <= eps) and equals
it up to rounding.
"""

from __future__ import annotations

import collections
import math
import operator
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import dask
import numpy as np
from distributed.scheduler import KilledWorker

from ..errors import MemoryLimitError
from ..formfactors.farfield import FarFieldCertificate, FarFieldStats
from ..lowrank.factors import LowRank
from ..lowrank.hf import counter_tree
from ..memory import human
from ..progress import ProgressCallback, report
from ..precompute.assemble import PrecomputePlan, add_statistics, assemble, concat_near
from ..precompute.backends import DaskBackend
from ..precompute.local import far_field_report
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from . import panels, sizing, store
from .connection import Cluster, WorkerLostError, connect
from ..solve.prefetch import NearPrefetch, prefetch_fits
from . import tiles as tiles_mod
from .tasks import (Job, chunk_task, form_task, gram_task, group_leaf_task, group_tree_task, leaf_task,
                    load_task,
                    merge_task, root_task, small_task, split_meta_task, split_rows_task, split_tail_task,
                    split_v_task, tile_task)

_POLL_SECONDS = 0.2


@dataclass(frozen=True)
class DaskTuning:
    """How :func:`factorize_distributed` cuts HF's tree into tasks; every default suits a run.

    Attributes
    ----------
    panel_leaves : int, optional
        Merges covering more than this many column blocks run by row panels
        (:mod:`hfrad.distributed.panels`): no worker holds the whole of such a node.
        Default :func:`default_panel_leaves` (``ceil(m / workers)``).
    row_panels : int, optional
        Row panels of those merges (default: one per worker).
    tile_group : int, optional
        With the reciprocity copy: blocks per group (default :func:`hfrad.distributed.tiles.default_group`).
    tile_band : int, optional
        With the reciprocity copy: groups at most this far apart share a tile (0: no copy); default
        the widest whose waiting tiles fit ``tile_bytes`` per worker (:func:`hfrad.distributed.tiles.band_for`).
    tile_bytes : int, optional
        Bytes of waiting tiles allowed per worker (default ``TILE_SHARE`` of the smallest worker
        memory limit or, with none, of this machine's available memory).
    near_prefetch : bool
        With the near field, a row-panelled top and an in-process assembly (fewer than
        ``ASSEMBLY_MIN_WORKERS`` workers): factor the channels' ``I - D_c N`` in the client
        while the top merges run (:mod:`hfrad.solve.prefetch`; the same result).
    """

    panel_leaves: int | None = None
    row_panels: int | None = None
    tile_group: int | None = None
    tile_band: int | None = None
    tile_bytes: int | None = None
    near_prefetch: bool = True


def factorize_distributed(scene, options: PrecomputePlan, backend: DaskBackend | None = None, *, checkpoint=None,
                          progress: ProgressCallback = None, status=None,
                          tuning: DaskTuning | None = None) -> HFactorization:
    """Precompute a scene on a Dask cluster: what :func:`hfrad.factorize` does, as Dask tasks.

    Users call ``hfrad.factorize(scene, backend=DaskBackend(...))``, which validates
    the options and comes here; this is the backend.

    Parameters
    ----------
    scene : Scene
    options : PrecomputePlan
        From :func:`hfrad.precompute.options.plan_precompute` (the local path's). With
        ``options.reciprocity`` each pair of groups of blocks within the band is computed
        once and copied by reciprocity (:mod:`hfrad.distributed.tiles`).
    backend : DaskBackend
        The cluster (``scheduler``, or ``workers`` for a LocalCluster; ``scheduler`` may
        also be a :class:`~hfrad.distributed.connection.Cluster` from
        :func:`~hfrad.distributed.connect`), numba threads per task, the connect timeout,
        and ``records``: a list filled with one dict per task of the tree (kind, node,
        rank, columns, rows, seconds, form-factor and SVD seconds, ranks merged, worker,
        resumed), the measured per-task costs behind docs/cluster.md's model, then one dict
        per task of the panelled merges (kind "slice", "gram", "form" or "chunk": node,
        seconds, cpu, rows or columns, ranks). See :class:`hfrad.precompute.backends.DaskBackend`.
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
    tuning : DaskTuning, optional
        How the tree is cut into tasks (row panels, reciprocity tiles, the near-field
        prefetch); the defaults suit every run, the fields are for measurements and tests.

    Returns
    -------
    HFactorization or NearFieldFactorization
        As the local path's (:func:`hfrad.precompute.assemble.assemble`); ``params`` and
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
    statistics (n x 22 floats) and its near entries do, and with the reciprocity
    copy the group-pair tiles (at most ``2 (g b)^2 s`` bytes per tile, ``2 band g b^2 s``
    per leaf: :mod:`hfrad.distributed.tiles`). A worker lost mid-run costs
    only its tasks: Dask recomputes them from the graph. Memory per worker:
    :func:`hfrad.distributed.sizing.worker_bytes`.
    """
    if not isinstance(options, PrecomputePlan):
        raise TypeError("options must come from hfrad.precompute.options.plan_precompute "
                        "(or call hfrad.factorize(scene, backend=hfrad.DaskBackend(...)))")
    backend = DaskBackend() if backend is None else backend
    tuning = DaskTuning() if tuning is None else tuning
    tiling = {"group": tuning.tile_group, "band": tuning.tile_band, "budget_bytes": tuning.tile_bytes}
    run = (scene, options, backend.task_threads, checkpoint, progress, status, backend.records,
           tuning.panel_leaves, tuning.row_panels, tiling, tuning.near_prefetch)
    if isinstance(backend.scheduler, Cluster):
        return _run(backend.scheduler, *run)
    with connect(backend.scheduler, workers=backend.workers, timeout=backend.connect_timeout) as cluster:
        return _run(cluster, *run)


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


#: At most the merges covering more than ``1 / PANELLED_TOP`` of the blocks run by row panels
#: (:func:`default_panel_leaves`): the top ``log2 PANELLED_TOP`` levels of the tree.
PANELLED_TOP = 8


def default_panel_leaves(m: int, workers: int) -> int:
    """Merges covering more than this many of the m leaves run by row panels (:mod:`hfrad.distributed.panels`).

    ``ceil(m / min(workers, PANELLED_TOP))``: below ``m / workers`` there are at least as many
    independent subtrees as workers and whole-node merges keep every worker busy; above, fewer
    merges than workers remain and a merge is the larger (ranks grow with the columns), so it is
    split over all workers. On many workers only the top levels are split: a panelled merge is
    about 3 P + 8 Dask tasks for P row panels (one per worker), so panelling the top ``log2 W``
    levels (W - 1 merges) would cost the scheduler ~3 W^2 tasks, while the merges between
    ``m / W`` and ``m / PANELLED_TOP`` blocks still run side by side, at least PANELLED_TOP at once.
    One worker: none (the node's panels would all be on it anyway).
    """
    return m if workers <= 1 else max(1, -(-m // min(workers, PANELLED_TOP)))


@dataclass
class _Panelled:
    """A node of the tree held by row panels: futures of U's panels, of V's column chunks (in column
    order, one per serial subtree below), of the bookkeeping dict, and of the serial subtrees' tails."""

    U: list
    V: list
    meta: object
    tails: list


def _tree_shape(m: int, n: int, b: int) -> tuple[dict, dict]:
    """Leaves and columns under each node of :func:`counter_tree`'s tree."""
    leaves = {j: 1 for j in range(m)}
    columns = {j: min(b, n - j * b) for j in range(m)}
    for i, (left, right) in enumerate(counter_tree(m)):
        leaves[m + i] = leaves[left] + leaves[right]
        columns[m + i] = columns[left] + columns[right]
    return leaves, columns


def _submit(client, job_future, m: int, token: str, saved: set, *, n: int = 0, block_size: int = 1,
            panel_leaves: int | None = None, bounds=None, workers=(), plan=None, fuse: bool = True):
    """Submit leaves and merges in the order HFStream would run them; returns (final, parents, resumed).

    A node in ``saved`` (a checkpoint's) is read back by a load task and nothing below it is submitted.
    Merges covering more than ``panel_leaves`` leaves run by the row panels ``bounds`` (panel p
    preferably on ``workers[p % len(workers)]``). ``final`` is the root task's future, or a
    :class:`_Panelled` of the root's truncated Q panels and V chunks. With a tile ``plan``
    (:mod:`hfrad.distributed.tiles`) the leaves come from group leaves and tiles, submitted row
    by row as the leaves' order reaches each group; with ``fuse`` (runs without a checkpoint: a
    cancelled task runs on and would drop its children's files under a rerun) a group whose blocks
    form a node of the tree is one task, leaves and merges (:func:`_fused_groups`).
    """
    order = task_order(m)
    parents = {c: node for kind, node, children in order for c in children}
    skipped = set()   # nodes below a saved one
    for kind, node, children in reversed(order):   # parents before their children
        if node in saved or node in skipped:
            skipped.update(children)
    leaves, columns = _tree_shape(m, n, block_size)
    panel_leaves = m if panel_leaves is None else panel_leaves
    futures, resumed = {}, []
    groups = _GroupLeaves(client, job_future, plan, token, set(range(m)) - skipped - saved) \
        if plan is not None else None
    fused = _fused_groups(order, m, plan, skipped | saved, panel_leaves) if plan is not None and fuse else {}
    inside = {x for _, merges in fused.values() for _, left, right in merges for x in (left, right)}
    for kind, node, children in order:
        if node in skipped or node in inside:
            continue
        if node in fused:
            futures[node] = groups.tree(*fused[node])
            continue
        if node in saved:
            futures[node] = client.submit(load_task, job_future, node, key=f"hfrad-load-{node}-{token}", pure=False)
            resumed.append(node)
        elif kind == "leaf" and groups is not None:
            futures[node] = groups.leaf(node)
        elif kind == "leaf":
            futures[node] = client.submit(leaf_task, job_future, node, key=f"hfrad-leaf-{node}-{token}", pure=False)
        elif leaves[node] > panel_leaves:
            left, right = (_as_panels(client, job_future, c, futures.pop(c), bounds, token) for c in children)
            futures[node] = _panel_merge(client, job_future, node, left, right, columns[node], bounds, workers, token)
        else:
            # a merge goes in as soon as both children are in: Dask then runs it before later leaves
            # (earlier submissions first, merges preferred), which keeps few nodes resident
            left, right = children
            futures[node] = client.submit(merge_task, job_future, node, futures.pop(left), futures.pop(right),
                                          children, key=f"hfrad-merge-{node}-{token}", pure=False, priority=1)
    (last,) = futures.values()  # the root: only it is held, so finished parts are freed as they merge
    if isinstance(last, _Panelled):
        Q = [client.submit(panels.root_panel, U, last.meta, key=f"hfrad-rootq-{p}-{token}", priority=2)
             for p, U in enumerate(last.U)]
        V = [client.submit(panels.root_chunk, V, last.meta, key=f"hfrad-rootv-{c}-{token}", priority=2)
             for c, V in enumerate(last.V)]
        return _Panelled(Q, V, last.meta, last.tails), parents, resumed
    root = client.submit(root_task, job_future, last, key=f"hfrad-root-{token}", pure=False, priority=2)
    return root, parents, resumed


def _fused_groups(order, m: int, plan, excluded: set, panel_leaves: int) -> dict:
    """Groups whose leaves and merges run as one task (:func:`~hfrad.distributed.tasks.group_tree_task`).

    A group of at least two blocks is fused when a node of the tree covers exactly its blocks (g a power
    of two, the group whole), none of them is resumed or saved (``excluded``), and that node is merged
    whole (at most ``panel_leaves`` leaves). Returns {group node: (J, ((node, left, right), ...))} with
    the merges under it in the tree's order.
    """
    g = plan.group
    if g < 2 or g > panel_leaves:
        return {}
    span = {j: (j, j + 1) for j in range(m)}
    within: dict = collections.defaultdict(list)   # group -> merges inside it so far
    out = {}
    for kind, node, children in order:
        if kind != "merge":
            continue
        left, right = children
        lo, hi = span[node] = (span[left][0], span[right][1])
        J = lo // g
        if (hi - 1) // g != J:
            continue
        within[J].append((node, left, right))
        if hi - lo == g and not any(x in excluded for x in range(lo, hi)) and node not in excluded:
            out[node] = (J, tuple(within.pop(J)))
    return out


class _GroupLeaves:
    """Submits the tiles and group leaves of a tile plan (:mod:`hfrad.distributed.tiles`) as leaves are asked for.

    ``todo``: the leaves to compute (not resumed). A group with none of them is not computed;
    its tile partners compute its rows themselves. When leaf j is asked for, group J = j // g
    (if not yet submitted) gets its row of tiles ``(J, J+1 .. J+band)`` and then its group leaf;
    leaf j is then a selection task on the group leaf's list of parts.
    """

    def __init__(self, client, job_future, plan, token: str, todo: set) -> None:
        self.client, self.job, self.plan, self.token = client, job_future, plan, token
        self.todo = todo
        self.needed = {plan.group_of(j) for j in todo}
        self.tiles: dict = {}      # (I, J) -> future, until both its group leaves are submitted
        self.groups: dict = {}     # J -> (future of the group leaf, its leaves)

    def _group(self, J: int, merges: tuple | None = None):
        """Submit group J's row of tiles, then its group leaf (with ``merges``: the group's whole tree,
        :func:`~hfrad.distributed.tasks.group_tree_task`)."""
        if J in self.groups:
            return self.groups[J]
        plan, client = self.plan, self.client
        direct, copied = plan.partners(J, self.needed)
        for K in copied:     # this group's row of tiles, then its leaf (row by row: few tiles wait)
            self.tiles[(J, K)] = client.submit(tile_task, self.job, plan, J, K, key=f"hfrad-tile-{J}-{K}-{self.token}",
                                               pure=False)
        leaves = tuple(j for j in plan.blocks_of(J) if j in self.todo)
        inputs = [self.tiles.pop((I, J)) for I in direct] + [self.tiles[(J, K)] for K in copied]
        if merges is None:
            future = client.submit(group_leaf_task, self.job, plan, J, leaves, tuple(direct), tuple(copied),
                                   *inputs, key=f"hfrad-group-{J}-{self.token}", pure=False)
        else:
            future = client.submit(group_tree_task, self.job, plan, J, leaves, tuple(direct), tuple(copied), merges,
                                   *inputs, key=f"hfrad-group-{J}-{self.token}", pure=False)
        self.groups[J] = (future, leaves)
        return self.groups[J]

    def tree(self, J: int, merges: tuple):
        """The future of group J's node: its leaves and the merges among them in one task."""
        return self._group(J, merges)[0]

    def leaf(self, j: int):
        """The future of leaf j's Part."""
        future, leaves = self._group(self.plan.group_of(j))
        return self.client.submit(operator.getitem, future, leaves.index(j), key=f"hfrad-leafpart-{j}-{self.token}",
                                  pure=False)


def _as_panels(client, job_future, node: int, part, bounds, token: str) -> _Panelled:
    """A serial node (the future of a Part) cut into row panels where it lies; a _Panelled unchanged."""
    if isinstance(part, _Panelled):
        return part
    U = [client.submit(split_rows_task, job_future, node, part, int(lo), int(hi),
                       key=f"hfrad-rows-{node}-{p}-{token}", priority=1)
         for p, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:]))]
    return _Panelled(U, [client.submit(split_v_task, part, key=f"hfrad-v-{node}-{token}", priority=1)],
                     client.submit(split_meta_task, part, key=f"hfrad-meta-{node}-{token}", priority=1),
                     [client.submit(split_tail_task, part, key=f"hfrad-tail-{node}-{token}", priority=1)])


def _panel_merge(client, job_future, node: int, left: _Panelled, right: _Panelled, columns: int, bounds,
                 workers, token: str) -> _Panelled:
    """Merge two panelled nodes: Gram per panel, a reduction, the small step, then U's panels and V's chunks."""
    def on(p):   # panel p's worker: a preference (another worker takes it if that one is gone)
        return {"workers": [workers[p % len(workers)]], "allow_other_workers": True} if workers else {}

    P = len(left.U)
    grams = [client.submit(gram_task, job_future, node, p, left.U[p], right.U[p], key=f"hfrad-gram-{node}-{p}-{token}",
                           priority=1, **on(p)) for p in range(P)]
    # the Gram matrices are summed by the small step itself: P - 1 tasks fewer than a reduction tree
    small = client.submit(small_task, job_future, node, grams[0], left.meta, right.meta, columns, P, *grams[1:],
                          key=f"hfrad-small-{node}-{token}", priority=1)
    part = {name: client.submit(operator.getitem, small, name, key=f"hfrad-{name}-{node}-{token}", priority=1)
            for name in ("B", "W1", "W2", "meta")}
    U = [client.submit(form_task, job_future, node, p, left.U[p], right.U[p], part["B"],
                       key=f"hfrad-form-{node}-{p}-{token}", priority=1, **on(p)) for p in range(P)]
    V = [client.submit(chunk_task, job_future, node, V, part[w], key=f"hfrad-chunk-{node}-{side}{c}-{token}",
                       priority=1)
         for side, w, chunks in (("l", "W1", left.V), ("r", "W2", right.V)) for c, V in enumerate(chunks)]
    return _Panelled(U, V, part["meta"], left.tails + right.tails)


class _Tracker:
    """Blocks done and the current rank, from the tasks' progress events (duplicates from retries ignored)."""

    def __init__(self, m: int) -> None:
        self.m, self.parents = m, {}
        self.events: collections.deque = collections.deque()
        self.rank_of: dict[int, int] = {}
        self.leaves_done: set[int] = set()
        self.executions = 0
        self.task_records: list[dict] = []   # the panelled merges' panel tasks

    def handler(self, event) -> None:  # runs on the client's event-loop thread
        self.events.append(event[1] if isinstance(event, tuple) else event)

    def drain(self) -> bool:
        changed = False
        while self.events:
            msg = self.events.popleft()
            if msg["kind"] == "task":
                self.task_records.append(msg["record"])
                continue
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


#: The near-field set-up runs as Dask tasks (one sparse LU per colour channel, then column panels)
#: from this many workers on; below, the client runs it in-process: with two workers the three
#: channels' LUs compete for the cores and the tasks' transfers cost more than they spread
#: (benchmarks/README.md, "Assembly in pieces").
ASSEMBLY_MIN_WORKERS = 3
#: Columns of ``D_c Q`` per task of the cluster's assembly (Neumann sweeps, no LU: a task costs
#: its columns times the sweeps times nnz(N), so narrow panels spread over many workers and
#: shorten the critical path; each panel is a few tasks more at the scheduler).
NEUMANN_COLUMNS = 16


def make_job(scene, options: PrecomputePlan, task_threads: int | None, token: str, checkpoint=None) -> Job:
    """The :class:`~hfrad.distributed.tasks.Job` a run scatters to its workers (also used by
    benchmarks/bench_cluster_model.py to run single tasks)."""
    from ..formfactors.visibility import DEFAULT_SAMPLES

    return Job(scene=scene, options=options, rows_rho=options.rows_rho(scene), weights=options.stats_weights(scene),
               samples=DEFAULT_SAMPLES if options.samples is None else options.samples,
               ray_budget=options.ray_budget(scene), task_threads=task_threads, token=token, checkpoint=checkpoint)


def tile_plan(cluster: Cluster, options: PrecomputePlan, group=None, band=None, budget_bytes=None):
    """The run's :class:`~hfrad.distributed.tiles.TilePlan` (None without the reciprocity copy or with one block).

    The tile budget per worker: ``budget_bytes``, else ``TILE_SHARE`` of the smallest worker memory
    limit, else of this machine's available memory (workers without a limit: assumed alike).
    """
    if not options.reciprocity or options.n_blocks < 2 or options.far_field == "sampled":
        return None       # the sampled far field copies nothing: its leaves evaluate what they need
    if budget_bytes is None:
        limits = [x for x in cluster.worker_memory_limits() if x > 0]
        if limits:
            budget_bytes = int(tiles_mod.TILE_SHARE * min(limits))
        else:
            from ..memory import available_bytes
            budget_bytes = int(tiles_mod.TILE_SHARE * available_bytes())
    return tiles_mod.plan(options.n, options.block_size, np.dtype(options.dtype).itemsize, max(1, cluster.n_workers),
                          group=group, band=band, budget_bytes=budget_bytes)


def _run(cluster: Cluster, scene, options: PrecomputePlan, task_threads, checkpoint, progress, status,
         records_out, panel_leaves=None, row_panels=None, tiling=None, near_prefetch=True) -> HFactorization:
    client = cluster.client
    n, block_size, m = options.n, options.block_size, options.n_blocks
    _check_worker_memory(cluster, n, block_size)
    saved = set()
    if checkpoint is not None:
        checkpoint = str(Path(checkpoint).resolve())
        saved = store.open_folder(checkpoint, options.key(scene))
    token = uuid.uuid4().hex[:12]
    job = make_job(scene, options, task_threads if task_threads is not None else cluster.task_threads, token,
                   checkpoint)
    t0 = time.perf_counter()
    [job_future] = client.scatter([job], broadcast=True, hash=False)  # the scene travels once per worker
    time_scatter = time.perf_counter() - t0
    tracker = _Tracker(m)
    tails = prefetch = None
    client.subscribe_topic(job.topic, tracker.handler)  # before the first task can report
    try:
        addresses = sorted(client.scheduler_info()["workers"])
        if panel_leaves is None:
            panel_leaves = default_panel_leaves(m, len(addresses))
        bounds = panels.panel_bounds(n, len(addresses) if row_panels is None else row_panels)
        plan = tile_plan(cluster, options, **(tiling or {}))
        root, tracker.parents, resumed = _submit(client, job_future, m, token, saved, n=n, block_size=block_size,
                                                 panel_leaves=panel_leaves, bounds=bounds, workers=addresses,
                                                 plan=plan, fuse=checkpoint is None)
        final = [root] if not isinstance(root, _Panelled) else [*root.U, *root.V, root.meta, *root.tails]
        # the near field is complete once the serial subtrees are: an in-process assembly's LUs
        # start then, beside the panelled top merges (hfrad.solve.prefetch)
        early = isinstance(root, _Panelled) and bool(options.near_entries) \
            and cluster.n_workers < ASSEMBLY_MIN_WORKERS and near_prefetch and prefetch_fits(n, options.near_entries)
        report(progress, 0, m)
        while not all(f.done() for f in final):
            time.sleep(_POLL_SECONDS)
            if early and tails is None and all(f.done() for f in root.tails):
                tails = client.gather(list(root.tails))
                prefetch = NearPrefetch(_near_of(tails), n, scene.reflectance, options.perm, options.dtype)
            if tracker.drain():
                report(progress, tracker.blocks, m)
                if status is not None:
                    status({"blocks": tracker.blocks, "rank": tracker.rank, "elapsed": time.perf_counter() - t0})
        t_gather = time.perf_counter()
        if isinstance(root, _Panelled):
            lowrank, records, stats_state, near = _gather_panelled(client, root, n, options, tails)
        else:
            lowrank, records, stats_state, near = root.result()
        del root, final
        time_gather = time.perf_counter() - t_gather
        tracker.drain()
    except KilledWorker as exc:
        client.cancel([job_future])
        if prefetch is not None:
            prefetch.close(wait=False)
        workers = cluster.n_workers
        raise WorkerLostError(
            f"{exc}: a task took down {dask.config.get('distributed.scheduler.allowed-failures')} workers in a "
            f"row, usually a worker out of memory; each worker needs about "
            f"{human(sizing.worker_bytes(n, block_size, sizing.rank_guess(n, options.eps), workers=workers))} here "
            "(docs/cluster.md, 'Memory per worker')") from None
    except BaseException:
        client.cancel([job_future])  # Ctrl-C or a failure: stop the cluster's work on this run
        if prefetch is not None:
            prefetch.close(wait=False)   # nor wait for the LU in flight
        raise
    finally:
        client.unsubscribe_topic(job.topic)
    wall = time.perf_counter() - t0
    report(progress, m, m)
    del job_future
    lowrank.info.update(_info(records, tracker.task_records, m, options, cluster, time_scatter, time_gather, wall,
                              tracker.executions, len(resumed), panel_leaves, bounds.size - 1, plan))
    if options.far_field == "sampled":
        lowrank.info["far_field"] = _far_field_info(records, stats_state, options)
    if records_out is not None:
        records_out.extend(records + tracker.task_records)
    stats = PassStatistics.from_state({**stats_state, "weights": job.weights})
    backend = {"backend": "dask", "workers": cluster.n_workers}
    if cluster.n_workers < ASSEMBLY_MIN_WORKERS:
        if prefetch is None:
            return assemble(scene, options, lowrank, stats, near, backend=backend)
        try:
            fac = assemble(scene, options, lowrank, stats, near, backend=backend, runner=prefetch.runner())
        finally:
            prefetch.close()
        lowrank.info["near_prefetched"] = prefetch.hits   # channels whose LU the prefetch made
        return fac
    from .assembly import assemble_on_cluster

    # no sparse LU on the critical path: every column panel sweeps N on its own worker
    return assemble_on_cluster(cluster.client, scene, options, lowrank, stats, near, backend=backend,
                               records=records_out, neumann=True, columns=NEUMANN_COLUMNS)


def _near_of(tails) -> dict | None:
    """The near entries of gathered tails (records, statistics, near), combined in column order."""
    near = None
    for _, _, nr in tails:
        near = concat_near(near, nr)
    return near


def _gather_panelled(client, root: _Panelled, n: int, options, tails=None) -> tuple:
    """The root's Q (panel by panel into one n x k array) and V, its error, the tails' records, statistics
    and near entries (combined in column order) from a panelled root (``tails``: those already gathered)."""
    meta = root.meta.result()
    k, error = panels.root_error(meta)
    Q = np.empty((n, k), np.dtype(options.dtype))
    row = 0
    for i in range(len(root.U)):
        part = root.U[i].result()
        Q[row:row + part.shape[0]] = part
        row += part.shape[0]
        root.U[i] = None   # frees the panel on its worker
    V = np.concatenate([f.result() for f in root.V]) if root.V else np.zeros((0, k), Q.dtype)
    records, stats, near = [], None, None
    for r, st, nr in (tails if tails is not None else (f.result() for f in root.tails)):
        records += r
        stats, near = add_statistics(stats, st), concat_near(near, nr)
    lowrank = LowRank(Q=Q, V=V, achieved_error=error, norm=math.sqrt(meta["norm2"]), eps=options.eps,
                      relative=options.relative, method="hf", info={})
    return lowrank, records + meta.get("records", []), stats, near


def _far_field_info(records, stats_state: dict, options: PrecomputePlan) -> dict:
    """``info["far_field"]`` of a sampled run, as the local path reports it: the leaves' counters
    added up, the certificate and the held-out check from the summed statistics."""
    tallies = FarFieldStats()
    for r in records:
        if r["kind"] == "leaf":
            tallies = tallies + FarFieldStats.from_state(r["far_field"])
    n, far = options.n, options.far_options
    certificate = FarFieldCertificate.from_state(stats_state, n)
    holdout = None
    if "far_holdout_q" in stats_state:
        holdout = FarFieldCertificate.design(n, far.holdout_rows, far.seed, 2)
        holdout.q = np.asarray(stats_state["far_holdout_q"], np.float64)
    return far_field_report(tallies, certificate, holdout, n)


def _info(records, task_records, m, options, cluster, time_scatter, time_gather, wall, executions, resumed,
          panel_leaves, row_panels, plan=None) -> dict:
    """Per-stage seconds (summed over the tasks of the final tree) and the run's shape, for the .hfr.

    ``task_executions`` counts the tasks' progress reports: above ``tasks_run`` when
    Dask re-ran tasks of a lost worker (a report still in flight at the end is missed).
    ``tasks_resumed``: nodes read back from a checkpoint (their subtrees were not run).
    ``time_merge`` includes the panelled merges' panel tasks (as reported by their events);
    ``time_formfactors`` the tile tasks of the reciprocity copy. ``pairs_computed``: form factors
    the leaves and tiles computed this run (copies excluded; n^2 without the copy and resumption);
    ``tile_group``/``tile_band``: the tile plan (0/0 without the copy).
    """
    leaves = sorted((r for r in records if r["kind"] == "leaf"), key=lambda r: r["node"])
    merges = [r for r in records if r["kind"] == "merge"]
    tiles = [r for r in task_records if r["kind"] == "tile"]
    time_ff = sum(r["formfactors"] for r in leaves) + sum(r["seconds"] for r in tiles)
    time_leaf = sum(r["svd"] for r in leaves)
    time_merge = sum(r["seconds"] for r in merges) + sum(r["seconds"] for r in task_records if r["kind"] != "tile")
    return {"backend": "dask", "workers": cluster.n_workers, "scheduler": cluster.address,
            "cluster": cluster.kind, "n_blocks": m, "leaf_ranks": [r["rank"] for r in leaves],
            "dtype": options.dtype, "leaf_share": options.leaf_share,
            "time_formfactors": time_ff, "time_leaf": time_leaf, "time_merge": time_merge,
            "time_total": time_leaf + time_merge, "time_scatter": time_scatter, "time_gather": time_gather,
            "time_precompute": wall, "tasks": len(records),
            "tasks_run": sum(1 for r in records if not r.get("resumed")), "tasks_resumed": resumed,
            "task_executions": executions, "panel_leaves": int(panel_leaves), "row_panels": int(row_panels),
            "panelled_merges": sum(1 for r in merges if "panels" in r),
            "pairs_computed": sum(r.get("pairs", 0) for r in leaves if not r.get("resumed"))
            + sum(r["pairs"] for r in tiles),
            "tile_group": plan.group if plan is not None else 0, "tile_band": plan.band if plan is not None else 0,
            "tile_tasks": len(tiles), "tile_bytes": sum(r["bytes"] for r in tiles)}
