"""HF: the one-pass hierarchical factorization of a matrix given by column blocks.

Aguerre & Fernández 2016; docs/method.md, section 4. Column blocks ``A_j`` (n x b_j)
arrive left to right; each is compressed by a truncated SVD (a leaf) and
siblings are merged by a thin QR plus a small SVD, driven by a binary counter
over a stack. Nothing n x n is ever formed: memory is one block plus
O(log m) factor pairs.

Error accounting
----------------
Every truncation discards a matrix ``D`` whose squared Frobenius norm is the sum
of its dropped squared singular values. These discards are mutually orthogonal
in the Frobenius inner product ``<X, Y> = trace(X^T Y)``:

* a node's discard has its row space inside the span of the *kept* right
  factors of its children, ``blockdiag(V_1, V_2)``;
* a child's own discard has rows orthogonal to its kept ``V_i`` (the dropped
  right singular vectors are orthogonal to the kept ones), and, by induction,
  so do the discards of all its descendants restricted to their columns;
* discards of disjoint column sets are orthogonal trivially.

Hence ``||A - Q V^T||_F^2 = sum of all squared discards`` exactly (up to
rounding), which is what ``achieved_error`` reports.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np
import scipy.linalg as sla

from ..errors import FactorizationError, InputError
from ..formfactors.pieces import BlockPieces, gram64
from ..progress import ProgressCallback, report
from ..resources import spare_threads
from ..validation import check_tolerance
from .factors import LowRank, sign_fix, truncation_rank


@dataclass
class _Node:
    """One factored column range: ``A_node ~= U diag(s) V^T``, U and V orthonormal."""

    level: int
    U: np.ndarray        # (n, k) orthonormal columns
    s: np.ndarray        # (k,) singular values, descending
    V: np.ndarray        # (b_node, k) orthonormal columns
    norm2: float         # exact ||A_node||_F^2 of the original columns (float64)
    discarded2: float    # sum of squared discards in this subtree
    slack2: float        # budget given to this subtree and not used yet


def _svd(A: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD via LAPACK gesdd, falling back to gesvd; FactorizationError names ``where``."""
    try:
        return sla.svd(A, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    except np.linalg.LinAlgError:
        try:
            return sla.svd(A, full_matrices=False, lapack_driver="gesvd", check_finite=False)
        except np.linalg.LinAlgError as exc:
            raise FactorizationError(f"SVD did not converge in {where}") from exc


def _truncate(U, s, Wt, budget2: float):
    """Keep the smallest rank fitting ``budget2``; returns (U_k, s_k, Wt_k, discarded2)."""
    k, discarded2 = truncation_rank(s, budget2)
    U, s, Wt = U[:, :k], s[:k], Wt[:k]
    sign_fix(U, Wt)
    return U, s, Wt, discarded2


#: The Gram leaf is used where the leaf's budget is this many machine epsilons of ``||A_j||^2``
#: or more: a Gram matrix's eigenvalues carry an error of a few eps ``||A_j||^2``, so they pick
#: the rank reliably only well above that (float32, eps 0.02: budget 2e-4, threshold 1.2e-4).
_GRAM_MIN_EPS = 1e3
#: ... and for blocks at least this many times taller than wide (below, gesdd costs little).
_GRAM_MIN_ASPECT = 8
_GRAM_MARGIN = 0.9  # the rank is chosen within this share of the budget, for rounding


#: Rows of a column block taken to float64 at a time (8 MB at 256 columns: heap memory that is
#: reused, where a float64 copy of a whole block is fresh pages every block).
SLAB_ROWS = 4096


def frobenius2(A: np.ndarray, slab: int = SLAB_ROWS) -> float:
    """``||A||_F^2`` accumulated in float64, slab by slab of rows.

    Not ``np.square(A, dtype=np.float64)``: that is an n x b float64 copy of every column
    block (8 n b bytes), fresh pages each time, whose page faults cost more than the sum.
    """
    return float(sum(np.square(A[a:a + slab], dtype=np.float64).sum() for a in range(0, A.shape[0], slab)))


def _leaf(A: np.ndarray, norm2: float, budget2: float, j: int, a2: float | None = None) -> _Node:
    """Compress one column block ``A_j`` (n x b) by a truncated thin SVD.

    ``a2`` is ``||A||^2`` when the caller has it (float64); it differs from ``norm2``
    when the budget comes from a larger norm (the near-field split).
    """
    n, b = A.shape
    if norm2 == 0.0 or n == 0:
        return _Node(0, np.zeros((n, 0), A.dtype), np.zeros(0, A.dtype),
                     np.zeros((b, 0), A.dtype), norm2, 0.0, budget2)
    if n >= _GRAM_MIN_ASPECT * b:
        # the block's own norm, not ``norm2``: with the near-field split the budget is taken
        # from the norm before the near entries were moved out, which A no longer holds
        if a2 is None:
            a2 = frobenius2(A)
        if budget2 >= _GRAM_MIN_EPS * np.finfo(A.dtype).eps * a2:
            node = _leaf_gram(A, a2, norm2, budget2, j)
            if node is not None:
                return node
    U, s, Wt = _svd(A, f"leaf block {j}")
    U, s, Wt, d2 = _truncate(U, s, Wt, budget2)
    return _Node(0, np.ascontiguousarray(U), s, np.ascontiguousarray(Wt.T), norm2, d2, budget2 - d2)


def _leaf_gram(A: np.ndarray, a2: float, norm2: float, budget2: float, j: int) -> _Node | None:
    """The leaf from the Gram matrix: one SYRK (n b^2) instead of gesdd's ~4 n b^2 flops.

    The eigenvectors of ``A^T A`` give the kept right subspace ``V_k``; then
    ``A V_k = Q R`` (thin QR: one Cholesky QR, :func:`_cholesky_qr_svd`, else Householder)
    and ``R = U_r S W^T`` make ``(Q U_r) S (V_k W)^T``, the exact
    orthogonal projection ``A V_k V_k^T``, so the discard is ``||A||^2 - sum S^2`` (measured
    on the projection itself, not taken from the eigenvalues; ``a2`` = ``||A||^2`` in float64,
    ``norm2`` = the norm the budget was taken from). None when rounding left that discard
    over the budget (the caller then runs the full SVD).
    """
    lam, W = np.linalg.eigh((A.T @ A).astype(np.float64))       # ascending
    lam, W = np.clip(lam[::-1], 0.0, None), W[:, ::-1]
    k, _ = truncation_rank(np.sqrt(lam), _GRAM_MARGIN * budget2)
    Vk = np.ascontiguousarray(W[:, :k], dtype=A.dtype)
    Y = A @ Vk
    factors = _cholesky_qr_svd(Y)
    if factors is None:   # Y too far from orthogonal columns for one Cholesky QR: Householder
        Qm, R = sla.qr(Y, mode="economic", overwrite_a=True, check_finite=False)
        Ur, s, Wt = _svd(R, f"leaf block {j} (Gram)")
        U = Qm @ Ur
    else:
        U, s, Wt = factors
    discarded2 = max(a2 - float(np.sum(np.square(s, dtype=np.float64))), 0.0)
    if discarded2 > budget2:
        return None
    Vt = Wt.astype(A.dtype, copy=False) @ Vk.T
    sign_fix(U, Vt)
    return _Node(0, np.ascontiguousarray(U), s, np.ascontiguousarray(Vt.T), norm2, discarded2,
                 budget2 - discarded2)


#: One Cholesky QR orthonormalizes the leaf's ``Y = A V_k`` when its columns, scaled to unit
#: norm, are this close to orthonormal (smallest diagonal of the Cholesky factor at least this,
#: i.e. condition number below ~1 / this): its orthogonality is then that of the float32 product.
_CHOLQR_MIN_DIAGONAL = 0.1


def _cholesky_qr_svd(Y: np.ndarray):
    """SVD ``Y = U diag(s) W^T`` (n x k) by one Cholesky QR: ``(U, s, W^T)`` or None.

    The leaf's ``Y = A V_k`` has nearly orthogonal columns (``V_k`` are eigenvectors of
    ``A^T A``), so its Gram matrix, summed in float64 slab by slab, scaled to unit diagonal
    and factored ``R_s^T R_s``, gives ``Y = Q R`` with ``Q = Y D R_s^{-1}`` well conditioned;
    then ``R = U_r S W^T`` (float64, k x k) and ``U = Y (D R_s^{-1} U_r)`` in one product.
    About a third of Householder's cost (geqrf + orgqr + a product), with U orthonormal to
    the float32 rounding of that product. None when a column is zero or the scaled Gram
    matrix is not comfortably positive definite (``_CHOLQR_MIN_DIAGONAL``).
    """
    n, k = Y.shape
    G = gram64(Y, slab_rows=SLAB_ROWS)
    norms = np.sqrt(np.diag(G))
    if k == 0 or not norms.min() > 0.0:
        return None
    d = 1.0 / norms
    try:
        Rs = sla.cholesky(G * d[:, None] * d[None, :], lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    if not np.diag(Rs).min() >= _CHOLQR_MIN_DIAGONAL:
        return None
    Ur, s, Wt = _svd(Rs * norms[None, :], "the leaf's Cholesky QR")     # R = R_s D^{-1}
    M = d[:, None] * sla.solve_triangular(Rs, Ur, lower=False, check_finite=False)
    return Y @ M.astype(Y.dtype), s.astype(Y.dtype), Wt


def _orthogonalize(U1: np.ndarray, U2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Write ``U2 = U1 C + Q2 R2`` with ``[U1 Q2]`` orthonormal (block CGS2 + Householder QR)."""
    C = U1.T @ U2
    W = U2 - U1 @ C
    C2 = U1.T @ W          # second Gram-Schmidt pass: keeps float32 orthogonality
    W -= U1 @ C2
    C += C2
    Q2, R2 = sla.qr(W, mode="economic", overwrite_a=True, check_finite=False)
    return C, Q2, R2


#: The merge's core ``M`` ((ka + p) x (ka + kb)) is truncated from its Gram matrix (below) where
#: ``ka + kb`` is at least this (smaller cores cost gesdd little) ...
_GRAM_MERGE_MIN_WIDTH = 256
#: ... and the working dtype is no finer than this: the float64 Gram squares M's condition, so it
#: resolves singular values down to ~sqrt(eps64) sigma_1 (1.5e-8 sigma_1), finer than float32's
#: eps sigma_1 but not float64's.
_GRAM_MERGE_MAX_DTYPE_EPS_RATIO = 1e6    # np.finfo(dtype).eps / np.finfo(float64).eps at least this
_EPS64 = float(np.finfo(np.float64).eps)


def _gram_merge_applies(ka: int, kb: int, dtype) -> bool:
    """Whether a merge of ranks ``ka`` and ``kb`` in ``dtype`` tries the Gram core first."""
    return (ka + kb >= _GRAM_MERGE_MIN_WIDTH
            and float(np.finfo(dtype).eps) >= _GRAM_MERGE_MAX_DTYPE_EPS_RATIO * _EPS64)


def _merge_core_gram(M: np.ndarray, ka: int, budget2: float):
    """The merge's truncated core from ``M^T M`` in float64 (eigh) instead of gesdd of ``M``.

    ``M = [[S1, C S2], [0, R2 S2]]`` (working dtype, (ka + p) x (ka + kb)), R2 upper triangular.
    Its Gram matrix is assembled from the blocks (``S1^2``, ``S1 (C S2)``, and the SYRK of the
    right block column: a third of the flops of ``M^T M``), its eigenvectors ``W`` (float64,
    divide and conquer) pick the kept right subspace ``W_k`` within the budget, and ``Y = M W_k`` (float64) gives ``M W_k W_k^T = U_r S W_k^T`` with
    ``S = ||y_i||``, ``U_r = Y / S``. That is the exact orthogonal projection of M onto
    ``W_k``, so its discard is measured by Pythagoras, ``||M||^2 - ||Y||^2`` in float64 (not taken
    from the eigenvalues), as the module's error accounting needs.

    Returns
    -------
    (U_r (ka + p, k), s (k,), W_t (k, ka + kb), discarded2), in M's dtype, sign-fixed; or None
    where the budget is too small for the Gram's rounding (``_GRAM_MIN_EPS`` eps64 ``||M||^2``),
    the measured discard exceeds the budget, or ``U_r`` is not orthonormal to the working
    precision (``max |U_r^T U_r - I| > eps(dtype)``, measured in float64): the caller then
    runs gesdd on M.
    """
    dtype = M.dtype
    right = M[:, ka:].astype(np.float64)               # [C S2; R2 S2], (ka + p) x kb
    s1 = M[np.arange(ka), np.arange(ka)].astype(np.float64)
    m2 = float(np.dot(s1, s1)) + float(np.einsum("ij,ij->", right, right))
    if budget2 < _GRAM_MIN_EPS * _EPS64 * m2:
        return None
    width = M.shape[1]
    G = np.empty((width, width))
    G[:ka, :ka] = np.diag(s1 * s1)
    G[:ka, ka:] = s1[:, None] * right[:ka]
    G[ka:, :ka] = G[:ka, ka:].T
    G[ka:, ka:] = right.T @ right
    lam, W = sla.eigh(G, overwrite_a=True, check_finite=False, driver="evd")   # ascending
    del G
    lam = np.clip(lam[::-1], 0.0, None)
    # the whole budget, as gesdd's truncation (and the row-panelled merge of hfrad.distributed)
    # spends it: float64 eigenvalues and the float64 measure below agree to ~1e-13 ||M||^2, so a
    # measured discard over the budget (then gesdd) needs a tail within that of the budget
    k, _ = truncation_rank(np.sqrt(lam), budget2)
    Wk = W[:, ::-1][:, :k]
    del W
    Y = right @ Wk[ka:]                                 # M W_k, using M's zero and diagonal blocks
    Y[:ka] += s1[:, None] * Wk[:ka]
    s = np.sqrt(np.einsum("ij,ij->j", Y, Y))
    order = np.argsort(-s, kind="stable")              # near-equal eigenvalues may swap
    s, Y, Wk = s[order], Y[:, order], Wk[:, order]
    discarded2 = max(m2 - float(np.dot(s, s)), 0.0)
    if discarded2 > budget2 or (k and not s[-1] > 0.0):
        return None
    Y /= s
    if k:
        off = np.triu(sla.blas.dsyrk(1.0, Y, trans=1))      # upper triangle of Y^T Y (half a GEMM)
        off[np.diag_indices(k)] -= 1.0
        if np.max(np.abs(off)) > float(np.finfo(dtype).eps):
            return None
    Ur, Wt = Y.astype(dtype), np.ascontiguousarray(Wk.T, dtype=dtype)
    sign_fix(Ur, Wt)
    return Ur, s.astype(dtype), Wt, discarded2


def _merge(a: _Node, b: _Node, share2: float, where: str) -> _Node:
    """Merge two adjacent nodes (a left of b) into one, truncating within budget.

    ``[Q1 Q2] = [U1 Q2~] M`` with ``M = [[S1, C S2], [0, R2 S2]]``, ``M = U_r S W^T``;
    then ``Q = [U1 Q2~] U_r S`` and ``V = blockdiag(V1, V2) W``. The truncated ``U_r S W^T``
    comes from M's float64 Gram matrix where :func:`_gram_merge_applies` and the budget allows
    (:func:`_merge_core_gram`; its discard is measured on the projection), else from gesdd.
    """
    norm2 = a.norm2 + b.norm2
    budget2 = share2 + a.slack2 + b.slack2
    ka, kb = a.s.size, b.s.size
    dtype = a.U.dtype
    ba, bb = a.V.shape[0], b.V.shape[0]
    level = max(a.level, b.level) + 1
    if ka + kb == 0:
        return _Node(level, a.U, a.s, np.zeros((ba + bb, 0), dtype), norm2,
                     a.discarded2 + b.discarded2, budget2)
    if kb == 0 or ka == 0:
        # nothing to merge: the non-empty child already is an SVD of the node
        Ur, s = (a.U, a.s) if kb == 0 else (b.U, b.s)
        V = np.zeros((ba + bb, Ur.shape[1]), dtype)
        if kb == 0:
            V[:ba] = a.V
        else:
            V[ba:] = b.V
        M_U, s_, M_Wt = np.eye(s.size, dtype=dtype), s, np.eye(s.size, dtype=dtype)
        M_U, s_, M_Wt, d2 = _truncate(M_U, s_, M_Wt, budget2)
        return _Node(level, Ur @ M_U, s_, V @ M_Wt.T, norm2, a.discarded2 + b.discarded2 + d2, budget2 - d2)
    C, Q2, R2 = _orthogonalize(a.U, b.U)
    p = Q2.shape[1]
    M = np.zeros((ka + p, ka + kb), dtype)
    M[np.arange(ka), np.arange(ka)] = a.s
    M[:ka, ka:] = C * b.s
    M[ka:, ka:] = R2 * b.s
    core = None
    if _gram_merge_applies(ka, kb, dtype):
        core = _merge_core_gram(M, ka, budget2)
    if core is None:
        Ur, s, Wt = _svd(M, where)
        Ur, s, Wt, d2 = _truncate(Ur, s, Wt, budget2)
    else:
        Ur, s, Wt, d2 = core
    U = a.U @ Ur[:ka] + Q2 @ Ur[ka:]
    V = np.empty((ba + bb, s.size), dtype)
    V[:ba] = a.V @ Wt[:, :ka].T
    V[ba:] = b.V @ Wt[:, ka:].T
    return _Node(level, U, s, V, norm2, a.discarded2 + b.discarded2 + d2, budget2 - d2)


class ErrorBudget:
    """Squared-Frobenius budget of each truncation (see module docstring).

    Relative mode: a leaf may discard ``leaf_share eps^2 ||A_j||^2`` and a merge
    node ``(1 - leaf_share) / L eps^2 ||A_node||^2`` with ``L = ceil(log2 m)``;
    every column lies under at most L merge nodes of the binary-counter tree,
    so the total is <= ``eps^2 ||A||^2``. Absolute mode: ``eps^2 / (2m - 1)`` for
    each of the 2m - 1 truncations. Budget a node leaves unused is passed up to
    its parent (``slack2``), which keeps the total within target and brings
    the rank closer to optimal.
    """

    def __init__(self, eps: float, relative: bool, m: int, leaf_share: float):
        self.eps2, self.relative, self.m = eps * eps, relative, m
        self.levels = max(math.ceil(math.log2(m)), 0) if m > 0 else 0
        self.leaf_share = 1.0 if self.levels == 0 else leaf_share

    def leaf(self, norm2: float) -> float:
        """Squared Frobenius error a leaf of squared norm ``norm2`` may discard."""
        if self.relative:
            return self.leaf_share * self.eps2 * norm2
        return self.eps2 / (2 * self.m - 1)

    def merge(self, norm2: float) -> float:
        """Squared Frobenius error a merge node of squared norm ``norm2`` may discard (plus its children's slack)."""
        if self.relative:
            return (1.0 - self.leaf_share) / self.levels * self.eps2 * norm2
        return self.eps2 / (2 * self.m - 1)


class HFStream:
    """One-pass hierarchical factorization fed block by block.

    Parameters
    ----------
    n : int
        Rows of the matrix (patches).
    n_blocks : int
        Number of column blocks m that will be pushed (splits the error budget).
    eps, relative, dtype, leaf_share
        As in :func:`hfrad.lowrank.hf.hierarchical_factorization`.
    """

    def __init__(self, n: int, n_blocks: int, *, eps: float = 0.02, relative: bool = True,
                 dtype=np.float32, leaf_share: float = 0.5) -> None:
        check_tolerance(eps)
        if not (0.0 < leaf_share <= 1.0):
            raise InputError(f"leaf_share must be in (0, 1]; got {leaf_share!r}")
        self.n, self.n_blocks = int(n), int(n_blocks)
        self.eps, self.relative, self.leaf_share = float(eps), bool(relative), float(leaf_share)
        self.dtype = np.dtype(dtype)
        self._budget = ErrorBudget(self.eps, self.relative, max(self.n_blocks, 1), self.leaf_share)
        self.stack: list[_Node] = []
        self.blocks_done = 0
        self.columns_done = 0
        self.leaf_ranks: list[int] = []
        self.time_leaf = self.time_merge = 0.0
        #: Arrays a caller keeps with the stream's checkpoints (e.g. the near field so far).
        self.extra: dict[str, np.ndarray] = {}

    @property
    def current_rank(self) -> int:
        """Sum of the ranks on the stack: the width of what is held now."""
        return int(sum(node.s.size for node in self.stack))

    def push(self, block: np.ndarray, norm2: float | None = None, *, block_norm2: float | None = None) -> None:
        """Compress the next column block (n x b, an array or
        :class:`~hfrad.formfactors.pieces.BlockPieces`) and merge along the binary counter.

        ``norm2`` overrides ``||block||_F^2`` as the measure the relative error
        budget is taken from (the near-field split passes the norm of the block
        before its near entries were moved out, so eps stays relative to ``||G||_F``);
        ``block_norm2`` is ``||block||_F^2`` (float64) when the caller has it.
        """
        pieces = isinstance(block, BlockPieces)
        A = block.astype(self.dtype) if pieces else np.asarray(block, dtype=self.dtype)
        j = self.blocks_done
        if len(A.shape) != 2 or A.shape[0] != self.n:
            raise InputError(f"column block {j} must have shape ({self.n}, b); got {A.shape}")
        if j >= self.n_blocks:
            raise InputError(f"more than the announced n_blocks={self.n_blocks} column blocks were pushed")
        with spare_threads():   # a caller's BLAS threads, fewer where other processes want the cores
            t = time.perf_counter()
            leaf = compress_leaf_pieces if pieces else compress_leaf
            node = leaf(A, self._budget, j, norm2, block_norm2)
            self.leaf_ranks.append(node.s.size)
            self.time_leaf += time.perf_counter() - t
            t = time.perf_counter()
            while self.stack and self.stack[-1].level == node.level:  # binary counter
                node = merge_nodes(self.stack.pop(), node, self._budget, f"merge ending at block {j}")
        self.stack.append(node)
        self.time_merge += time.perf_counter() - t
        self.blocks_done += 1
        self.columns_done += A.shape[1]

    def finish(self) -> LowRank:
        """Merge what is left on the stack and return ``Q V^T`` with its achieved error."""
        if self.blocks_done != self.n_blocks:
            raise InputError(f"n_blocks={self.n_blocks} but {self.blocks_done} column blocks were given")
        t = time.perf_counter()
        stack = list(self.stack)
        if not stack:
            stack.append(_Node(0, np.zeros((self.n, 0), self.dtype), np.zeros(0, self.dtype),
                               np.zeros((0, 0), self.dtype), 0.0, 0.0, 0.0))
        with spare_threads() if len(stack) > 1 else contextlib.nullcontext():
            while len(stack) > 1:  # remaining nodes, top (smallest) down
                right, left = stack.pop(), stack.pop()
                stack.append(merge_nodes(left, right, self._budget, "final merge"))
        lowrank = root_lowrank(stack[0], self.eps, self.relative)
        self.time_merge += time.perf_counter() - t
        lowrank.info.update({"time_total": self.time_leaf + self.time_merge, "time_leaf": self.time_leaf,
                             "time_merge": self.time_merge, "n_blocks": self.blocks_done,
                             "leaf_ranks": self.leaf_ranks, "dtype": self.dtype.name,
                             "leaf_share": self.leaf_share})
        return lowrank


# -- The same tree, one piece at a time ---------------------------------------------
# HFStream runs these pieces in a loop; hfrad.distributed runs them as tasks on a
# cluster. Sharing them keeps both backends' truncations, budgets and results equal.

def compress_leaf(A: np.ndarray, budget: ErrorBudget, j: int, norm2: float | None = None,
                  block_norm2: float | None = None) -> _Node:
    """Leaf ``j`` of the tree: the truncated SVD of one column block ``A`` (n x b), within its share.

    ``A`` must already be in the working dtype; its norm accumulates in float64. ``norm2``
    overrides the norm the relative budget is taken from (see ``HFStream.push``);
    ``block_norm2`` is ``||A||_F^2`` (float64) when the caller has it (not read again).
    """
    a2 = block_norm2  # ||A||^2: when known, the leaf need not compute it again
    if norm2 is None:
        norm2 = a2 = frobenius2(A) if a2 is None else a2
    return _leaf(A, norm2, budget.leaf(norm2), j, a2)


def compress_leaf_pieces(P: BlockPieces, budget: ErrorBudget, j: int, norm2: float | None = None,
                         block_norm2: float | None = None) -> _Node:
    """:func:`compress_leaf` of a block in pieces, ``A = P_E D + P_R W X``, never forming A.

    ``W = Q R`` (thin QR, n s^2 flops for s skeleton columns) gives ``A = [P_E, P_R Q] C`` with
    ``C = [D; R X]`` ((m + s) x b) and ``[P_E, P_R Q]`` orthonormal (disjoint rows), so the
    truncated SVD of the small C is that of A, with the same discard; its left factor is lifted
    to n rows. ``A`` in the working dtype. The leaf's norm is measured on C (it equals
    ``||A||^2``; ``block_norm2``, the caller's figure of it, is not needed).
    """
    if P.is_dense:
        return compress_leaf(P.to_dense(), budget, j, norm2, block_norm2)
    dtype = P.dtype
    Q, R = sla.qr(np.asarray(P.W, np.float64), mode="economic", check_finite=False)
    m = P.rows.size
    C = np.empty((m + R.shape[0], P.X.shape[1]), dtype)
    C[:m] = P.dense
    C[m:] = R @ P.X
    a2 = frobenius2(C)
    if norm2 is None:
        norm2 = a2
    node = _leaf(C, norm2, budget.leaf(norm2), j, a2)
    U = np.empty((P.n, node.s.size), dtype)
    U[P.rows] = node.U[:m]
    U[P.far] = Q.astype(dtype) @ node.U[m:]
    node.U = U
    return node


def merge_nodes(left: _Node, right: _Node, budget: ErrorBudget, where: str) -> _Node:
    """Merge two adjacent nodes (``left`` covers the columns before ``right``'s) within the node's share."""
    return _merge(left, right, budget.merge(left.norm2 + right.norm2), where)


def root_lowrank(root: _Node, eps: float, relative: bool) -> LowRank:
    """``Q V^T`` of the root node, spending the budget the tree left unused (its discard is
    orthogonal to all others), with the achieved error; ``info`` is left for the caller."""
    # the root is already an SVD: truncating it keeps leading columns (no product with an identity,
    # which would cost 2 n k^2 flops)
    k, d2 = truncation_rank(root.s, root.slack2)
    Q, V = root.U[:, :k] * root.s[:k], np.ascontiguousarray(root.V[:, :k])
    return LowRank(Q=Q, V=V, achieved_error=math.sqrt(max(root.discarded2 + d2, 0.0)),
                   norm=math.sqrt(root.norm2), eps=eps, relative=relative, method="hf", info={})


def counter_tree(m: int) -> list[tuple[int, int]]:
    """The merges :class:`HFStream` performs for ``m`` blocks, as a tree.

    Nodes ``0 .. m-1`` are the leaves (column blocks, left to right); merge
    ``i`` of the returned list creates node ``m + i`` from ``(left, right)``.
    The last node created (node ``m - 1`` when m == 1) is the root. Merges
    whose children are both done may run at the same time: the tree has
    depth ``ceil(log2 m)``.

    Examples
    --------
    >>> counter_tree(3)
    [(0, 1), (3, 2)]
    """
    merges: list[tuple[int, int]] = []
    stack: list[tuple[int, int]] = []  # (level, node)
    for j in range(m):
        level, node = 0, j
        while stack and stack[-1][0] == level:  # binary counter, as in HFStream.push
            left_level, left = stack.pop()
            merges.append((left, node))
            level, node = max(left_level, level) + 1, m + len(merges) - 1
        stack.append((level, node))
    while len(stack) > 1:  # as in HFStream.finish
        (_, right), (_, left) = stack.pop(), stack.pop()
        merges.append((left, right))
        stack.append((0, m + len(merges) - 1))
    return merges


def _count_blocks(blocks, n_blocks: int | None) -> int:
    if n_blocks is not None:
        return int(n_blocks)
    try:
        return len(blocks)
    except TypeError:
        raise InputError("the number of column blocks must be known up front to split the error "
                         "budget: pass n_blocks=m, or give blocks as a sized sequence") from None


def hierarchical_factorization(blocks: Iterable[np.ndarray], n: int, *, eps: float = 0.02,
                               relative: bool = True, dtype=np.float32, leaf_share: float = 0.5,
                               n_blocks: int | None = None,
                               progress: ProgressCallback = None) -> LowRank:
    """Factor ``A = (A_1 ... A_m) ~= Q V^T`` in one pass over its column blocks.

    ``||A - Q V^T||_F <= eps ||A||_F`` (relative) or ``<= eps`` (absolute),
    guaranteed by the error budget and reported as achieved.

    Parameters
    ----------
    blocks : iterable of (n, b_j) array_like
        Consecutive column blocks of A, left to right. Each is read once and
        may be dropped by the caller afterwards (a generator is fine).
    n : int
        Number of rows of A.
    eps : float, keyword-only
        Frobenius tolerance, relative to ``||A||_F`` unless ``relative=False``.
    relative : bool
    dtype : numpy float dtype
        Working precision (float32 or float64); norms accumulate in float64.
    leaf_share : float in (0, 1]
        Fraction of the squared budget given to the leaves.
    n_blocks : int, optional
        m, the number of blocks; needed when ``blocks`` has no ``len``.
    progress : callable (done, total), optional

    Returns
    -------
    LowRank
        ``Q`` (n, k) = U S, ``V`` (N, k) orthonormal, N = sum b_j, with
        ``achieved_error`` = sqrt(sum of squared discards) = ``||A - Q V^T||_F``.

    Raises
    ------
    ValueError
        Bad eps/leaf_share, unknown block count, or a block with the wrong
        number of rows.
    FactorizationError
        An SVD did not converge (names the block).

    Notes
    -----
    Cost O(n b^2) per leaf and O(n (k1 + k2)^2) per merge; memory one block plus
    O(log m) factor pairs. Aguerre & Fernández 2016, section 3; docs/method.md,
    section 4.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> A = rng.standard_normal((60, 8)) @ rng.standard_normal((8, 60))
    >>> lr = hierarchical_factorization([A[:, i:i + 16] for i in range(0, 60, 16)], 60,
    ...                                 eps=1e-3, dtype=np.float64)
    >>> bool(np.linalg.norm(A - lr.Q @ lr.V.T) <= 1e-3 * np.linalg.norm(A))
    True
    """
    m = _count_blocks(blocks, n_blocks)
    stream = HFStream(n, m, eps=eps, relative=relative, dtype=dtype, leaf_share=leaf_share)
    t0 = time.perf_counter()
    for block in blocks:
        stream.push(block)
        report(progress, stream.blocks_done, m)
    lowrank = stream.finish()
    lowrank.info["time_total"] = time.perf_counter() - t0
    return lowrank
