"""The form-factor matrix as an H-matrix: near blocks exact, far blocks low rank, never all n² pairs.

The patches are ordered along a *cluster tree* (:func:`cluster_tree`): each node is a
contiguous range of that order whose patches lie in a compact box, halved at the median
of its longest side down to ``leaf_size`` patches. Pairs of nodes are then taken from the
root down (:func:`block_partition`):

- a pair of nodes R, C is **far** (admissible) when the gap between their boxes is at least
  ``eta`` times the larger box's diagonal: seen from anywhere in R the unoccluded kernel
  varies smoothly over C, so ``F[R, C]`` has a low rank *if* visibility is all or nothing;
- two leaves that are not far are **near**: every pair computed, with visibility, as in the
  exact pass.

A far pair's visibility is decided without rays by the conservative cluster-pair test of
:mod:`hfrad.formfactors.clustervis` on the two nodes' boxes: VISIBLE (``F`` is the unoccluded
kernel: adaptive cross approximation from a few of its rows and columns,
:mod:`hfrad.formfactors.aca`), BLOCKED (``F = 0``: nothing stored) or MIXED (a shadow edge, a
contact: the larger node is halved until both have at most ``probe_size`` patches, then
``PROBES`` rays from each row patch decide that row; rows whose rays disagree are probed again
against each half of the column node, down to a leaf, where they are computed with
``edge_rays`` segments a pair). A VISIBLE block whose cross approximation does not converge
within ``max_rank`` is computed exactly.

At n patches this evaluates O(n log n) pairs instead of n² (``pairs_evaluated``), and
holds ``storage`` floats (dense entries plus ``r (m + b)`` a far block). G = diag(rho) F is
then applied to blocks of vectors (:meth:`FormFactorHMatrix.matmat`, ``rmatmat``): the
global low-rank factors come from products only (:mod:`hfrad.lowrank.operator`).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np
import scipy.sparse as sp
from numba import njit, prange

from ..memory import release_freed_memory
from ..progress import ProgressCallback, report
from ..resources import numba_loops_at_once, numba_threads
from .bfloat16 import stored_value, to_bfloat16, value_dtype
from .clustervis import BLOCKED, CLUSTER_SIZE, MIXED, VISIBLE, _cluster_pair_states
from .engine import FormFactorEngine
from .hashed_rays import probe_counts, scale_by_edge_visibility

__all__ = ["ClusterTree", "cluster_tree", "block_partition", "FormFactorHMatrix", "build_hmatrix",
           "HMatrixOptions", "default_values", "BFLOAT16_FROM",
           "block_squares", "HMatrixPairs", "hmatrix_pairs", "split_into_parts", "build_part",
           "join_blocks", "join_parts"]

#: Patches in a leaf of the cluster tree.
LEAF_SIZE = 32
#: Admissibility: far when gap >= ETA x the larger diagonal.
ETA = 0.5
#: Rank at which a far block's cross approximation gives up (the block is computed exactly).
MAX_RANK = 24
#: Mixed far pairs are halved until both nodes have at most this many patches, then probed row by row.
PROBE_SIZE = 256
#: Rays from a row patch to patches spread over a mixed column node.
PROBES = 6
#: More rays from each row whose first ``PROBES`` agreed, where other rows of its pair disagreed.
MORE_PROBES = 8
#: Rays per pair in the rows computed exactly across a shadow edge (a mixed row against a leaf):
#: the pair's visibility is the unblocked share of this many segments. 0 gives them the engine's
#: full visibility (probes, boundary rays, second round), about 8 rays a pair there. Cornell box,
#: 39,482 patches: build 38.6 s with the engine, 28.8 s with 4 rays, 25.1 s with 2; error on 192
#: exact rows 0.48%, 0.54%, 0.58%. Šibenik, 10,181 patches: 50.1 s and 2.1% with the engine,
#: 30.2 s and 2.7% with 4 rays. The certificate's exact rows keep the engine's visibility.
EDGE_RAYS = 4


#: ``far_field="hierarchical"`` holds the H-matrix's values as bfloat16 from this many patches
#: (:func:`default_values`). Cornell box, 39,482 patches, both ways from one engine: 416 MB of blocks
#: against 234 MB, the products with 64 vectors 0.537 s both, their results 0.18% apart (Frobenius),
#: the rows 0.23%: under a twentieth of eps 0.05. Below it the H-matrix takes under 1.5 GB and float32
#: keeps the closed-form checks (rows of a closed scene summing to 1) to float32's rounding.
BFLOAT16_FROM = 100_000


def default_values(n: int) -> str:
    """How ``far_field="hierarchical"`` holds the values of an H-matrix of n patches: "bfloat16" from
    :data:`BFLOAT16_FROM` patches (half the bytes: the H-matrix is most of its memory), else "float32"."""
    return "bfloat16" if n >= BFLOAT16_FROM else "float32"


#: The dtype of the blocks' row numbers (tree positions, below n): int32 halves what int64 took, 0.74 of
#: 3.5 GiB at 161,808 Cornell-box patches. Checkpoints written with int64 load as they are.
ROW_INDEX = np.int32


@dataclass(frozen=True)
class HMatrixOptions:
    """How the H-matrix of F is built (defaults for a first run).

    Attributes
    ----------
    leaf_size : int
        Patches in a leaf of the cluster tree (near blocks are at most leaf x leaf).
    eta : float
        A pair of clusters is far when the gap between their boxes is at least ``eta`` times
        the larger box's diagonal.
    tolerance : float
        Relative Frobenius error allowed in each far block's cross approximation.
    max_rank : int
        A far block needing more is computed exactly.
    probe_size : int
        Mixed far pairs are halved until both clusters have at most this many patches; then
        each row patch casts ``PROBES`` rays to the column cluster.
    edge_rays : int
        Rays per pair in the rows computed exactly across a shadow edge (``EDGE_RAYS``); 0 gives
        them the engine's full visibility (slower, a little more accurate).
    values : {"float32", "bfloat16"}
        How the blocks' values (dense entries, low-rank factors) are held: float32, or bfloat16
        (:mod:`hfrad.formfactors.bfloat16`: half the bytes, each value within 2^-8 = 0.39% of its
        float32, 0.17% root mean square; the products, squares and rows read them as float32).
    """

    leaf_size: int = LEAF_SIZE
    eta: float = ETA
    tolerance: float = 0.01
    max_rank: int = MAX_RANK
    probe_size: int = PROBE_SIZE
    edge_rays: int = EDGE_RAYS
    values: str = "float32"

    def replace(self, **changes) -> "HMatrixOptions":
        return dataclasses.replace(self, **changes)

    def __post_init__(self) -> None:
        if not (isinstance(self.edge_rays, (int, np.integer)) and 0 <= self.edge_rays <= 256):
            raise ValueError(f"edge_rays must be an integer in [0, 256], got {self.edge_rays!r}")
        value_dtype(self.values)


# -- The cluster tree -----------------------------------------------------------------------------

@dataclass
class ClusterTree:
    """A binary tree of patch ranges: node t holds ``perm[start[t]:stop[t]]``.

    Attributes
    ----------
    perm : (n,) int64
        Tree order: position p holds patch ``perm[p]``; every node is a range of it.
    start, stop : (K,) int64
    left, right : (K,) int64
        Children (-1 for a leaf). Node 0 is the root.
    lo, hi : (K, 3) float64
        Each node's box (of its patches' boxes).
    """

    perm: np.ndarray
    start: np.ndarray
    stop: np.ndarray
    left: np.ndarray
    right: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @property
    def size(self) -> np.ndarray:
        return self.stop - self.start


def cluster_tree(centroids: np.ndarray, lo: np.ndarray, hi: np.ndarray, leaf_size: int = LEAF_SIZE) -> ClusterTree:
    """Halve the patches at the median centroid along the longest side of their box, recursively.

    Parameters
    ----------
    centroids, lo, hi : (n, 3) float
        Patch centroids and boxes (any frame).
    leaf_size : int
        Nodes of at most this many patches are leaves.
    """
    n = len(centroids)
    perm = np.arange(n, dtype=np.int64)
    cap = 4 * max(1, -(-n // max(1, leaf_size))) + 1   # leaves hold more than leaf_size / 2 patches
    start = np.zeros(cap, np.int64)
    stop = np.zeros(cap, np.int64)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    c = np.asarray(centroids, np.float64)
    start[0], stop[0] = 0, n
    count, todo = 1, [0]
    while todo:
        t = todo.pop()
        a, b = start[t], stop[t]
        if b - a <= leaf_size:
            continue
        idx = perm[a:b]
        pts = c[idx]
        axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
        m = (b - a) // 2
        order = np.argpartition(pts[:, axis], m)
        perm[a:b] = idx[order]
        for child, (s, e) in enumerate(((a, a + m), (a + m, b))):
            start[count], stop[count] = s, e
            (left if child == 0 else right)[t] = count
            todo.append(count)
            count += 1
    start, stop, left, right = start[:count], stop[:count], left[:count], right[:count]
    node_lo, node_hi = _node_boxes(np.asarray(lo, np.float64)[perm], np.asarray(hi, np.float64)[perm], start, stop,
                                   left, right)
    return ClusterTree(perm, start, stop, left, right, node_lo, node_hi)


def _node_boxes(lo: np.ndarray, hi: np.ndarray, start: np.ndarray, stop: np.ndarray, left: np.ndarray,
                right: np.ndarray):
    """(K, 3) boxes of the nodes, from the boxes ``lo, hi`` in tree order: a leaf's over its
    range, an inner node's over its two children (children are numbered after their parent)."""
    node_lo = np.empty((len(start), 3))
    node_hi = np.empty((len(start), 3))
    _fill_boxes(np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64), start, stop, left,
                right, node_lo, node_hi)
    return node_lo, node_hi


@njit(cache=True)
def _fill_boxes(lo, hi, start, stop, left, right, node_lo, node_hi):
    for t in range(start.shape[0] - 1, -1, -1):
        for d in range(3):
            if left[t] < 0:
                a, b = np.inf, -np.inf
                for p in range(start[t], stop[t]):
                    a = min(a, lo[p, d])
                    b = max(b, hi[p, d])
            else:
                a = min(node_lo[left[t], d], node_lo[right[t], d])
                b = max(node_hi[left[t], d], node_hi[right[t], d])
            node_lo[t, d] = a
            node_hi[t, d] = b


# -- The block partition --------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _far(lo, hi, r, c, eta):
    gap2 = 0.0
    dr2 = 0.0
    dc2 = 0.0
    for d in range(3):
        g = max(lo[r, d] - hi[c, d], lo[c, d] - hi[r, d], 0.0)
        gap2 += g * g
        dr2 += (hi[r, d] - lo[r, d]) ** 2
        dc2 += (hi[c, d] - lo[c, d]) ** 2
    return gap2 >= eta * eta * max(dr2, dc2)


@njit(cache=True)
def _partition(lo, hi, left, right, eta, r0, c0):
    """Far pairs and near leaf pairs below the node pairs (r0[k], c0[k]) (a stack walk)."""
    far_r, far_c, near_r, near_c = [0], [0], [0], [0]
    far_r.pop(); far_c.pop(); near_r.pop(); near_c.pop()
    stack_r = list(r0)
    stack_c = list(c0)
    while stack_r:
        r = stack_r.pop()
        c = stack_c.pop()
        if _far(lo, hi, r, c, eta):
            far_r.append(r)
            far_c.append(c)
            continue
        r_leaf = left[r] < 0
        c_leaf = left[c] < 0
        if r_leaf and c_leaf:
            near_r.append(r)
            near_c.append(c)
            continue
        dr = 0.0
        dc = 0.0
        for d in range(3):
            dr += (hi[r, d] - lo[r, d]) ** 2
            dc += (hi[c, d] - lo[c, d]) ** 2
        if c_leaf or (not r_leaf and dr >= dc):
            stack_r.append(left[r]); stack_c.append(c)
            stack_r.append(right[r]); stack_c.append(c)
        else:
            stack_r.append(r); stack_c.append(left[c])
            stack_r.append(r); stack_c.append(right[c])
    return (np.array(far_r, np.int64), np.array(far_c, np.int64),
            np.array(near_r, np.int64), np.array(near_c, np.int64))


def block_partition(tree: ClusterTree, eta: float = ETA, r0=None, c0=None):
    """(far_r, far_c, near_r, near_c): node pairs that are far, and leaf pairs that are near.

    Every pair of patches lies in exactly one of them. ``r0, c0`` (arrays of nodes): start
    below these node pairs instead of the root's.
    """
    r0 = np.zeros(1, np.int64) if r0 is None else np.asarray(r0, np.int64)
    c0 = np.zeros(1, np.int64) if c0 is None else np.asarray(c0, np.int64)
    if len(r0) == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, z
    return _partition(tree.lo, tree.hi, tree.left, tree.right, float(eta), r0, c0)


def _split_pairs(tree: ClusterTree, r: np.ndarray, c: np.ndarray):
    """Halve the larger node of each pair (the only node that is not a leaf if one is)."""
    size = tree.hi - tree.lo
    dr = (size[r] ** 2).sum(axis=1)
    dc = (size[c] ** 2).sum(axis=1)
    r_leaf, c_leaf = tree.left[r] < 0, tree.left[c] < 0
    split_r = ~r_leaf & (c_leaf | (dr >= dc))
    rr = np.concatenate([tree.left[r[split_r]], tree.right[r[split_r]], r[~split_r], r[~split_r]])
    cc = np.concatenate([c[split_r], c[split_r], tree.left[c[~split_r]], tree.right[c[~split_r]]])
    return rr, cc


# -- The H-matrix ---------------------------------------------------------------------------------

@dataclass
class BlockList:
    """Blocks ``F[rows_t][:, c0_t : c0_t + b_t]`` in tree positions: the rows of block t are
    ``row_index[row_ptr[t]:row_ptr[t + 1]]`` (any subset), its columns a range.

    Dense blocks hold their values row-major at ``values[off[t]:]``; low-rank ones ``U_t`` (m, r)
    at ``U[u_off[t]:]`` and ``V_t`` (b, r) at ``V[v_off[t]:]`` with the block ~= U_t V_t^T.
    """

    row_index: np.ndarray
    row_ptr: np.ndarray
    c0: np.ndarray
    b: np.ndarray
    rank: np.ndarray            # -1 for a dense block
    u_off: np.ndarray           # dense: offset of the values in U
    v_off: np.ndarray
    U: np.ndarray
    V: np.ndarray

    @property
    def count(self) -> int:
        return len(self.c0)

    @property
    def m(self) -> np.ndarray:
        return np.diff(self.row_ptr)


@dataclass
class FormFactorHMatrix:
    """F in tree order as dense and low-rank blocks (see the module docstring).

    Attributes
    ----------
    perm : (n,) int64
        Tree order: position p holds patch ``perm[p]`` (the scene's order).
    blocks : BlockList
    info : dict
        Counters: pairs evaluated (with rays, kernel only), blocks by kind, storage, seconds.
    """

    perm: np.ndarray
    blocks: BlockList
    info: dict = field(default_factory=dict)
    #: Entries of low-rank blocks moved out by :meth:`take_near` (their values cannot be zeroed in a
    #: factor): the products and squares subtract them. ``(L, L^T)`` CSR, or None.
    removed: tuple | None = None

    @property
    def n(self) -> int:
        return len(self.perm)

    @property
    def nbytes(self) -> int:
        """Bytes of the blocks' arrays (values, factors and row numbers)."""
        return sum(int(getattr(self.blocks, f.name).nbytes) for f in dataclasses.fields(self.blocks))

    @property
    def storage(self) -> int:
        """Floats held (dense entries and low-rank factors)."""
        return int(self.blocks.U.size + self.blocks.V.size)

    def frobenius2(self, row_scale: np.ndarray | None = None) -> float:
        """||diag(row_scale) F||_F^2 of the H-matrix (exact for what it holds; float64 sums).

        ``row_scale`` (n,) in tree order, e.g. rho_max for G = diag(rho_max) F; default ones.
        """
        rows2 = self.squares(np.ones((self.n, 1)), columns=False)[:, 0]
        s = np.ones(self.n) if row_scale is None else np.asarray(row_scale, np.float64).reshape(self.n)
        return float(np.dot(s * s, rows2))

    def squares(self, scale: np.ndarray, *, columns: bool) -> np.ndarray:
        """(n, c) weighted sums of squares of F's rows or columns (:func:`block_squares`), less the
        entries :meth:`take_near` moved out of low-rank blocks."""
        out = block_squares(self.blocks, scale, columns=columns)
        if self.removed is not None:
            L2 = self._removed_squares
            out -= (L2.T if columns else L2) @ np.asarray(scale, np.float64)
            np.maximum(out, 0.0, out=out)     # an entry's square and its block's share agree to rounding
        return out

    def matmat(self, X: np.ndarray) -> np.ndarray:
        """F @ X in tree order: X (n,) or (n, l) -> the same shape; float32 X gives float32, else float64."""
        return self._apply(X, False)

    def rmatmat(self, X: np.ndarray) -> np.ndarray:
        """F.T @ X in tree order: X (n,) or (n, l) -> the same shape; float32 X gives float32, else float64."""
        return self._apply(X, True)

    def _apply(self, X: np.ndarray, transpose: bool) -> np.ndarray:
        # float32 products where the caller works in float32 (the operator factorization's default):
        # the blocks are float32 already, and the products run twice as fast (2-core VM, 39,482 patches,
        # 64 vectors: 0.47-0.64 s against 1.02 s), at ~1e-6 relative rounding
        X = np.asarray(X)
        dt = np.float32 if X.dtype == np.float32 else np.float64
        X2 = np.ascontiguousarray(X.reshape(self.n, -1), dt)
        k = self.blocks
        parts = self._parts(numba.get_num_threads())
        Y = np.zeros((len(parts) - 1,) + X2.shape, dt)
        _apply(X2, Y, parts, k.row_index, k.row_ptr, k.c0, k.b, k.rank, k.u_off, k.v_off, k.U, k.V, transpose,
               self._max_rank)
        out = Y.sum(axis=0)
        if self.removed is not None:
            L = self.removed[1 if transpose else 0]
            _csr_subtract(L.indptr, L.indices, L.data, X2, out)
        return out.reshape(X.shape)

    # the blocks' shapes never change once built (take_near only zeroes values): what the products
    # derive from them is computed once, not at each of the range finder's products
    @cached_property
    def _max_rank(self) -> int:
        return max(1, int(self.blocks.rank.max(initial=0)))

    def _parts(self, threads: int) -> np.ndarray:
        cache = self.__dict__.setdefault("_parts_by_threads", {})
        if threads not in cache:
            cache[threads] = _work_parts(self.blocks, threads)
        return cache[threads]

    def release(self) -> None:
        """Drop the blocks (and what the products derived from them), keeping ``perm`` and ``info``: the
        precompute's solver set-up (the near field's sparse LUs, gigabytes on a clustered scene) then
        does not hold the H-matrix too. The object is unusable for products afterwards."""
        empty = np.zeros(0, np.int64)
        self.blocks = BlockList(np.zeros(0, ROW_INDEX), np.zeros(1, np.int64), empty, empty, empty, empty, empty,
                                np.zeros(0, np.float32), np.zeros(0, np.float32))
        self.removed = None
        for cached in ("_parts_by_threads", "_removed_squares", "_max_rank"):
            self.__dict__.pop(cached, None)
        release_freed_memory()

    def take_near(self, centroids: np.ndarray, radius: float, *, lowrank: bool | str = "auto"):
        """Move the entries whose patches' centroids are at most ``radius`` apart out of the H-matrix
        (it then holds F - N) and return N as coordinates in tree order.

        For the near-field split (:mod:`hfrad.lowrank.nearsplit`): N is kept sparse and exact, the rest
        is factored. Dense blocks' entries are zeroed in place. A low-rank block's entries cannot be:
        with ``lowrank``, those within the radius (their values ``U_i V_j^T``) join N too and the
        products subtract them as a sparse correction (:attr:`removed`).

        Why both: at a fixed count of neighbours a row the radius spans more leaves as n grows, and
        most of the close pairs then sit in low-rank blocks. Cornell box, eps 0.05, the range finder's
        rank of G - N: 39,746 patches, 281 with the dense blocks' 2.5M entries, 150 with the low-rank
        blocks' 3.5M more (the exact pass's N); 9,986 patches, 216 against 295: there the radius cuts
        slivers off large low-rank blocks (0.25M entries), and a block less a sliver has a higher rank.
        ``"auto"`` takes them where they are at least as many as the dense blocks'.

        Parameters
        ----------
        centroids : (n, 3) float, metres, in tree order
        radius : float, metres
        lowrank : bool or "auto"

        Returns
        -------
        rows, cols : (nnz,) int64
        values : (nnz,) float64
        """
        if self.removed is not None:
            raise ValueError("take_near was called on this H-matrix already")
        if lowrank not in (True, False, "auto"):
            raise ValueError(f"lowrank must be True, False or 'auto'; got {lowrank!r}")
        k = self.blocks
        c = np.ascontiguousarray(centroids, np.float64)
        r2 = float(radius) ** 2
        dense_args = (c, r2, k.row_index, k.row_ptr, k.c0, k.b, k.rank, k.u_off, k.U)
        rows, cols, values = _fill_entries(_near_entries, dense_args, _count_entries(_near_entries, dense_args,
                                                                                     k.count))
        low_args = (c, r2, k.row_index, k.row_ptr, k.c0, k.b, k.rank, k.u_off, k.v_off, k.U, k.V)
        low_counts = _count_entries(_lowrank_near_entries, low_args, k.count)
        low = int(low_counts.sum())
        take_low = (low >= len(rows)) if lowrank == "auto" else lowrank
        self.info.update({"near_dense_entries": int(len(rows)), "near_lowrank_entries": low,
                          "near_lowrank_taken": bool(take_low)})
        if not take_low or low == 0:
            return rows, cols, values
        lr, lc, lv = _fill_entries(_lowrank_near_entries, low_args, low_counts)
        L = sp.csr_matrix((lv.astype(np.float32), (lr, lc)), shape=(self.n, self.n))
        self.removed = (L, L.T.tocsr())
        return np.concatenate([rows, lr]), np.concatenate([cols, lc]), np.concatenate([values, lv])

    @cached_property
    def _removed_squares(self) -> sp.csr_matrix:
        """The squares of :attr:`removed`'s entries, float64 (made once: every ``squares`` call reads them)."""
        return self.removed[0].astype(np.float64).power(2)

    def rows(self, positions: np.ndarray) -> np.ndarray:
        """(len(positions), n) float32 rows of F at tree positions, read from the blocks that hold them:
        a row lies in few blocks, so this scans the blocks' row lists once instead of a product over
        the whole H-matrix per 64 rows (the certificate's 256 rows at 161,808 patches: four).
        Entries :meth:`take_near` moved out are left out, as the products leave them."""
        positions = np.asarray(positions, np.int64).reshape(-1)
        unique, inverse = np.unique(positions, return_inverse=True)
        slot = np.full(self.n, -1, np.int64)
        slot[unique] = np.arange(unique.size)
        out = np.zeros((unique.size, self.n), np.float32)
        k = self.blocks
        _block_rows(slot, k.row_index, k.row_ptr, k.c0, k.b, k.rank, k.u_off, k.v_off, k.U, k.V, out)
        if self.removed is not None:
            out -= self.removed[0][unique].toarray()
        in_order = unique.size == positions.size and np.array_equal(unique, positions)
        return out if in_order else out[inverse]

    def to_dense(self) -> np.ndarray:
        """(n, n) F in tree order (small scenes: tests)."""
        return self.matmat(np.eye(self.n))


@njit(cache=True, nogil=True)
def _block_rows(slot, rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, out):  # pragma: no cover (numba)
    """Add each block's entries in the rows with ``slot[row] >= 0`` to ``out[slot[row]]`` (float64 sums of
    a low-rank block's ``U_i V_j^T``)."""
    for t in range(c0.shape[0]):
        r, b, c = rank[t], b_[t], c0[t]
        if r == 0:
            continue
        for i in range(row_ptr[t], row_ptr[t + 1]):
            w = slot[rows[i]]
            if w < 0:
                continue
            local = i - row_ptr[t]
            if r < 0:
                o = u_off[t] + local * b
                for j in range(b):
                    out[w, c + j] += stored_value(U, o + j)
                continue
            uo, vo = u_off[t] + local * r, v_off[t]
            for j in range(b):
                acc = 0.0
                for e in range(r):
                    acc += np.float64(stored_value(U, uo + e)) * np.float64(stored_value(V, vo + j * r + e))
                out[w, c + j] += acc


def _count_entries(kernel, args, count: int) -> np.ndarray:
    """(count,) each block's entries a two-pass entry kernel (:func:`_near_entries`,
    :func:`_lowrank_near_entries`) would take, from its counting pass."""
    counts = np.zeros(count, np.int64)
    z = np.zeros(0, np.int64)
    kernel(*args, counts, z, z, np.zeros(0), False)
    return counts


def _fill_entries(kernel, args, counts: np.ndarray):
    """``(rows, cols, values)`` from the kernel's filling pass, each block's entries at the offsets of ``counts``."""
    ptr = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=ptr[1:])
    rows, cols, values = np.empty(ptr[-1], np.int64), np.empty(ptr[-1], np.int64), np.empty(ptr[-1])
    kernel(*args, ptr, rows, cols, values, True)
    return rows, cols, values


@njit(cache=True, parallel=True, nogil=True)
def _lowrank_near_entries(c, r2, rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, at, out_r, out_c, out_v,
                          take):  # pragma: no cover (numba)
    """:func:`_near_entries` for the low-rank blocks: their entries ``U_i V_j^T`` within sqrt(r2) (counted,
    or written from offsets ``at``; nothing is changed). A block whose rows' box and columns' box are
    farther apart is skipped without looking at its pairs."""
    for t in prange(c0.shape[0]):
        r = rank[t]
        if r <= 0:
            if not take:
                at[t] = 0
            continue
        p, m, b = row_ptr[t], row_ptr[t + 1] - row_ptr[t], b_[t]
        gap2 = 0.0
        for d in range(3):
            rlo, rhi, clo, chi = np.inf, -np.inf, np.inf, -np.inf
            for i in range(m):
                rlo, rhi = min(rlo, c[rows[p + i], d]), max(rhi, c[rows[p + i], d])
            for j in range(b):
                clo, chi = min(clo, c[c0[t] + j, d]), max(chi, c[c0[t] + j, d])
            g = max(rlo - chi, clo - rhi, 0.0)
            gap2 += g * g
        q = at[t] if take else 0
        if gap2 <= r2:
            uo, vo = u_off[t], v_off[t]
            for i in range(m):
                ri = rows[p + i]
                for j in range(b):
                    cj = c0[t] + j
                    d2 = (c[ri, 0] - c[cj, 0]) ** 2 + (c[ri, 1] - c[cj, 1]) ** 2 + (c[ri, 2] - c[cj, 2]) ** 2
                    if d2 <= r2:
                        if take:
                            s = 0.0
                            for k in range(r):
                                s += (np.float64(stored_value(U, uo + i * r + k))
                                      * np.float64(stored_value(V, vo + j * r + k)))
                            out_r[q], out_c[q], out_v[q] = ri, cj, s
                        q += 1
        if not take:
            at[t] = q


@njit(cache=True, parallel=True, nogil=True)
def _csr_subtract(indptr, indices, data, X, Y):  # pragma: no cover (numba)
    """Y -= L X for L in CSR (rows in parallel), in Y's dtype."""
    l = X.shape[1]
    for i in prange(indptr.shape[0] - 1):
        for e in range(indptr[i], indptr[i + 1]):
            a = data[e]
            j = indices[e]
            for v in range(l):
                Y[i, v] -= a * X[j, v]


@njit(cache=True, parallel=True, nogil=True)
def _near_entries(c, r2, rows, row_ptr, c0, b_, rank, u_off, U, at, out_r, out_c, out_v, take):
    """Count (``take`` False: into ``at``) or move out (``take``: from offsets ``at``) the entries of dense
    blocks whose centroids are within sqrt(r2)."""
    for t in prange(c0.shape[0]):
        if rank[t] >= 0:
            continue
        p, m, b, o = row_ptr[t], row_ptr[t + 1] - row_ptr[t], b_[t], u_off[t]
        q = at[t] if take else 0
        for i in range(m):
            ri = rows[p + i]
            for j in range(b):
                cj = c0[t] + j
                d2 = (c[ri, 0] - c[cj, 0]) ** 2 + (c[ri, 1] - c[cj, 1]) ** 2 + (c[ri, 2] - c[cj, 2]) ** 2
                v = stored_value(U, o + i * b + j)
                if d2 <= r2 and v != 0.0:
                    if take:
                        out_r[q], out_c[q], out_v[q] = ri, cj, v
                        U[o + i * b + j] = 0.0
                    q += 1
        if not take:
            at[t] = q


def block_squares(blocks: BlockList, scale: np.ndarray, *, columns: bool) -> np.ndarray:
    """(n, c) weighted squares of the H-matrix's F, float64, from its blocks (tree order).

    ``columns``: ``out[p, c] = sum_i scale[i, c] F[i, p]^2`` (column sums of squares, rows weighted);
    else ``out[i, c] = sum_p scale[p, c] F[i, p]^2`` (row sums, columns weighted). A low-rank block
    ``U V^T`` adds ``diag(V (U^T diag(s) U) V^T)`` (or the transpose's): O((m + b) r^2) a channel.
    ``scale``: (n, c) >= 0.
    """
    scale = np.ascontiguousarray(scale, np.float64)
    k = blocks
    parts = _work_parts(k, numba.get_num_threads())
    out = np.zeros((len(parts) - 1,) + scale.shape)          # one copy a part: blocks share rows and columns
    _squares_parts(parts, k.row_index, k.row_ptr, k.c0, k.b, k.rank, k.u_off, k.v_off, k.U, k.V, scale, columns, out)
    return out.sum(axis=0)


@njit(cache=True, parallel=True, nogil=True)
def _squares_parts(parts, rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, W, columns, out):  # pragma: no cover
    """:func:`_squares` over each run of blocks ``parts[q]:parts[q + 1]`` on its own thread, into ``out[q]``
    (the runs' scratch arrays are made inside :func:`_squares`, a call per run, never hoisted across runs)."""
    for q in prange(parts.shape[0] - 1):
        _squares(parts[q], parts[q + 1], rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, W, columns, out[q])


@njit(cache=True, nogil=True)
def _squares(first, last, rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, W, columns, out):  # pragma: no cover
    """:func:`block_squares` of blocks ``first:last``, block after block, added to ``out``."""
    C = W.shape[1]
    R = max(1, rank[first:last].max()) if last > first else 1
    M = np.zeros((R, R))
    for t in range(first, last):
        p, m, b, c, r = row_ptr[t], row_ptr[t + 1] - row_ptr[t], b_[t], c0[t], rank[t]
        if r < 0:                                     # dense, (m, b) row-major at u_off
            o = u_off[t]
            for i in range(m):
                gi = rows[p + i]
                for j in range(b):
                    f = np.float64(stored_value(U, o + i * b + j))
                    f2 = f * f
                    if f2 == 0.0:
                        continue
                    for k in range(C):
                        if columns:
                            out[c + j, k] += W[gi, k] * f2
                        else:
                            out[gi, k] += W[c + j, k] * f2
            continue
        if r == 0:
            continue
        # U V^T: M = X^T diag(w) X (r x r) over the weighted factor's rows X, then each row y of the
        # other factor adds y M y^T (plain loops: no array made per block)
        src, dst = (U, V) if columns else (V, U)
        so, do = (u_off[t], v_off[t]) if columns else (v_off[t], u_off[t])
        for k in range(C):
            M[:r, :r] = 0.0
            for i in range(m if columns else b):
                w = W[rows[p + i], k] if columns else W[c + i, k]
                if w == 0.0:
                    continue
                for a in range(r):
                    fa = w * np.float64(stored_value(src, so + i * r + a))
                    for e in range(r):
                        M[a, e] += fa * np.float64(stored_value(src, so + i * r + e))
            for i in range(b if columns else m):
                acc = 0.0
                for a in range(r):
                    inner = 0.0
                    for e in range(r):
                        inner += M[a, e] * np.float64(stored_value(dst, do + i * r + e))
                    acc += np.float64(stored_value(dst, do + i * r + a)) * inner
                out[c + i if columns else rows[p + i], k] += acc


def _work_parts(blocks: BlockList, threads: int) -> np.ndarray:
    """Boundaries of ``threads`` runs of blocks with about equal stored floats (one run a thread)."""
    work = np.where(blocks.rank < 0, blocks.m * blocks.b, (blocks.m + blocks.b) * np.maximum(blocks.rank, 0)) + 1
    edges = np.searchsorted(np.cumsum(work), np.linspace(0, work.sum(), threads + 1)[1:-1])
    return np.unique(np.r_[0, edges, blocks.count]).astype(np.int64)


@njit(cache=True, parallel=True, nogil=True, fastmath={"reassoc", "contract"})
def _apply(X, Y, parts, rows, row_ptr, c0, b_, rank, u_off, v_off, U, V, transpose, max_rank):
    """Y[part] += F X (or F^T X with ``transpose``) over the blocks of each part, X (n, l) row-major: every
    block is read once for all l vectors. Each part writes its own copy of Y (the caller sums them).
    Arithmetic in X's dtype. ``max_rank``: the largest block rank (sizes each part's scratch once: an array
    re-allocated inside a prange body is not safe with numba's allocation hoisting)."""
    l = X.shape[1]
    for q in prange(parts.shape[0] - 1):
        y = Y[q]
        z = np.empty((max_rank, l), X.dtype)
        for t in range(parts[q], parts[q + 1]):
            p, m, b, c, r = row_ptr[t], row_ptr[t + 1] - row_ptr[t], b_[t], c0[t], rank[t]
            if r < 0:                                 # dense, (m, b) row-major at u_off
                o = u_off[t]
                for i in range(m):
                    ri = rows[p + i]
                    for j in range(b):
                        d = stored_value(U, o + i * b + j)
                        if d == 0.0:
                            continue
                        if transpose:
                            for v in range(l):
                                y[c + j, v] += d * X[ri, v]
                        else:
                            for v in range(l):
                                y[ri, v] += d * X[c + j, v]
                continue
            if r == 0:
                continue
            uo, vo = u_off[t], v_off[t]
            for k in range(r):
                for v in range(l):
                    z[k, v] = 0.0
            # transpose: y[c:c+b] += V (U^T X[rows]); else y[rows] += U (V^T X[c:c+b])
            for i in range(m if transpose else b):
                src = rows[p + i] if transpose else c + i
                for k in range(r):
                    f = stored_value(U, uo + i * r + k) if transpose else stored_value(V, vo + i * r + k)
                    for v in range(l):
                        z[k, v] += f * X[src, v]
            for i in range(b if transpose else m):
                dst = c + i if transpose else rows[p + i]
                for k in range(r):
                    f = stored_value(V, vo + i * r + k) if transpose else stored_value(U, uo + i * r + k)
                    for v in range(l):
                        y[dst, v] += f * z[k, v]


# -- Building it ----------------------------------------------------------------------------------

#: Bytes :func:`_drain` copies between two hand-backs of the pieces it freed (:func:`release_freed_memory`).
DRAIN_TRIM_BYTES = 256 << 20


def _drain(pieces: list, dtype) -> np.ndarray:
    """``pieces`` (a list, emptied) joined into one array of ``dtype``, each piece dropped once copied:
    the peak is the joined array and one piece, not twice the pieces (np.concatenate's).

    The pieces are a build's batches, a few MB each, so glibc keeps them on its heaps once freed: the
    memory they held is handed back every :data:`DRAIN_TRIM_BYTES` copied, or the process would hold
    both the pieces and the joined array at the end."""
    out = np.empty(sum(len(x) for x in pieces), dtype)
    at = since_trim = 0
    pieces.reverse()            # pop from the end: the first piece first
    while pieces:
        x = pieces.pop()
        out[at:at + len(x)] = x
        at += len(x)
        since_trim += x.nbytes
        del x
        if since_trim >= DRAIN_TRIM_BYTES:
            release_freed_memory()
            since_trim = 0
    return out


class _Collector:
    """Blocks as they are decided, in batches (no Python step a block: 2.1M blocks at 161,808 patches):
    dense (exact values) and low rank (U, V)."""

    def __init__(self, values: str = "float32") -> None:
        self.rows, self.m, self.c0, self.b, self.rank = [], [], [], [], []
        self.U, self.V, self.u_size, self.v_size = [], [], [], []
        self.dtype = value_dtype(values)

    def _stored(self, x: np.ndarray) -> np.ndarray:
        """Values as the blocks hold them (float32, or bfloat16 bits: converted as they come, so the
        build never holds them in float32 first)."""
        return to_bfloat16(x) if self.dtype == np.uint16 else np.asarray(x, np.float32)

    def _add(self, rows, m, c0, b, rank, U, V, u_size, v_size) -> None:
        for store, x in ((self.rows, np.asarray(rows, ROW_INDEX)), (self.m, m), (self.c0, c0), (self.b, b),
                         (self.rank, rank), (self.U, U), (self.V, V), (self.u_size, u_size), (self.v_size, v_size)):
            store.append(np.asarray(x))

    def add_dense(self, rows: np.ndarray, m, c0, b, values: np.ndarray) -> None:
        """Dense blocks t with rows ``rows[sum(m[:t]):][:m[t]]``, columns ``c0[t] : c0[t] + b[t]`` and their
        values row-major one after the other in ``values``: one batch however many blocks (a list piece a
        block made 15 s of a 161,808-patch build's joins)."""
        m, b = np.asarray(m, np.int64), np.asarray(b, np.int64)
        self._add(rows, m, np.asarray(c0, np.int64), b, np.full(len(m), -1, np.int64),
                  self._stored(values).ravel(), np.zeros(0, self.dtype), m * b, np.zeros(len(m), np.int64))

    def add_lowrank(self, rows: np.ndarray, row_ptr: np.ndarray, c0: np.ndarray, b: np.ndarray, res, keep) -> None:
        """The blocks ``keep`` (bool) of an ACA result ``res`` over the blocks t (rows
        ``rows[row_ptr[t]:row_ptr[t + 1]]``, columns ``c0[t] : c0[t] + b[t]``)."""
        keep = np.asarray(keep, bool)
        if not keep.any():
            return
        m = np.diff(row_ptr)
        u_size, v_size = np.diff(res.u_offsets), np.diff(res.v_offsets)    # m_t r_t and b_t r_t
        U = res.U[res.u_offsets[0]:res.u_offsets[-1]][np.repeat(keep, u_size)]
        V = res.V[res.v_offsets[0]:res.v_offsets[-1]][np.repeat(keep, v_size)]
        self._add(rows[np.repeat(keep, m)], m[keep], c0[keep], b[keep], res.ranks[keep], self._stored(U),
                  self._stored(V), u_size[keep],
                  v_size[keep])

    def blocks(self) -> BlockList:
        """The collected blocks as one list; the batches are dropped as they are copied (the values, the
        H-matrix's storage, are never held twice), so it can be called once."""
        if self.m is None:
            raise RuntimeError("the collected blocks were already taken (_Collector.blocks is called once)")
        cat = _drain
        exclusive = (lambda z: np.cumsum(z) - z)                 # each block's offset from the sizes
        row_ptr = np.zeros(sum(len(x) for x in self.m) + 1, np.int64)
        np.cumsum(cat(self.m, np.int64), out=row_ptr[1:])
        u_off, v_off = exclusive(cat(self.u_size, np.int64)), exclusive(cat(self.v_size, np.int64))
        out = BlockList(cat(self.rows, ROW_INDEX), row_ptr, cat(self.c0, np.int64), cat(self.b, np.int64),
                        cat(self.rank, np.int64), u_off, v_off, cat(self.U, self.dtype), cat(self.V, self.dtype))
        self.m = None
        return _without_zeros(out)


def _without_zeros(blocks: BlockList) -> BlockList:
    """``blocks`` (used up: its row and value arrays are reused) less what holds only zeros: a dense
    block's all-zero rows and its leading and trailing all-zero columns, then blocks left empty and
    low-rank blocks of rank 0. Coplanar patches see nothing of each other and blocked pairs are zero,
    so at 161,808 Cornell-box patches half the dense entries were zero and 163K dense blocks had
    nothing else. The same products and squares; compacted in place (the arrays shrink, nothing is
    copied whole)."""
    k = blocks
    m, b, c0, u_off = k.m.copy(), k.b.copy(), k.c0.copy(), k.u_off.copy()
    rows_end, u_end = _compact_dense(k.row_index, k.row_ptr, m, b, c0, k.rank, u_off, k.U)
    keep = np.flatnonzero(np.where(k.rank < 0, m * b > 0, k.rank > 0))
    row_index, U = _shrink(k.row_index, rows_end), _shrink(k.U, u_end)
    row_ptr = np.zeros(len(keep) + 1, np.int64)      # the dropped blocks kept no rows (m 0)
    np.cumsum(m[keep], out=row_ptr[1:])
    return BlockList(row_index, row_ptr, c0[keep], b[keep], k.rank[keep], u_off[keep], k.v_off[keep], U, k.V)


def _shrink(a: np.ndarray, size: int) -> np.ndarray:
    """The first ``size`` entries of the 1-d array ``a``: ``a`` itself cut in place (realloc, no copy) where
    it owns its buffer (the collector's joined arrays: nothing else views them), else a copy."""
    if not a.flags.owndata:
        return a[:size].copy()
    a.resize((int(size),), refcheck=False)
    return a


@njit(cache=True, nogil=True)
def _nonzero_span(U, start, width):  # pragma: no cover (numba)
    """(first, last) positions of the nonzeros in ``U[start:start + width]``; (width, -1) when all are zero."""
    first, last = width, -1
    for j in range(width):
        if stored_value(U, start + j) != 0.0:
            first, last = min(first, j), j
    return first, last


@njit(cache=True, nogil=True)
def _compact_dense(rows, row_ptr, m, b, c0, rank, u_off, U):  # pragma: no cover (numba)
    """Move each block's rows and U values down over what :func:`_without_zeros` drops, in block order
    (a block never moves up, so in place): dense blocks lose their all-zero rows and outer all-zero
    columns (``m``, ``b``, ``c0`` updated), blocks to be dropped (dense with nothing left, rank 0) keep
    no rows. Updates ``m``, ``b``, ``c0``, ``u_off``; returns the used lengths of ``rows`` and ``U``."""
    at_row, at_u = 0, 0
    for t in range(len(m)):
        p, mt, bt, o, r = row_ptr[t], m[t], b[t], u_off[t], rank[t]
        if r >= 0:
            if r == 0:
                m[t] = 0
                u_off[t] = at_u
                continue
            for i in range(mt):
                rows[at_row + i] = rows[p + i]
            for e in range(mt * r):
                U[at_u + e] = U[o + e]
            u_off[t] = at_u
            at_row += mt
            at_u += mt * r
            continue
        first, last = bt, -1                       # the nonzero columns' range over the kept rows
        kept = 0
        for i in range(mt):
            lo, hi = _nonzero_span(U, o + i * bt, bt)
            if hi >= 0:
                kept += 1
                first, last = min(first, lo), max(last, hi)
        width = last - first + 1 if kept else 0
        u_off[t] = at_u
        w = 0
        for i in range(mt):
            if _nonzero_span(U, o + i * bt, bt)[1] < 0:
                continue
            rows[at_row + w] = rows[p + i]
            for j in range(width):
                U[at_u + w * width + j] = U[o + i * bt + first + j]
            w += 1
        m[t], b[t] = kept, width
        if kept:
            c0[t] += first
        at_row += kept
        at_u += kept * width
    return at_row, at_u


def build_hmatrix(scene, engine: FormFactorEngine, options: HMatrixOptions | None = None,
                  progress: ProgressCallback = None, threads: int | None = None) -> FormFactorHMatrix:
    """The H-matrix of ``scene``'s F (see the module docstring).

    Parameters
    ----------
    scene : Scene
    engine : FormFactorEngine
        Computes the exact blocks (with its visibility settings) and holds the kernel geometry.
    options : HMatrixOptions, optional
    progress : callable, optional
        ``progress(done, total)`` over the near blocks' row leaves (of every part once each has begun them).
    threads : int, optional
        Parts built at once, each on its own thread with one numba thread (:data:`PARTS_PER_THREAD`
        parts a thread, :func:`split_into_parts`: the same blocks); default numba's thread count.
        Most engine calls of a build are too small to keep every core busy on their own: on the 2-core
        VM, Cornell box 39,482 patches, 33.2 s on one thread of parts (numba's 2 inside) against 26.1 s
        on two (4 parts).
    """
    options = HMatrixOptions() if options is None else options
    t0 = time.perf_counter()
    pairs = hmatrix_pairs(scene, options)
    tree_seconds = time.perf_counter() - t0
    threads = numba.get_num_threads() if threads is None else max(1, int(threads))
    if threads == 1 or not numba_loops_at_once():      # numba's workqueue layer: one parallel loop at a time
        built = [build_part(scene, engine, pairs, options, progress=progress)]
    else:
        built = _build_parts(scene, engine, pairs, options, threads, progress)
    blocks, infos = [b for b, _ in built], [i for _, i in built]
    del built
    infos[0]["time_tree"] = tree_seconds
    return join_parts(pairs, blocks, infos, options, time.perf_counter() - t0)


#: Parts of an in-process build per thread (:func:`build_hmatrix`): parts differ in cost, and a thread
#: free early takes the next one.
PARTS_PER_THREAD = 2


def _build_parts(scene, engine, pairs, options, threads: int, progress) -> list[tuple]:
    """``PARTS_PER_THREAD * threads`` parts of ``pairs`` built on ``threads`` threads of one numba thread each
    (the engine's calls release the GIL); ``progress`` sums the parts' near-block counts."""
    from concurrent.futures import ThreadPoolExecutor

    parts = split_into_parts(pairs, PARTS_PER_THREAD * threads)
    counts = [(0, 0)] * len(parts)
    lock = threading.Lock()

    def build(k: int) -> tuple:
        def part_progress(done: int, total: int) -> None:
            with lock:
                counts[k] = (done, total)
                report(progress, sum(d for d, _ in counts), sum(t for _, t in counts))

        with numba_threads(1):
            return build_part(scene, engine, parts[k], options, progress=part_progress if progress else None)

    with ThreadPoolExecutor(threads, thread_name_prefix="hfrad-hmatrix") as pool:
        return list(pool.map(build, range(len(parts))))


@dataclass
class HMatrixPairs:
    """The cluster tree of a build and its node pairs from the root down (:func:`block_partition`):
    what the build decides, pair by pair. Each pair's blocks depend on that pair alone (hashed rays,
    a block's own cross approximation), so any split of the pairs into parts
    (:func:`split_into_parts`), each built on its own (:func:`build_part`, e.g. by a Dask worker), gives
    the same blocks (:func:`join_parts`)."""

    tree: ClusterTree
    far_r: np.ndarray
    far_c: np.ndarray
    near_r: np.ndarray
    near_c: np.ndarray


def hmatrix_pairs(scene, options: HMatrixOptions) -> HMatrixPairs:
    """The cluster tree of ``scene`` (its patch boxes) and the far and near node pairs of its partition."""
    from .farfield import patch_boxes

    lo, hi = patch_boxes(scene)
    tree = cluster_tree(scene.centroids, lo, hi, options.leaf_size)
    return HMatrixPairs(tree, *block_partition(tree, options.eta))


def split_into_parts(pairs: HMatrixPairs, parts: int) -> list[HMatrixPairs]:
    """``pairs`` in ``parts`` parts of about equal work: far pairs dealt in turn (the partition lists
    them by level, so each part gets a share of every size); near pairs by their lower node, so a
    pair and its mirror, which :meth:`_Builder.near` computes once, stay together."""
    parts = max(1, int(parts))
    low = np.minimum(pairs.near_r, pairs.near_c)
    _, rank = np.unique(low, return_inverse=True)
    out = []
    for k in range(parts):
        far = np.arange(k, len(pairs.far_r), parts)
        near = np.flatnonzero(rank % parts == k)
        out.append(HMatrixPairs(pairs.tree, pairs.far_r[far], pairs.far_c[far], pairs.near_r[near],
                                pairs.near_c[near]))
    return out


def build_part(scene, engine: FormFactorEngine, pairs: HMatrixPairs, options: HMatrixOptions,
               progress: ProgressCallback = None) -> tuple[BlockList, dict]:
    """The blocks of ``pairs`` (a part of a build, or all of it) and the build's counters over them."""
    builder = _Builder(scene, engine, pairs.tree, options)
    builder.far(pairs.far_r, pairs.far_c)
    builder.near(pairs.near_r, pairs.near_c, progress)
    builder.flush_exact(None)
    blocks, info = builder.out.blocks(), builder.info
    del builder
    # the part's batches, freed on this thread's arena: at 296,350 patches the build ended at 14.4 GiB with
    # a trim only after the whole build, at 8.8 GiB with one after each part (and int32 row numbers)
    release_freed_memory()
    return blocks, info


def join_blocks(lists: list[BlockList]) -> BlockList:
    """One block list of several (their blocks in turn; offsets moved to the joined arrays). The lists
    are used up: each one's large arrays are dropped once copied (the peak is the joined list and one
    part, not twice the H-matrix)."""
    if len(lists) == 1:
        return lists[0]
    row_ptr = [np.zeros(1, np.int64)]
    u_off, v_off, rows_at, u_at, v_at = [], [], 0, 0, 0
    for k in lists:
        row_ptr.append(k.row_ptr[1:] + rows_at)
        u_off.append(k.u_off + u_at)
        v_off.append(k.v_off + v_at)
        rows_at, u_at, v_at = rows_at + len(k.row_index), u_at + len(k.U), v_at + len(k.V)
    cat = (lambda name: np.concatenate([getattr(k, name) for k in lists]))
    c0, b, rank = cat("c0"), cat("b"), cat("rank")
    dtype = lists[0].U.dtype
    if any(k.U.dtype != dtype or k.V.dtype != dtype for k in lists):
        raise ValueError("the parts' blocks hold their values in different dtypes (HMatrixOptions.values)")

    def drain(name: str, dtype) -> np.ndarray:
        pieces = [getattr(k, name) for k in lists]
        for k in lists:
            setattr(k, name, None)
        return _drain(pieces, dtype)

    return BlockList(drain("row_index", ROW_INDEX), np.concatenate(row_ptr), c0, b, rank, np.concatenate(u_off),
                     np.concatenate(v_off), drain("U", dtype), drain("V", dtype))


def join_parts(pairs: HMatrixPairs, blocks: list[BlockList], infos: list[dict], options: HMatrixOptions,
               seconds: float) -> FormFactorHMatrix:
    """The H-matrix of the parts built from ``pairs`` (:func:`build_part`); its ``info`` sums the parts'
    counters and seconds (with several parts: seconds of work, not of the wall) and adds the build's
    totals, ``seconds`` its wall time."""
    tree = pairs.tree
    info: dict = {}
    for part in infos:
        for key, value in part.items():
            info[key] = info.get(key, 0) + value
    hm = FormFactorHMatrix(tree.perm, join_blocks(blocks), info)
    release_freed_memory()      # the parts, copied into the joined blocks (freed on their threads' arenas)
    n = len(tree.perm)
    info.update({"n": n, "leaf_size": options.leaf_size, "eta": options.eta, "tolerance": options.tolerance,
                 "values": options.values,
                 "tree_nodes": int(len(tree.start)), "near_blocks": int(len(pairs.near_r)), "blocks": hm.blocks.count,
                 "pairs_evaluated": info["exact_pairs"] + info["kernel_pairs"],
                 "pairs_share": (info["exact_pairs"] + info["kernel_pairs"]) / max(1, n * n),
                 "storage_floats": hm.storage, "bytes": hm.nbytes, "time_total": seconds})
    ranks = hm.blocks.rank[hm.blocks.rank >= 0]
    info["mean_rank"] = float(ranks.mean()) if len(ranks) else 0.0
    info["lowrank_blocks"] = int(len(ranks))
    info["dense_blocks"] = int(hm.blocks.count - len(ranks))
    return hm


class _Builder:
    """The far pairs' decisions (visibility, probes, cross approximation) and the exact rows."""

    def __init__(self, scene, engine: FormFactorEngine, tree: ClusterTree, options: HMatrixOptions) -> None:
        self.engine, self.tree, self.options = engine, tree, options
        self.boxes = _visibility_boxes(scene, engine, tree)
        self.engine_areas = scene.areas
        self.out = _Collector(options.values)
        self.pending: dict[int, list] = {}        # column node -> row positions wanted exactly
        self.info = {"far_blocks": 0, "visible_blocks": 0, "blocked_blocks": 0, "mixed_blocks": 0,
                     "probed_blocks": 0, "aca_failed": 0, "kernel_pairs": 0, "exact_pairs": 0,
                     "blocked_pairs": 0, "probe_rays": 0, "time_visibility": 0.0, "time_probes": 0.0,
                     "time_aca": 0.0, "time_exact": 0.0}

    def node_rows(self, t: int) -> np.ndarray:
        return np.arange(self.tree.start[t], self.tree.stop[t], dtype=np.int64)

    def far(self, r: np.ndarray, c: np.ndarray) -> None:
        """Decide every far node pair: VISIBLE ones by cross approximation, BLOCKED ones zero,
        MIXED ones halved down to ``probe_size`` and then probed row by row."""
        tree, info = self.tree, self.info
        info["far_blocks"] += len(r)
        while len(r):
            t = time.perf_counter()
            states = _states(self.engine, self.boxes, r, c)
            info["time_visibility"] += time.perf_counter() - t
            blocked = states == BLOCKED
            info["blocked_blocks"] += int(blocked.sum())
            info["blocked_pairs"] += int((tree.size[r[blocked]] * tree.size[c[blocked]]).sum())
            visible = states == VISIBLE
            info["visible_blocks"] += int(visible.sum())
            rows, row_ptr = _concat_ranges(None, tree.start[r[visible]], tree.stop[r[visible]])
            self.lowrank(rows, row_ptr, c[visible])
            mixed = states == MIXED
            info["mixed_blocks"] += int(mixed.sum())
            small = mixed & (np.maximum(tree.size[r], tree.size[c]) <= self.options.probe_size)
            small |= mixed & (tree.left[r] < 0) & (tree.left[c] < 0)
            self.probe(r[small], c[small])
            split = mixed & ~small
            r, c = _split_pairs(tree, r[split], c[split])

    def lowrank(self, rows: np.ndarray, row_ptr: np.ndarray, c: np.ndarray) -> None:
        """Cross approximations of the unoccluded blocks F[rows[row_ptr[k]:row_ptr[k + 1]]][:, node c[k]];
        those that do not converge are computed exactly."""
        from .aca import aca_blocks

        if not len(c):
            return
        tree, perm = self.tree, self.tree.perm
        t = time.perf_counter()
        cols, col_ptr = _concat_ranges(perm, tree.start[c], tree.stop[c])
        res = aca_blocks(self.engine.geometry, perm[rows], row_ptr, cols, col_ptr, self.options.tolerance,
                         self.options.max_rank)
        self.info["time_aca"] += time.perf_counter() - t
        self.info["kernel_pairs"] += int(res.evaluated.sum())
        self.out.add_lowrank(rows, row_ptr, tree.start[c], tree.size[c], res, res.ok)
        self.info["aca_failed"] += int((~res.ok).sum())
        for k in np.flatnonzero(~res.ok):
            self.exact_rows(rows[row_ptr[k]:row_ptr[k + 1]], c[k])

    def probe(self, r: np.ndarray, c: np.ndarray) -> None:
        """Mixed pairs: PROBES rays from each row patch to patches spread over the column node; rows
        whose facing rays all agree are visible (cross approximation) or blocked (zero). The others
        (a shadow edge across the node) are probed again against each half of the column node, down
        to a leaf, where they are computed exactly: the exact pairs follow the shadow edge."""
        tree = self.tree
        rows, row_ptr = _concat_ranges(None, tree.start[r], tree.stop[r])
        self.info["probed_blocks"] += len(r)
        c = np.asarray(c, np.int64)
        while len(c):
            rows, row_ptr, c = self._probe_round(rows, row_ptr, c)

    def _probe_round(self, rows: np.ndarray, row_ptr: np.ndarray, c: np.ndarray):
        """One round of :meth:`probe` over the groups of rows ``rows[row_ptr[q]:row_ptr[q + 1]]``, each
        against column node ``c[q]``; returns the next round's ``(rows, row_ptr, c)``.

        Each row first casts ``PROBES`` rays; in a pair where some row's rays disagree (a shadow
        edge crosses it), the rows whose rays agreed cast ``MORE_PROBES`` more before they count as
        visible or blocked: the shadow may fall between their first rays. Šibenik, 3,103 patches,
        the H-matrix's error in the certificate's norm: 3.6% with 6 rays a row, 1.6% with 6 + 8,
        1.0% with 6 + 16; the 10K Cornell box's build 10.5, 11.4 and 15.0 s."""
        tree = self.tree
        t = time.perf_counter()
        owner = np.repeat(np.arange(len(c)), np.diff(row_ptr))
        n_facing, n_blocked = self._probe_rays(rows, c[owner], 0, PROBES)
        edge = np.zeros(len(c), bool)
        edge[owner[(n_blocked > 0) & (n_blocked < n_facing)]] = True
        again = np.flatnonzero(edge[owner] & ((n_blocked == 0) | (n_blocked == n_facing)))
        if len(again) and MORE_PROBES:
            f2, b2 = self._probe_rays(rows[again], c[owner[again]], PROBES, MORE_PROBES)
            n_facing[again] += f2
            n_blocked[again] += b2
        state = np.full(len(rows), MIXED, np.int8)
        state[n_blocked == 0] = VISIBLE
        state[(n_blocked == n_facing) & (n_facing > 0)] = BLOCKED
        self.info["time_probes"] += time.perf_counter() - t
        self.info["blocked_pairs"] += int(tree.size[c[owner[state == BLOCKED]]].sum())
        leaf = (tree.left[c] < 0)[owner]
        exact_rows, exact_ptr, exact_c = _groups_where(rows, owner, (state == MIXED) & leaf, c)
        for q in range(len(exact_c)):
            self.exact_rows(exact_rows[exact_ptr[q]:exact_ptr[q + 1]], exact_c[q])
        self.lowrank(*_groups_where(rows, owner, state == VISIBLE, c))
        # the other mixed rows, against each half of their column node (left, then right)
        rows, row_ptr, c = _groups_where(rows, owner, (state == MIXED) & ~leaf, c)
        rows, row_ptr = _concat_ranges(rows, np.repeat(row_ptr[:-1], 2), np.repeat(row_ptr[1:], 2))
        return rows, row_ptr, np.column_stack([tree.left[c], tree.right[c]]).ravel()

    def _probe_rays(self, rows: np.ndarray, c: np.ndarray, first: int, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(facing, blocked) counts of ``k`` rays from each row position ``rows[i]`` to patches of
        column node ``c[i]``, one in each of k equal parts of its range at a hashed place (rays
        ``first .. first + k - 1`` of the pair: the same pair and ray, the same patch)."""
        tree = self.tree
        n_facing, n_blocked = probe_counts(self.engine.visibility, rows, c, tree.start, tree.size, tree.perm,
                                           first, k)
        self.info["probe_rays"] += int(n_facing.sum())
        return n_facing, n_blocked

    def near(self, r: np.ndarray, c: np.ndarray, progress) -> None:
        """The near leaf pairs, exactly: one engine call a row leaf for its pairs (r, c) with r <= c;
        the pair (c, r) is their mirror by reciprocity, ``A_j F_ji = A_i F_ij`` (the engine's visibility
        is symmetric, ``V_ij == V_ji``), so each pair of patches is computed once."""
        tree, perm = self.tree, self.tree.perm
        t = time.perf_counter()
        pairs = 0       # counted here, not from the engine's counter: parts may share one engine (Dask threads)
        keep = r <= c
        r, c = r[keep], c[keep]
        order = np.lexsort((c, r))
        r, c = r[order], c[order]
        bounds = np.flatnonzero(np.diff(np.r_[-1, r, -1]))
        areas = np.asarray(self.engine_areas, np.float64)
        for g in range(len(bounds) - 1):
            a, e = bounds[g], bounds[g + 1]
            rows = self.node_rows(r[a])
            cols, ptr = _concat_ranges(None, tree.start[c[a:e]], tree.stop[c[a:e]])
            F = self.engine.block(perm[rows], perm[cols])
            pairs += F.size
            blocks = []                             # (rows, first column, values): one batch a row leaf
            for q in range(e - a):
                part = F[:, ptr[q]:ptr[q + 1]]
                blocks.append((rows, tree.start[c[a + q]], part))
                if c[a + q] != r[a]:             # the mirror block (c, r): F_ji = F_ij A_i / A_j
                    mirror = part.T * (areas[perm[rows]][None, :] / areas[perm[cols[ptr[q]:ptr[q + 1]]]][:, None])
                    blocks.append((cols[ptr[q]:ptr[q + 1]], tree.start[r[a]], mirror))
            self.out.add_dense(np.concatenate([x[0] for x in blocks]), [x[2].shape[0] for x in blocks],
                               [x[1] for x in blocks], [x[2].shape[1] for x in blocks],
                               np.concatenate([x[2].ravel() for x in blocks]))
            report(progress, g + 1, len(bounds) - 1)
        self.info["exact_pairs"] += pairs
        self.info["near_pairs"] = pairs
        self.info["time_near"] = time.perf_counter() - t

    def exact_rows(self, rows: np.ndarray, c: int) -> None:
        """Ask for F[rows][:, node c] with visibility (computed by :meth:`flush_exact`, a column node at a time)."""
        self.pending.setdefault(int(c), []).append(np.asarray(rows, np.int64))

    def flush_exact(self, progress) -> None:
        """The exact blocks asked for, one engine call per column node (its rows stacked)."""
        tree, perm = self.tree, self.tree.perm
        t = time.perf_counter()
        pairs = 0
        items = sorted(self.pending.items())
        for g, (c, parts) in enumerate(items):
            rows = np.concatenate(parts)
            F = self.edge_block(perm[rows], perm[tree.start[c]:tree.stop[c]])
            pairs += F.size
            # one block a part (rows of one far pair), their values F's rows in order: one batch
            self.out.add_dense(rows, [len(part) for part in parts], np.full(len(parts), tree.start[c]),
                               np.full(len(parts), F.shape[1]), F)
            report(progress, g + 1, len(items))
        self.pending.clear()
        self.info["exact_pairs"] += pairs
        self.info["time_exact"] += time.perf_counter() - t

    def edge_block(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """F[rows][:, cols] (patch numbers) across a shadow edge: each pair's visibility the unblocked
        share of ``edge_rays`` segments between hashed points of the two patches (the engine's full
        visibility when ``edge_rays`` is 0). These pairs lie in far blocks, apart by at least ``eta``
        times their clusters' size, so unweighted segments serve where near pairs need the kernel's."""
        k, vis = self.options.edge_rays, self.engine.visibility
        if k == 0 or vis is None:
            return self.engine.block(rows, cols)
        F = np.ascontiguousarray(self.engine.unoccluded(rows, cols))
        scale_by_edge_visibility(vis, F, rows, cols, k)
        return F


def _visibility_boxes(scene, engine: FormFactorEngine, tree: ClusterTree):
    """Node boxes in the visibility frame (padded patch boxes), or None without occluders."""
    vis = engine.visibility
    if vis is None or vis.cluster_pairs(scene, CLUSTER_SIZE) is None:
        return None
    return _node_boxes(vis.patch_lo[tree.perm], vis.patch_hi[tree.perm], tree.start, tree.stop, tree.left,
                       tree.right)


def _states(engine: FormFactorEngine, boxes, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Cluster-pair visibility of node pairs (clustervis.py's test on the nodes' boxes)."""
    out = np.full(len(r), VISIBLE, np.int8)
    if boxes is None or len(r) == 0:
        return out
    cv = engine.visibility.clusters
    a, b = np.minimum(r, c), np.maximum(r, c)     # the test is made for the canonical pair
    _cluster_pair_states(a, b, boxes[0], boxes[1], cv.tri, cv.normal, cv.d0, cv.tlo, cv.thi, cv.glo, cv.cell,
                         cv.g, cv.cstart, cv.clist, cv.tol, cv.margin, out)
    return out


def _groups_where(rows: np.ndarray, owner: np.ndarray, where: np.ndarray, c: np.ndarray):
    """The rows ``where`` (bool), still grouped by ``owner`` (non-decreasing group numbers), groups left
    empty dropped: ``(rows, row_ptr, c)`` as the probe rounds pass them."""
    kept = owner[where]                      # sorted already: its runs are the groups (no np.unique sort)
    starts = np.flatnonzero(np.r_[True, kept[1:] != kept[:-1]]) if len(kept) else np.zeros(0, np.int64)
    row_ptr = np.r_[starts, len(kept)].astype(np.int64)
    return rows[where], row_ptr, np.asarray(c, np.int64)[kept[starts]]


def _concat_ranges(perm: np.ndarray | None, start: np.ndarray, stop: np.ndarray):
    """``perm[start[k]:stop[k]]`` for every k, concatenated (the positions themselves when ``perm``
    is None), and the offsets of each."""
    size = stop - start
    ptr = np.zeros(len(size) + 1, np.int64)
    np.cumsum(size, out=ptr[1:])
    idx = np.repeat(start - ptr[:-1], size) + np.arange(ptr[-1], dtype=np.int64)
    return (idx if perm is None else perm[idx]), ptr
