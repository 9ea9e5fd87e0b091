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


def worker_bytes(n: int, block_size: int, rank: int, itemsize: int = 4, near_entries: int = 0) -> int:
    """Peak bytes of the worker that runs the root merge (the busiest one).

    ``PROCESS + ENGINE n + max(leaf, root merge) + 2 n k s`` for resident nodes waiting for
    their siblings (the frontier of the tree holds at most about 2 n k words):
    the root's children have ranks of at most k each. Other workers need less:
    their merges are lower in the tree, where ranks are smaller. Plus the pass
    statistics of the root's two children and its own (3 x 176 n bytes) and, with the
    near-field split, the near entries of both children and their concatenation
    (2 x 24 bytes x ``near_entries`` n).

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
    """
    return (PROCESS_BYTES + ENGINE_BYTES_PER_PATCH * n
            + max(leaf_bytes(n, block_size), merge_bytes(n, rank, rank, itemsize))
            + 2 * n * rank * itemsize + 3 * STATS_BYTES_PER_PATCH * n
            + 2 * NEAR_BYTES_PER_ENTRY * near_entries * n)
