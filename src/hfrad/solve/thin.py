"""Products of a tall n x k factor with a few columns, reading the factor once.

A relighting solve multiplies Q and V (n x k) by a handful of right-hand
sides (3 m: three colour channels, m emissions). OpenBLAS's GEMM with so few
columns packs the big operand first and runs at a fraction of the memory
bandwidth (``benchmarks/bench_solve.py --relight`` compares them); three
GEMVs read it three times. These kernels stream each row of the factor once through the cache
and do all the columns' work on it. Rows of ``X`` that are entirely zero
(patches that do not emit) are skipped in ``A^T X``: their rows of A are not
read at all.

Above :data:`THIN_MAX` columns the products go to BLAS, which is compute
bound and efficient there.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

__all__ = ["THIN_MAX", "matmul", "tmatmul"]

#: Up to this many right-hand sides the streaming kernels are used; above, BLAS.
THIN_MAX = 12


@njit(parallel=True, fastmath=True, cache=True)
def _rows_dot(A, ST, out):  # pragma: no cover - compiled
    """``out[i, c] = sum_j A[i, j] ST[c, j]``: row i of A is read once (then from L1, once per c)."""
    n, k = A.shape
    r = ST.shape[0]
    for i in prange(n):
        row = A[i]
        for c in range(r):
            s = ST[c]
            acc = A.dtype.type(0)
            for j in range(k):
                acc += row[j] * s[j]
            out[i, c] = acc


@njit(parallel=True, fastmath=True, cache=True)
def _rows_axpy(A, X, chunks):  # pragma: no cover - compiled
    """``(A^T X)^T`` as (r, k): per chunk of rows, ``P[c] += X[i, c] A[i]``, skipping zero rows of X."""
    n, k = A.shape
    r = X.shape[1]
    size = (n + chunks - 1) // chunks
    part = np.zeros((chunks, r, k), A.dtype)
    for t in prange(chunks):
        P = part[t]
        for i in range(t * size, min(n, (t + 1) * size)):
            nonzero = False
            for c in range(r):
                if X[i, c] != 0:
                    nonzero = True
            if not nonzero:
                continue
            row = A[i]
            for c in range(r):
                x = X[i, c]
                p = P[c]
                for j in range(k):
                    p[j] += x * row[j]
    out = np.zeros((r, k), A.dtype)
    for t in range(chunks):
        out += part[t]
    return out


def matmul(A: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``A @ S`` for a C-contiguous tall ``A`` (n, k) and ``S`` (k, r), in A's dtype.

    Returns
    -------
    (n, r) array of A's dtype
    """
    n, k = A.shape
    r = S.shape[1]
    if r > THIN_MAX or not A.flags.c_contiguous or k == 0:
        return A @ S.astype(A.dtype, copy=False)
    out = np.empty((n, r), A.dtype)
    _rows_dot(A, np.ascontiguousarray(S.T, dtype=A.dtype), out)
    return out


def tmatmul(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``A.T @ X`` for a C-contiguous tall ``A`` (n, k) and ``X`` (n, r), in A's dtype.

    Returns
    -------
    (k, r) array of A's dtype
    """
    n, k = A.shape
    r = X.shape[1]
    if r > THIN_MAX or not A.flags.c_contiguous or k == 0:
        return A.T @ X.astype(A.dtype, copy=False)
    chunks = max(1, min(numba.get_num_threads(), n // 256))
    return _rows_axpy(A, np.ascontiguousarray(X, dtype=A.dtype), chunks).T
