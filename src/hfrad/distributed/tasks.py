"""What runs on the Dask workers: one leaf per column block, one merge per tree node.

A task returns a :class:`Part`: the HF node (``U``, ``s``, ``V`` and the error
bookkeeping of :mod:`hfrad.lowrank.hf`), the pass statistics and near-field
entries of its columns, plus the records of the tasks below it. The n x b
form-factor block of a leaf is made, split, compressed and dropped inside the
task, so only its factors (n x k_j and b x k_j), statistics and near entries
ever leave the worker.

Everything here trusts its input: :func:`hfrad.precompute.options.plan_precompute`
validated it on the client.
"""

from __future__ import annotations

import copy
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..formfactors.pieces import BlockPieces
from ..lowrank.hf import ErrorBudget, compress_leaf, compress_leaf_pieces, merge_nodes, root_lowrank
from ..lowrank.nearsplit import NearFieldSplit
from ..formfactors.parallel import column_block
from ..formfactors.budget import RayBudget
from ..precompute.assemble import add_statistics, concat_near, far_block, statistics_state
from ..precompute.local import sampled_far_field
from ..solve.stats import PassStatistics
from . import panels, store
from ..resources import numba_threads


@dataclass(frozen=True)
class Job:
    """Everything a task needs, scattered to the workers once per run.

    Attributes
    ----------
    scene : Scene
        The patches; each worker process builds its form-factor engine and
        Embree scene from it once (:func:`hfrad.formfactors.parallel.column_block`).
    options : PrecomputePlan
        The validated options (:mod:`hfrad.precompute.options`), the local path's:
        internal order ``perm``, block size, dtype, error budget, near-field radius.
    rows_rho : (n, 1) of the factors' dtype
        ``rho_max`` in internal order: a block of G is ``rows_rho * F[perm][:, cols]``.
    weights : (n,) float64
        Patch areas in internal order (the pass statistics' norm).
    samples : int
        Visibility rays per pair.
    ray_budget : RayBudget or None
        Fewer rays for weak pairs (the local path's thresholds).
    task_threads : int or None
        Threads of the numba kernel inside one task (None: the worker's setting).
    token : str
        Names this run (task keys, the progress topic).
    checkpoint : str or None
        Folder the finished parts are saved to (:mod:`hfrad.distributed.store`).
    """

    scene: object
    options: object
    rows_rho: np.ndarray
    weights: np.ndarray | None
    samples: int
    ray_budget: RayBudget | None
    task_threads: int | None
    token: str
    checkpoint: str | None = None

    @property
    def perm(self) -> np.ndarray:
        return self.options.perm

    @property
    def budget(self) -> ErrorBudget:
        return self.options.budget

    @property
    def topic(self) -> str:
        """The Dask event topic the tasks of this run report to."""
        return f"hfrad-progress-{self.token}"


@dataclass
class Part:
    """A factored column range, what the pass recorded on it, and the records of the tasks that made it.

    ``stats``: the pass statistics of these columns (:func:`~hfrad.precompute.assemble.far_block`,
    additive). ``near``: their near-field entries (None without the split). ``records`` has one
    dict per task in the subtree: ``kind`` ("leaf" or "merge"), ``node``, ``rank``, ``columns``,
    ``rows``, ``seconds`` (task wall time), ``cpu`` (CPU seconds of the worker process during the
    task: with one task at a time, the task's own, and not inflated by other processes competing
    for the cores), ``formfactors``, ``svd`` and ``cpu_formfactors`` seconds (leaves),
    ``ranks_in`` (merges), ``worker``, ``resumed`` (read back from a checkpoint, not run now),
    ``pairs`` (leaves: form factors computed for the block, copies excluded; with the reciprocity
    copy also ``group`` and ``copied_rows``: :mod:`hfrad.distributed.tiles`).
    """

    node: object
    records: list = field(default_factory=list)
    stats: dict | None = None
    near: dict | None = None


# Each task runs its kernels with the job's ``task_threads`` numba threads (numba_threads). BLAS stays at
# one thread, as in the local path: Dask's nanny starts workers with OPENBLAS_NUM_THREADS=1, and a
# multi-threaded BLAS beside busy cores spin-waits (10-50x slower small SVDs, see hfrad.pipeline).


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


#: One near-field splitter (its k-d tree of the centroids) per worker process and run.
_SPLITS: dict = {}


def _splitter(job: Job) -> NearFieldSplit:
    """A splitter with empty coordinate lists, sharing the worker's k-d tree (read-only, so threads of
    one worker process may run leaves at once: each gets its own lists)."""
    template = _SPLITS.get(job.token)
    if template is None:
        _SPLITS.clear()
        template = _SPLITS[job.token] = NearFieldSplit(job.scene.centroids[job.perm], job.options.near_radius)
    split = copy.copy(template)
    split.rows, split.cols, split.values = [], [], []
    return split


def _saved(job: Job, node_id: int, part: Part, children=()) -> Part:
    """Save ``part`` to the run's checkpoint folder (if any), then drop its children's files."""
    if job.checkpoint is not None:
        store.save_part(job.checkpoint, node_id, part)
        for child in children:
            store.drop_part(job.checkpoint, child)
    return part


#: One sampled far field (engines, cluster pairs) per worker process and run; the lock keeps its
#: tallies one leaf's at a time where a worker runs tasks in several threads.
_FAR: dict = {}
_FAR_LOCK = threading.Lock()


def _sampled_block(job: Job, j: int):
    """Column block ``j`` from the run's sampled far field, the local path's producer (made once a
    worker process): its pieces in the factors' dtype, the exact rows the per-solve samples want,
    and this block's tallies (counters, certificate, held-out check) for the client to add up."""
    with _FAR_LOCK:
        producer = _FAR.get(job.token)
        if producer is None:
            for old in _FAR.values():
                old.close()
            _FAR.clear()
            n = job.perm.size
            design = PassStatistics(n, job.weights, reflectance=job.scene.reflectance[job.perm])
            ff_kwargs = {"samples": job.samples, **({"ray_budget": job.ray_budget} if job.samples else {})}
            producer = _FAR[job.token] = sampled_far_field(job.scene, job.options, design, ff_kwargs)
        producer.fresh_tallies()
        with numba_threads(job.task_threads):
            pieces, exact = producer.block(j)
        return pieces.astype(job.options.dtype), exact, (producer.stats, producer.certificate, producer.holdout)


def leaf_task(job: Job, j: int) -> Part:
    """Leaf ``j``: column block ``G[:, cols_j]`` of ``G = diag(rho_max) F``, as the local path treats it.

    The block's pass statistics, its near entries moved out (with the split), then the
    truncated SVD of the rest within the leaf's share of the budget of the block's full
    norm. Returns those (n x k_j, k_j, b x k_j factors, the statistics, the sparse near
    entries), never the block. The block is the local path's, value for value (same
    engine, ray budget and dtype). Peak memory: the float64 block (8 n b bytes), its dtype
    copies and the SVD's workspace, about 25 n b bytes with float32 factors.
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    if job.options.far_field == "sampled":
        F, exact, tallies = _sampled_block(job, j)
        t1, cpu1 = time.perf_counter(), time.process_time()
        return leaf_from_block(job, j, F, t0, cpu0, t1, cpu1, pairs=int(tallies[0].pairs),
                               extra={"far_field": tallies[0].state()}, exact_rows=exact, far=tallies[1:])
    b = job.options.block_size
    cols = job.perm[j * b:(j + 1) * b]
    with numba_threads(job.task_threads):
        F = column_block(job.scene, cols, order=job.perm, samples=job.samples, ray_budget=job.ray_budget,
                         dtype=job.options.dtype)
    t1, cpu1 = time.perf_counter(), time.process_time()
    return leaf_from_block(job, j, F, t0, cpu0, t1, cpu1, pairs=int(F.size))


def leaf_from_block(job: Job, j: int, F, t0: float, cpu0: float, t1: float, cpu1: float,
                    pairs: int, extra: dict | None = None, exact_rows: np.ndarray | None = None,
                    far: tuple | None = None) -> Part:
    """The leaf of column block ``j`` from its n x b block ``F`` (what :func:`leaf_task` does once F is made).

    ``t0``/``cpu0``: wall and CPU clock when the leaf's form factors started, ``t1``/``cpu1``
    when they were done; ``pairs``: form factors computed for this block (copies excluded);
    ``extra``: more fields for the leaf's record. From the sampled far field, ``F`` is in
    pieces (:class:`~hfrad.formfactors.pieces.BlockPieces`), ``exact_rows`` are the exact rows
    at the per-solve samples' patches, and ``far`` the block's (certificate, held-out check).
    """
    b = job.options.block_size
    start = j * b
    n = job.perm.size
    rho = None if job.scene is None else job.scene.reflectance[job.options.perm]   # the smoothed rows' R_c
    block_stats = PassStatistics(n, job.weights, reflectance=rho)
    if far is not None:
        block_stats.far_field = far[0]
    split = _splitter(job) if job.options.near_entries else None
    G, norm2, block_norm2 = far_block(block_stats, start, start + F.shape[1], F, job.rows_rho, split,
                                      exact_rows=exact_rows)
    del F
    stats = statistics_state(block_stats)
    if far is not None and far[1] is not None:
        stats["far_holdout_q"] = far[1].q
    near = None if split is None else split.state()
    leaf = compress_leaf_pieces if isinstance(G, BlockPieces) else compress_leaf
    node = leaf(G, job.budget, j, norm2, block_norm2)
    columns = int(G.shape[1])
    del G
    t2 = time.perf_counter()
    rank = int(node.s.size)
    record = {"kind": "leaf", "node": j, "rank": rank, "columns": columns, "rows": int(n),
              "seconds": t2 - t0, "formfactors": t1 - t0, "svd": t2 - t1,
              "cpu": time.process_time() - cpu0, "cpu_formfactors": cpu1 - cpu0, "pairs": int(pairs),
              "worker": _worker_name()}
    part = Part(node, [record | (extra or {})], stats, near)
    _saved(job, j, part)
    _announce(job, {"node": j, "kind": "leaf", "rank": rank})
    return part


# -- The reciprocity copy (hfrad.distributed.tiles): group-pair tiles and group leaves -----------------

def tile_task(job: Job, plan, I: int, J: int) -> np.ndarray:
    """Tile ``(I, J)`` of :mod:`hfrad.distributed.tiles`: ``F[rows of group I, cols of group J]`` in the
    factors' dtype (gb x gb), for group J's leaves as it is and group I's by reciprocity."""
    t0, c0 = time.perf_counter(), time.process_time()
    rows, cols = plan.rows(I), plan.rows(J)
    with numba_threads(job.task_threads):
        T = column_block(job.scene, job.perm[cols], order=job.perm[rows], samples=job.samples,
                         ray_budget=job.ray_budget, dtype=job.options.dtype)
    _record(job, {"kind": "tile", "node": int(J), "group_rows": int(I), "rows": int(T.shape[0]),
                  "columns": int(T.shape[1]), "pairs": int(T.size), "bytes": int(T.nbytes),
                  "seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0})
    return T


def group_leaf_task(job: Job, plan, J: int, leaves: tuple, direct_groups: tuple, copied_groups: tuple,
                    *tiles: np.ndarray) -> list:
    """The leaves ``leaves`` (block numbers) of group J, their rows from the tiles where a tile has them.

    ``tiles``: the tiles (I, J) of ``direct_groups`` (in that order), then the tiles (J, K) of
    ``copied_groups``. Each leaf computes the other rows (:meth:`~hfrad.distributed.tiles.TilePlan.own_rows`),
    fills the rest from the tiles (:func:`~hfrad.distributed.tiles.fill_block`) and runs
    :func:`leaf_from_block`. Returns the leaves' parts, in the order of ``leaves``. The tiles'
    own cost is in their tile tasks' records, not in the leaves'.
    """
    from .tiles import diagonal_tile

    direct = dict(zip(direct_groups, tiles[:len(direct_groups)]))
    copied = dict(zip(copied_groups, tiles[len(direct_groups):]))
    skip = np.zeros(plan.n, bool)
    for K in (J, *direct_groups, *copied_groups):
        skip[plan.rows(K)] = True
    own = np.flatnonzero(~skip)
    areas = np.asarray(job.scene.areas, np.float64)[job.perm]
    copied_rows = int(skip.sum()) - sum(plan.rows(I).stop - plan.rows(I).start for I in (J, *direct_groups))
    t0, cpu0 = time.perf_counter(), time.process_time()
    diag = diagonal_tile(plan, J, areas, lambda rows, cols: _block(job, rows, cols))
    # the diagonal tile serves all the group's blocks: each leaf's record carries its share
    share = (time.perf_counter() - t0) / len(leaves), (time.process_time() - cpu0) / len(leaves)
    diag_pairs = plan.diagonal_pairs(J) / len(leaves)
    parts = []
    for j in leaves:
        t0, cpu0 = time.perf_counter() - share[0], time.process_time() - share[1]
        F = group_block(job, plan, J, j, own, areas, direct, copied, diag)
        t1, cpu1 = time.perf_counter(), time.process_time()
        parts.append(leaf_from_block(job, j, F, t0, cpu0, t1, cpu1, pairs=int(own.size * F.shape[1] + diag_pairs),
                                     extra={"group": int(J), "copied_rows": copied_rows}))
        del F
    return parts


def group_tree_task(job: Job, plan, J: int, leaves: tuple, direct_groups: tuple, copied_groups: tuple,
                    merges: tuple, *tiles: np.ndarray) -> Part:
    """Group J's leaves (:func:`group_leaf_task`) and then the tree's merges among them, in one task.

    ``merges``: ``(node, left, right)`` of the merges whose leaves are all in the group, in the tree's
    order (:func:`hfrad.distributed.run.task_order`); the last one is the group's node. Each is
    :func:`merge_task` (the same records, events and checkpoint files as a merge task of its own).
    One task instead of ``2 g`` (g leaf selections and g - 1 merges): the scheduler's cost per task
    is what limits a large cluster, and the merges of a group's small leaves cost little.
    Returns the group node's Part.
    """
    parts = dict(zip(leaves, group_leaf_task(job, plan, J, leaves, direct_groups, copied_groups, *tiles)))
    for node, left, right in merges:
        parts[node] = merge_task(job, node, parts.pop(left), parts.pop(right), (left, right))
    (part,) = parts.values()
    return part


def _block(job: Job, rows: slice, cols: slice) -> np.ndarray:
    """F of internal positions ``rows`` x ``cols`` in the factors' dtype."""
    with numba_threads(job.task_threads):
        return column_block(job.scene, job.perm[cols], order=job.perm[rows], samples=job.samples,
                            ray_budget=job.ray_budget, dtype=job.options.dtype)


def group_block(job: Job, plan, J: int, j: int, own: np.ndarray, areas: np.ndarray, direct: dict,
                copied: dict, diag: np.ndarray) -> np.ndarray:
    """Column block j (of group J), n x b in the factors' dtype: rows ``own`` (internal positions)
    computed here, group J's rows from its diagonal tile ``diag`` (:func:`hfrad.distributed.tiles.diagonal_tile`),
    the others from the tiles (:func:`hfrad.distributed.tiles.fill_block`)."""
    from .tiles import fill_block

    b = job.options.block_size
    cols = job.perm[j * b:(j + 1) * b]
    with numba_threads(job.task_threads):
        mine = column_block(job.scene, cols, order=job.perm[own], samples=job.samples,
                            ray_budget=job.ray_budget, dtype=job.options.dtype)
    F = np.empty((plan.n, cols.size), mine.dtype)
    F[own] = mine
    del mine
    lo = j * b - plan.rows(J).start
    F[plan.rows(J)] = diag[:, lo:lo + cols.size]
    fill_block(F, plan, J, j, areas, direct, copied)
    return F


def merge_task(job: Job, node_id: int, left: Part, right: Part, children: tuple = ()) -> Part:
    """Merge two sibling parts (``left`` covers the earlier columns) within the node's error share.

    Their statistics add, their near entries are concatenated. Peak memory about
    ``7 n (k_left + k_right)`` words: both children's U, the orthogonalised block, and
    the merged U with its two products. ``children``: the child node ids, whose
    checkpoint files are dropped once this node's are written.
    """
    t0, cpu0 = time.perf_counter(), time.process_time()
    node = merge_nodes(left.node, right.node, job.budget, f"merge node {node_id}")
    seconds = time.perf_counter() - t0
    rank = int(node.s.size)
    own = {"kind": "merge", "node": node_id, "rank": rank, "rows": int(job.perm.size),
           "columns": int(node.V.shape[0]), "ranks_in": [int(left.node.s.size), int(right.node.s.size)],
           "seconds": seconds, "cpu": time.process_time() - cpu0, "worker": _worker_name()}
    part = Part(node, left.records + right.records + [own], add_statistics(left.stats, right.stats),
                concat_near(left.near, right.near))
    _saved(job, node_id, part, children)
    _announce(job, {"node": node_id, "kind": "merge", "rank": rank})
    return part


def load_task(job: Job, node_id: int) -> Part:
    """Node ``node_id`` as a finished run saved it (a rerun skips its subtree)."""
    node, stats, near, records = store.load_part(job.checkpoint, node_id)
    for r in records:
        r["resumed"] = True
    _announce(job, {"node": node_id, "kind": "resumed", "rank": int(node.s.size),
                    "leaves": [r["node"] for r in records if r["kind"] == "leaf"]})
    return Part(node, records, stats, near)


def root_task(job: Job, root: Part) -> tuple:
    """``Q V^T`` of the root with its achieved error (``Q`` and ``V`` are n x k), the task records,
    the statistics and the near entries of all columns."""
    return root_lowrank(root.node, job.options.eps, job.options.relative), root.records, root.stats, root.near


# -- Panelled merges (hfrad.distributed.panels): the top of the tree, by row panels ---------------------

def _record(job: Job, rec: dict) -> None:
    """Send a panel task's record (kind, node, seconds, cpu, sizes) to the client with the progress events."""
    rec["worker"] = _worker_name()
    _announce(job, {"node": rec["node"], "kind": "task", "record": rec})


def node_meta(node) -> dict:
    """The small bookkeeping of a node (singular values, norms, discards, slack) a panelled merge needs."""
    return {"s": np.asarray(node.s, np.float64), "norm2": float(node.norm2),
            "discarded2": float(node.discarded2), "slack2": float(node.slack2)}


def split_meta_task(part: Part) -> dict:
    """A serial part's bookkeeping, for the panelled merge above it."""
    return node_meta(part.node)


def split_rows_task(job: Job, node_id: int, part: Part, lo: int, hi: int) -> np.ndarray:
    """Rows ``lo:hi`` of a serial part's U (runs where the part is; the panel then moves alone)."""
    out, rec = panels.timed("slice", node_id, lambda: np.ascontiguousarray(part.node.U[lo:hi]),
                            rows=int(hi - lo), bytes=int((hi - lo) * part.node.U.shape[1] * part.node.U.itemsize))
    _record(job, rec)
    return out


def split_v_task(part: Part) -> np.ndarray:
    """A serial part's V: one column chunk of every panelled node above it (stays on this worker)."""
    return part.node.V


def split_tail_task(part: Part) -> tuple:
    """A serial part's records, statistics and near entries (gathered by the client at the end)."""
    return part.records, part.stats, part.near


def gram_task(job: Job, node_id: int, p: int, U1: np.ndarray, U2: np.ndarray) -> np.ndarray:
    """Panel ``p``'s float64 Gram matrix of ``[U1 U2]`` (:func:`hfrad.distributed.panels.panel_gram`)."""
    G, rec = panels.timed("gram", node_id, panels.panel_gram, U1, U2, panel=int(p), rows=int(U1.shape[0]),
                          ranks_in=[int(U1.shape[1]), int(U2.shape[1])])
    _record(job, rec)
    return G


def small_task(job: Job, node_id: int, G: np.ndarray, left: dict, right: dict, columns: int,
               panel_count: int, *more_grams: np.ndarray) -> dict:
    """The small step of panelled merge ``node_id`` (:func:`hfrad.distributed.panels.merge_small`).

    ``G`` and ``more_grams``: the panels' Gram matrices, summed here (one task instead of a
    reduction tree of ``P - 1``: P (K x K) float64 matrices are a few MB each).
    """
    t0, c0 = time.perf_counter(), time.process_time()
    if more_grams:
        G = G.copy()
        for other in more_grams:
            G += other
    out = panels.merge_small(G, left, right, job.budget.merge(left["norm2"] + right["norm2"]))
    rank = int(out["meta"]["s"].size)
    own = {"kind": "merge", "node": int(node_id), "rank": rank, "rows": int(job.perm.size), "columns": int(columns),
           "ranks_in": [int(left["s"].size), int(right["s"].size)], "panels": int(panel_count),
           "seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0, "worker": _worker_name()}
    out["meta"]["records"] = left.get("records", []) + right.get("records", []) + [own]
    _announce(job, {"node": node_id, "kind": "merge", "rank": rank})
    return out


def form_task(job: Job, node_id: int, p: int, U1: np.ndarray, U2: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Panel ``p`` of the merged U (:func:`hfrad.distributed.panels.panel_form`)."""
    U, rec = panels.timed("form", node_id, panels.panel_form, U1, U2, B, np.dtype(job.options.dtype),
                          panel=int(p), rows=int(U1.shape[0]), ranks_in=[int(U1.shape[1]), int(U2.shape[1])],
                          rank=int(B.shape[1]))
    _record(job, rec)
    return U


def chunk_task(job: Job, node_id: int, V: np.ndarray, W: np.ndarray) -> np.ndarray:
    """A column chunk of the merged V (:func:`hfrad.distributed.panels.chunk_update`)."""
    out, rec = panels.timed("chunk", node_id, panels.chunk_update, V, W, columns=int(V.shape[0]),
                            ranks_in=[int(W.shape[0])], rank=int(W.shape[1]))
    _record(job, rec)
    return out
