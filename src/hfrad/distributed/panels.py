"""The top merges of HF's tree split by row panels, so no worker holds a whole n x k factor.

A merge of two adjacent nodes ``U_1 S_1 V_1^T`` and ``U_2 S_2 V_2^T`` (U's n x k_1 and
n x k_2, orthonormal) is the truncated SVD of ``X = [U_1 S_1, U_2 S_2]`` (n x K, K = k_1 + k_2)
followed by ``V = blockdiag(V_1, V_2) W``. Here the rows of the U's are cut into P
panels that live on different workers and the merge runs in three steps:

1. **Panel Gram** (one task per panel, on the worker holding it):
   ``G_p = Y_p^T Y_p`` in float64 with ``Y_p = [U_1, U_2]`` restricted to the panel's rows
   (n_p x K; accumulated slab by slab, so the task holds its panel plus a K x K matrix).
2. **Small step** (one task): ``G = D (sum_p G_p) D`` with ``D = diag(S_1, S_2)`` is ``X^T X``;
   its eigenvectors ``W`` (K x K) and eigenvalues ``s^2`` are X's right singular vectors and
   squared singular values. The rank ``k`` is the smallest whose dropped ``sum s_i^2`` fits the
   node's budget, exactly as :func:`hfrad.lowrank.hf.merge_nodes` truncates.
3. **Panel forming** (one task per panel, where it lives): ``U_p = Y_p B`` with
   ``B = D W_k diag(1/s_k)`` (K x k), and each column chunk of V (one per subtree below,
   on the worker that made it) becomes ``V_c W_k[rows of its child]``.

Why a float64 Gram matrix and not a QR of stacked panels (TSQR): flat TSQR stacks P
R-factors of ``min(n_p, K) x K``, which is the whole of X once panels are shorter than K
(1M patches on 64 workers: n_p = 15.6K rows against K = 2k ~ 24K), and a TSQR tree needs
log P rounds each way. The Gram matrix needs one reduction of K x K matrices whatever
n_p is. Its accuracy: ``G`` is exact to float64 rounding (``Y`` is float32 or float64
data, its products accumulate in float64), so the singular values come out to about
``1e-8 s_1`` and ``U`` is orthonormal to about ``1e-16 (s_1 / s_k)^2``; the float32 factors
themselves carry ``6e-8 s_1``, and the kept ``s_k`` are far above ``1e-8 s_1`` at any eps a
user sets (this is the argument of the Gram leaf in :mod:`hfrad.lowrank.hf`). The result is
the serial merge's in exact arithmetic: same rank, same discard, the same ``U S V^T``
(columns may differ in sign, and within clusters of equal singular values by a rotation).

Everything here is numpy on arrays; :mod:`hfrad.distributed.run` makes the tasks.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..lowrank.factors import truncation_rank

#: Rows of a panel taken to float64 at a time (bounds a panel task's extra memory to SLAB x K words).
SLAB_ROWS = 4096


def panel_bounds(n: int, panels: int) -> np.ndarray:
    """Row bounds of ``panels`` near-equal row panels of n rows: ``(panels + 1,)`` ints from 0 to n."""
    panels = max(1, min(int(panels), max(n, 1)))
    return np.linspace(0, n, panels + 1).round().astype(np.int64)


def panel_gram(U1: np.ndarray, U2: np.ndarray, slab: int = SLAB_ROWS) -> np.ndarray:
    """``[U1 U2]^T [U1 U2]`` of one row panel in float64, K x K (K = k1 + k2).

    Parameters
    ----------
    U1, U2 : (n_p, k1), (n_p, k2) arrays
        The panel's rows of the two children's left factors.
    """
    k1, k2 = U1.shape[1], U2.shape[1]
    G = np.zeros((k1 + k2, k1 + k2))
    Y = np.empty((min(slab, U1.shape[0]), k1 + k2))
    for a in range(0, U1.shape[0], slab):
        h = min(slab, U1.shape[0] - a)
        Y[:h, :k1], Y[:h, k1:] = U1[a:a + h], U2[a:a + h]
        G += Y[:h].T @ Y[:h]
    return G


def merge_small(G: np.ndarray, left: dict, right: dict, share2: float) -> dict:
    """The small step of a panelled merge: rank, singular values and the K x k matrices.

    Parameters
    ----------
    G : (K, K) float64
        Sum of :func:`panel_gram` over all panels (unscaled: ``[U1 U2]^T [U1 U2]``).
    left, right : dict
        The children's ``s`` (singular values), ``norm2``, ``discarded2`` and ``slack2``
        (the bookkeeping of :class:`hfrad.lowrank.hf` nodes).
    share2 : float
        This merge's own squared budget (``ErrorBudget.merge`` of the summed norms); the
        children's slack is added, as :func:`hfrad.lowrank.hf.merge_nodes` does.

    Returns
    -------
    dict
        ``B`` (K, k) float64: ``U_p = [U1_p U2_p] B``; ``W1`` (k1, k), ``W2`` (k2, k): the
        V chunks' multipliers; ``meta``: ``s`` (k,), ``norm2``, ``discarded2``, ``slack2``.
    """
    s1, s2 = np.asarray(left["s"], np.float64), np.asarray(right["s"], np.float64)
    k1 = s1.size
    d = np.concatenate([s1, s2])
    if d.size == 0:
        return {"B": np.zeros((0, 0)), "W1": np.zeros((0, 0)), "W2": np.zeros((0, 0)),
                "meta": {"s": d, "norm2": left["norm2"] + right["norm2"],
                         "discarded2": left["discarded2"] + right["discarded2"],
                         "slack2": share2 + left["slack2"] + right["slack2"]}}
    lam, W = np.linalg.eigh(G * d[:, None] * d[None, :])          # ascending
    lam, W = np.clip(lam[::-1], 0.0, None), W[:, ::-1]
    s = np.sqrt(lam)
    budget2 = share2 + left["slack2"] + right["slack2"]
    k, d2 = truncation_rank(s, budget2)
    s, Wk = s[:k], np.ascontiguousarray(W[:, :k])
    B = (d[:, None] * Wk) / s[None, :] if k else np.zeros((d.size, 0))
    meta = {"s": s, "norm2": left["norm2"] + right["norm2"],
            "discarded2": left["discarded2"] + right["discarded2"] + d2, "slack2": budget2 - d2}
    return {"B": B, "W1": Wk[:k1], "W2": Wk[k1:], "meta": meta}


def panel_form(U1: np.ndarray, U2: np.ndarray, B: np.ndarray, dtype, slab: int = SLAB_ROWS) -> np.ndarray:
    """The merged node's rows of this panel: ``[U1 U2] B`` (n_p x k) in float64, stored as ``dtype``.

    float64 because ``B`` holds ``1/s_k``: a float32 product would lose orthogonality as
    ``6e-8 s_1 / s_k``.
    """
    k1 = U1.shape[1]
    out = np.empty((U1.shape[0], B.shape[1]), dtype)
    B1, B2 = B[:k1], B[k1:]
    for a in range(0, U1.shape[0], slab):
        out[a:a + slab] = U1[a:a + slab] @ B1 + U2[a:a + slab] @ B2   # float32 @ float64 -> float64
    return out


def chunk_update(V: np.ndarray, W: np.ndarray) -> np.ndarray:
    """A column chunk of the merged V: ``V_c W`` (rows of W: the chunk's child's columns), in V's dtype."""
    return (V @ W.astype(V.dtype, copy=False)) if W.shape[1] else np.zeros((V.shape[0], 0), V.dtype)


def root_panel(U: np.ndarray, meta: dict) -> np.ndarray:
    """Rows of ``Q = U_k S_k`` of the root, truncated with the slack the tree left (as ``root_lowrank``)."""
    k, _ = truncation_rank(meta["s"], meta["slack2"])
    return U[:, :k] * np.asarray(meta["s"][:k], U.dtype)


def root_chunk(V: np.ndarray, meta: dict) -> np.ndarray:
    """Rows of the root's V, truncated as :func:`root_panel`."""
    k, _ = truncation_rank(meta["s"], meta["slack2"])
    return np.ascontiguousarray(V[:, :k])


def root_error(meta: dict) -> tuple[int, float]:
    """The root's rank and achieved Frobenius error (all discards, including the root's truncation)."""
    k, d2 = truncation_rank(meta["s"], meta["slack2"])
    return k, math.sqrt(max(meta["discarded2"] + d2, 0.0))


def timed(kind: str, node: int, fn, *args, **extra):
    """Run ``fn(*args)``; returns (result, record) with wall and CPU seconds of the call."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args)
    rec = {"kind": kind, "node": int(node), "seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0}
    rec.update(extra)
    return out, rec
