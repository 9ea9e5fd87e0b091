"""Memory one Dask worker needs for a precompute, as a function of n, the block size and the rank.

docs/cluster.md explains the terms; benchmarks/bench_dask.py measures them.
"""

from __future__ import annotations

import math

# A worker process with Python, numpy, scipy, numba, Dask and hfrad imported (RSS, measured).
PROCESS_BYTES = 160 * 2**20
# Bytes per patch of the scene and the worker's form-factor engine (geometry,
# sample points, culling bit masks, Embree BVH), measured on the Cornell box.
ENGINE_BYTES_PER_PATCH = 2048
# A leaf holds the float64 block (8 n b), its ray mask (n b), the working-dtype
# copy and the SVD workspace (about 4 n b each for float32): about 25 n b bytes.
LEAF_BYTES_PER_ENTRY = 25
# A merge of children of ranks k1, k2 holds both U's, the orthogonalised block
# and the merged U with its two partial products: about 7 n (k1 + k2) words.
MERGE_WORDS_PER_ROW_RANK = 7
# A part's pass statistics: row sums, column sums and the 20-probe sketch, float64.
STATS_BYTES_PER_PATCH = 22 * 8
# A near entry on its way up the tree: row, column (int64) and value (float64).
NEAR_BYTES_PER_ENTRY = 24


def rank_guess(n: int, eps: float = 0.02) -> int:
    """A rough rank for the memory estimate: ~19 sqrt(n) at eps 0.02, growing like 1/sqrt(eps).

    Fitted to the Cornell box (1,869 at 10K patches, 3,849 at 40K, eps 0.02);
    real scenes differ, which is why :func:`worker_bytes` takes the rank.
    """
    return int(min(n, math.ceil(19.0 * math.sqrt(n) * math.sqrt(0.02 / eps))))


def leaf_bytes(n: int, block_size: int) -> int:
    """Peak bytes of one leaf task beyond the engine: the block and its SVD."""
    return LEAF_BYTES_PER_ENTRY * n * block_size


def merge_bytes(n: int, rank_left: int, rank_right: int, itemsize: int = 4) -> int:
    """Peak bytes of one merge task whose children have ranks ``rank_left`` and ``rank_right``."""
    return MERGE_WORDS_PER_ROW_RANK * n * (rank_left + rank_right) * itemsize


#: A panelled merge's rows on one worker, in words per row per rank: both children's panels (2),
#: the merged panel (1) and, at the root, its truncated Q panel (1); plus V's column chunks there
#: (input and output, 2 words per column per rank; the columns are spread like the subtrees).
PANEL_WORDS_PER_ROW_RANK = 4
CHUNK_WORDS_PER_COLUMN_RANK = 2
#: The small step of a panelled merge (K = 2k): the float64 Gram matrix, its scaled copy, the
#: eigenvectors and eigh's workspace (5 K^2), B and W's blocks (2 K k): 24 k^2 float64 words.
SMALL_WORDS_PER_RANK2 = 24


def root_worker_bytes(n: int, rank: int, workers: int, itemsize: int = 4) -> int:
    """Bytes the root's merge puts on one worker when merges run by row panels (one panel per worker).

    ``(4 + 2) n k s / W + 192 k^2``: a fraction ``6 / W`` of the n k factor words per worker
    (its row panels of both children, of the merged U and of the root's Q, and V's chunks there)
    plus, on the one worker of the small step, ``24 k^2`` float64 words. One worker: the whole
    merge, :func:`merge_bytes`.
    """
    if workers <= 1:
        return merge_bytes(n, rank, rank, itemsize)
    words = (PANEL_WORDS_PER_ROW_RANK + CHUNK_WORDS_PER_COLUMN_RANK) * n * rank / workers
    return int(words * itemsize + SMALL_WORDS_PER_RANK2 * 8 * rank * rank)


def worker_bytes(n: int, block_size: int, rank: int, itemsize: int = 4, near_entries: int = 0,
                 workers: int = 1, tasks: int = 1, transition_rank: int | None = None) -> int:
    """Peak bytes of the busiest worker.

    One worker: ``PROCESS + ENGINE n + max(tasks x leaf, root merge) + 2 n k s`` for resident
    nodes waiting for their siblings (the frontier of the tree holds at most about 2 n k words):
    the root's children have ranks of at most k each. Plus the pass statistics of the root's two
    children and its own (3 x 176 n bytes) and, with the near-field split, the near entries of
    both children and their concatenation (2 x 24 bytes x ``near_entries`` n).

    W > 1 workers, the merges above ``ceil(m / W)`` blocks by row panels
    (:mod:`hfrad.distributed.panels`): ``PROCESS + ENGINE n + max(tasks x leaf, transition,
    root share)`` with the transition the last whole merge (children of rank k_t, plus its
    rows cut into panels: ``14 n k_t s + n k_t s``) and the root share
    :func:`root_worker_bytes` (``6 n k s / W + 192 k^2``); the statistics as above and the
    worker's share of the near entries (``2 x 24 x near_entries n / W``: the client gathers
    them from the subtrees, no worker concatenates them all).

    Parameters
    ----------
    n : int
        Patches.
    block_size : int
        Columns per leaf (b).
    rank : int
        The final rank k (unknown before the run: see :func:`rank_guess`).
    itemsize : int
        4 for float32 factors, 8 for float64.
    near_entries : int
        Near entries per row (0 without the split; 120 with ``near_field="auto"``).
    workers : int
        Workers W of the cluster (the row panels: one per worker).
    tasks : int
        Tasks a worker runs at once (its Dask threads).
    transition_rank : int, optional
        Rank of the largest node merged whole (covering ``ceil(m / W)`` blocks); default ``rank``
        (an upper bound: ranks grow with the columns a node covers).
    """
    base = PROCESS_BYTES + ENGINE_BYTES_PER_PATCH * n + 3 * STATS_BYTES_PER_PATCH * n
    leaves = tasks * leaf_bytes(n, block_size)
    if workers <= 1:
        return (base + max(leaves, merge_bytes(n, rank, rank, itemsize)) + 2 * n * rank * itemsize
                + 2 * NEAR_BYTES_PER_ENTRY * near_entries * n)
    kt = rank if transition_rank is None else transition_rank
    transition = merge_bytes(n, kt, kt, itemsize) + n * kt * itemsize
    return int(base + max(leaves, transition, root_worker_bytes(n, rank, workers, itemsize))
               + 2 * NEAR_BYTES_PER_ENTRY * near_entries * n / workers)
