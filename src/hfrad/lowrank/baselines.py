"""Baseline factorizers with the same eps semantics as HF, for comparisons.

* :func:`svd_factorization` -- LAPACK thin SVD of the whole matrix, truncated
  to the smallest rank within eps (the optimal rank; O(n^3)).
* :func:`randomized_factorization` -- randomized SVD (Halko, Martinsson & Tropp
  2011, Alg. 4.4 with power iterations), sample size grown until eps is met.
* :func:`sketch_factorization` -- single-pass randomized sketch (Tropp, Yurtsever,
  Udell & Cevher 2017, Alg. 7), one pass over column blocks, sketch grown until
  eps is met (each growth is a new pass; verification is an extra pass).

All return :class:`~hfrad.lowrank.factors.LowRank` with ``Q = U S``, ``V``
orthonormal and the *achieved* Frobenius error.
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.linalg as sla

from ..errors import FactorizationError, InputError
from ..validation import check_tolerance
from .factors import LowRank, sign_fix, truncation_rank


def _budget(A: np.ndarray, eps: float, relative: bool) -> tuple[float, float]:
    """(||A||_F^2, the squared error budget) of a randomized baseline."""
    norm2 = float(np.sum(np.square(A, dtype=np.float64)))
    return norm2, _target2(eps, relative, norm2)


def _target2(eps: float, relative: bool, norm2: float) -> float:
    return eps * eps * norm2 if relative else eps * eps


def _check(A, eps: float, dtype) -> np.ndarray:
    check_tolerance(eps)
    A = np.asarray(A, dtype=dtype)
    if A.ndim != 2:
        raise InputError(f"expected a 2-D matrix; got shape {A.shape}")
    return A


def svd_factorization(A, *, eps: float = 0.02, relative: bool = True, dtype=np.float32) -> LowRank:
    """Optimal truncated SVD: smallest k with ``||A - Q V^T||_F <= eps ||A||_F``.

    Parameters
    ----------
    A : (n, N) array_like
    eps, relative, dtype : as in :func:`~hfrad.lowrank.hf.hierarchical_factorization`

    Returns
    -------
    LowRank
        ``achieved_error = sqrt(sum(s[k:]^2))``.

    Notes
    -----
    O(n^3) time, O(n^2) memory: the reference the other methods are judged by.
    """
    A = _check(A, eps, dtype)
    t0 = time.perf_counter()
    try:
        U, s, Wt = sla.svd(A, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise FactorizationError("full SVD did not converge") from exc
    norm2 = float(np.sum(s.astype(np.float64) ** 2))
    k, d2 = truncation_rank(s, _target2(eps, relative, norm2))
    U, s, Wt = U[:, :k].copy(), s[:k], Wt[:k].copy()
    sign_fix(U, Wt)
    return LowRank(Q=U * s, V=Wt.T.copy(), achieved_error=math.sqrt(d2), norm=math.sqrt(norm2),
                   eps=float(eps), relative=relative, method="svd",
                   info={"time_total": time.perf_counter() - t0})


def _orth(Y: np.ndarray) -> np.ndarray:
    return sla.qr(Y, mode="economic", check_finite=False)[0]


def randomized_factorization(A, *, eps: float = 0.02, relative: bool = True, dtype=np.float32,
                             n_power_iter: int = 2, initial_rank: int = 64, growth: float = 1.5,
                             oversample: int = 10, rng=None) -> LowRank:
    """Randomized SVD whose sample size grows until the Frobenius target is met.

    With an orthonormal range basis P (n x l), ``||A - P P^T A||_F^2 =
    ||A||_F^2 - ||P^T A||_F^2`` exactly, so the error of every truncation of
    the SVD of ``P^T A`` is known without touching A again; l grows by
    ``growth`` until the target is within reach, then the smallest rank within
    eps is kept (close to optimal).

    Parameters
    ----------
    A : (n, N) array_like
    eps, relative, dtype : see :func:`svd_factorization`
    n_power_iter : int
        Subspace (power) iterations, re-orthonormalised each time (Halko Alg. 4.4).
    initial_rank, growth, oversample : sample-size schedule.
    rng : None, int or numpy.random.Generator
        Pass an int for reproducible results.

    Returns
    -------
    LowRank
        ``info["passes"]`` counts passes over A, ``info["sample_size"]`` the final l.
    """
    A = _check(A, eps, dtype)
    rng = np.random.default_rng(rng)
    t0 = time.perf_counter()
    n, N = A.shape
    norm2, target2 = _budget(A, eps, relative)
    l, passes = min(initial_rank + oversample, N, n), 0
    while True:
        Y = A @ rng.standard_normal((N, l)).astype(A.dtype)
        P = _orth(Y)
        for _ in range(n_power_iter):
            P = _orth(A @ _orth(A.T @ P))
            passes += 2
        Bm = P.T @ A
        passes += 2
        Ub, s, Wt = sla.svd(Bm, full_matrices=False, lapack_driver="gesdd", check_finite=False)
        kept2 = np.cumsum(s.astype(np.float64) ** 2)
        resid2 = np.maximum(norm2 - np.concatenate([[0.0], kept2]), 0.0)   # error of rank-i, i = 0..l
        ok = np.flatnonzero(resid2 <= target2)
        if ok.size or l >= min(n, N):
            break
        l = min(int(math.ceil(l * growth)), n, N)
    k = int(ok[0]) if ok.size else s.size
    U = P @ Ub[:, :k]
    Wt = Wt[:k].copy()
    sign_fix(U, Wt)
    return LowRank(Q=U * s[:k], V=Wt.T.copy(), achieved_error=math.sqrt(resid2[k]),
                   norm=math.sqrt(norm2), eps=float(eps), relative=relative, method="rsvd",
                   info={"time_total": time.perf_counter() - t0, "passes": passes, "sample_size": l})


def _column_blocks(A: np.ndarray, block_size: int):
    for i in range(0, A.shape[1], block_size):
        yield i, A[:, i:i + block_size]


def _sketch_once(A: np.ndarray, k: int, block_size: int, rng):
    """One pass (Tropp et al. 2017): range sketch Y = A Omega, co-range sketch W = Psi A."""
    n, N = A.shape
    ell = 2 * k + 1
    Psi = rng.standard_normal((ell, n)).astype(A.dtype)
    Y = np.zeros((n, k), A.dtype)
    W = np.empty((ell, N), A.dtype)
    for i, Aj in _column_blocks(A, block_size):
        # each block's test matrix rows come from the same stream: order-independent
        Y += Aj @ rng.standard_normal((Aj.shape[1], k)).astype(A.dtype)
        W[:, i:i + Aj.shape[1]] = Psi @ Aj
    P = _orth(Y)
    X = np.linalg.lstsq(Psi @ P, W, rcond=None)[0]            # (Psi P)^+ W, k x N
    Ux, s, Wt = sla.svd(X, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    return P @ Ux, s, Wt


def _truncation_errors(A: np.ndarray, U, s, Wt, norm2: float, block_size: int) -> np.ndarray:
    """Exact ``||A - U_i S_i Wt_i||_F^2`` for every i = 0..k in one pass over A.

    ``||A - U_i S_i W_i^T||^2 = ||A||^2 - 2 sum_{j<i} s_j u_j^T A w_j + sum_{j<i} s_j^2``
    (U and W orthonormal).
    """
    diag = np.zeros(s.size)
    for i, Aj in _column_blocks(A, block_size):
        diag += np.einsum("kb,bk->k", U.T @ Aj, Wt[:, i:i + Aj.shape[1]].T, dtype=np.float64)
    s64 = s.astype(np.float64)
    return np.maximum(norm2 + np.concatenate([[0.0], np.cumsum(s64 * s64 - 2 * s64 * diag)]), 0.0)


def sketch_factorization(A, *, eps: float = 0.02, relative: bool = True, dtype=np.float32,
                         initial_rank: int = 64, growth: float = 1.5, block_size: int = 256,
                         rng=None) -> LowRank:
    """Single-pass randomized sketch (Tropp et al. 2017), grown until eps is met.

    Each attempt reads A once, block by block (Y = A Omega, W = Psi A), then
    reconstructs ``A ~= P X`` with ``X = (Psi P)^+ W`` and truncates the SVD of
    X. The exact error of every truncation is measured by one verification
    pass; when no truncation meets the target the sketch grows by ``growth``
    and A is read again. ``info["passes"]`` reports the passes used.

    Parameters
    ----------
    A : (n, N) array_like
    eps, relative, dtype : see :func:`svd_factorization`
    initial_rank, growth : sketch-size schedule (range sketch k, co-range 2k+1).
    block_size : int
        Width of the column blocks streamed in each pass.
    rng : None, int or numpy.random.Generator

    Returns
    -------
    LowRank
    """
    A = _check(A, eps, dtype)
    rng = np.random.default_rng(rng)
    t0 = time.perf_counter()
    n, N = A.shape
    norm2, target2 = _budget(A, eps, relative)
    k, passes = min(initial_rank, n, N), 0
    while True:
        U, s, Wt = _sketch_once(A, k, block_size, rng)
        err2 = _truncation_errors(A, U, s, Wt, norm2, block_size)
        passes += 2
        ok = np.flatnonzero(err2 <= target2)
        if ok.size or k >= min(n, N):
            break
        k = min(int(math.ceil(k * growth)), n, N)
    r = int(ok[0]) if ok.size else s.size
    U, Wt = U[:, :r].copy(), Wt[:r].copy()
    sign_fix(U, Wt)
    return LowRank(Q=U * s[:r], V=Wt.T.copy(), achieved_error=math.sqrt(err2[r]),
                   norm=math.sqrt(norm2), eps=float(eps), relative=relative, method="sketch",
                   info={"time_total": time.perf_counter() - t0, "passes": passes, "sketch_rank": k})
