"""``(I - D N)^{-1} b`` by a Chebyshev-accelerated Neumann series: the near field of a relighting solve.

The near-field solver (:mod:`hfrad.solve.nearfield`) applies ``A_c^{-1}``,
``A_c = I - D_c N``, to every new emission. SuperLU's triangular solves do it
exactly but one right-hand side and one channel at a time, on one thread,
through L and U (which hold several times the entries of N: fill-in), so an RGB
solve reads ``nnz(L + U)`` entries three times. Here ``T = D_c N`` (forward)
or ``T = N^T D_c`` (adjoint) is applied in sweeps, each reading N once for
every channel and emission together on every core (numba ``prange`` over rows).
While the iterate is local (a lamp: its emitters and, after t sweeps, t rings of
near neighbours), a sweep computes only those rows (:class:`_Support`).

The plain series ``x_{t+1} = b + T x_t`` converges at the spectral radius
rho of T. T's eigenvalues are real: reciprocity (``A_i F_ij = A_j F_ji``)
makes ``N = diag(rho_max / A) S`` with S symmetric, so T is similar to a
symmetric matrix, and they lie in ``[-rho, rho]``. Chebyshev semi-iteration
on that interval (Golub & Varga 1961),

    x_1 = b + T x_0,    x_{t+1} = x_{t-1} + w_{t+1} (b + T x_t - x_{t-1}),
    w_2 = 2 / (2 - rho^2),    w_{t+1} = 1 / (1 - rho^2 w_t / 4),

converges at ``rho / (1 + sqrt(1 - rho^2))`` per sweep instead of rho (0.56 ->
0.31, 0.9 -> 0.63) for the same work. rho is bounded from above by
:func:`spectral_bound` (Collatz-Wielandt: for nonnegative N and any positive
x, ``rho <= max_i (N x)_i / x_i``); ``D_c <= 1`` so N's bound holds for every
channel.

A solve stops when the residual ``b + T x_t - x_t`` is below ``tol`` of the
iterate (max norm, all columns): the error is then about ``tol / (1 - rho)``
relative. When rho's bound is not below 1 (overlapping faces can give rows of F
above 1) or the sweeps do not converge, the caller falls back to a sparse LU.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit, prange

__all__ = ["NEUMANN_TOL", "MAX_SWEEPS", "neumann_solve", "spectral_bound"]

#: Relative residual (max norm) at which the sweeps stop: two orders below the smallest
#: eps a precompute takes (1e-3), and two above float32 rounding (``2^-24 ~ 6e-8``), near
#: which an iterate with float32 N stagnates.
NEUMANN_TOL = 1e-5

#: Sweeps before giving up (the caller then uses a sparse LU).
MAX_SWEEPS = 200

#: Once the iterate's support holds this share of the rows, every row is swept (no more tracking).
ALL_ROWS_SHARE = 0.5


@njit(cache=True, parallel=True, fastmath=True)
def _sweep(indptr, indices, data, rows, src, x, prev, b, scale, omega, out, change, size):  # pragma: no cover
    """One sweep over the listed rows, (n, w) columns: ``y = b + scale * (M src)``,
    ``out = prev + omega (y - prev)``; per listed row the largest residual ``|y - x|`` and ``|out|``.

    Columns go in groups of four with the sums in registers: accumulating into
    ``out[i, c]`` would make every entry of N a store and a reload of ``out``.
    """
    w = x.shape[1]
    for r in prange(rows.shape[0]):
        i = rows[r]
        lo, hi = indptr[i], indptr[i + 1]
        big = 0.0
        top = 0.0
        for c0 in range(0, w, 4):
            m = min(4, w - c0)
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            if m == 4:
                for p in range(lo, hi):
                    v, j = data[p], indices[p]
                    a0 += v * src[j, c0]
                    a1 += v * src[j, c0 + 1]
                    a2 += v * src[j, c0 + 2]
                    a3 += v * src[j, c0 + 3]
            elif m == 3:
                for p in range(lo, hi):
                    v, j = data[p], indices[p]
                    a0 += v * src[j, c0]
                    a1 += v * src[j, c0 + 1]
                    a2 += v * src[j, c0 + 2]
            elif m == 2:
                for p in range(lo, hi):
                    v, j = data[p], indices[p]
                    a0 += v * src[j, c0]
                    a1 += v * src[j, c0 + 1]
            else:
                for p in range(lo, hi):
                    a0 += data[p] * src[indices[p], c0]
            for t in range(m):
                c = c0 + t
                acc = a0 if t == 0 else (a1 if t == 1 else (a2 if t == 2 else a3))
                y = b[i, c] + scale[i, c] * acc
                z = prev[i, c] + omega * (y - prev[i, c])
                out[i, c] = z
                big = max(big, abs(y - x[i, c]))
                top = max(top, abs(z))
        change[r] = big
        size[r] = top


@njit(cache=True)
def _reach(indptr, indices, frontier, reached, added):  # pragma: no cover
    """Mark in ``reached`` every row linked to a frontier row by the pattern; the newly marked
    rows go to ``added`` (returns how many)."""
    count = 0
    for j in frontier:
        for p in range(indptr[j], indptr[j + 1]):
            i = indices[p]
            if not reached[i]:
                reached[i] = True
                added[count] = i
                count += 1
    return count


class _Support:
    """The rows an iterate can be nonzero on, grown by one ring of neighbours per sweep.

    ``A^{-1} b`` for a local emission (a lamp) is local too: the near field only
    links patches within its radius, so after t sweeps the iterate lives on
    the emitters and t rings of their neighbours. Sweeping just those rows
    makes a lamp's solve cost its neighbourhood instead of all of N; once
    they are half the rows (:data:`ALL_ROWS_SHARE`), every row is swept.
    """

    def __init__(self, reach: tuple[np.ndarray, np.ndarray] | None, b: np.ndarray):
        n = b.shape[0]
        self._reach = reach
        self._all = np.arange(n)
        self._reached = np.any(b != 0, axis=1)
        self._frontier = np.flatnonzero(self._reached)
        self._added = np.empty(n, np.int64)
        if reach is None or self._frontier.size > ALL_ROWS_SHARE * n:
            self._reach = None

    def rows(self) -> np.ndarray:
        """The rows the next sweep must compute: the support so far and its frontier's neighbours."""
        if self._reach is None:
            return self._all
        count = _reach(self._reach[0], self._reach[1], self._frontier, self._reached, self._added)
        self._frontier = self._added[:count].copy()
        rows = np.flatnonzero(self._reached)
        if rows.size > ALL_ROWS_SHARE * self._all.size:
            self._reach = None
            return self._all
        return rows


def spectral_bound(M: sp.csr_matrix, iterations: int = 60, rtol: float = 0.01) -> float:
    """An upper bound on the spectral radius of ``|M|`` (hence of M and of ``D M``, ``M D``, 0 <= D <= 1).

    Power iteration on ``|M|`` from a positive vector kept positive; the
    Collatz-Wielandt bound ``max_i (|M| x)_i / x_i`` holds for any positive x
    and tightens as x approaches the Perron vector (stops when it is within
    ``rtol`` of the lower bound ``min_i``, or after ``iterations``).
    """
    A = abs(sp.csr_matrix(M, dtype=np.float64))
    n = A.shape[0]
    if n == 0 or A.nnz == 0:
        return 0.0
    x = np.ones(n)
    upper = np.inf
    for _ in range(iterations):
        y = A @ x
        ratio = y / x
        upper, lower = min(upper, float(ratio.max())), float(ratio.min())
        if upper - lower <= rtol * upper:
            break
        x = y / y.max() + 1e-3          # positive: rows without entries stay in the bound
    return upper


def _omegas(rho: float):
    """Chebyshev weights w_1 = 1, w_2, w_3, ... for spectrum in [-rho, rho]."""
    r2 = rho * rho
    omega = 1.0
    yield omega
    omega = 2.0 / (2.0 - r2)
    while True:
        yield omega
        omega = 1.0 / (1.0 - 0.25 * r2 * omega)


def neumann_solve(M: sp.csr_matrix, b: np.ndarray, *, rho: float, pre: np.ndarray | None = None,
                  post: np.ndarray | None = None, tol: float = NEUMANN_TOL, max_sweeps: int = MAX_SWEEPS,
                  reach: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray | None, int]:
    """Solve ``(I - post M pre) x = b`` by Chebyshev-accelerated sweeps.

    Parameters
    ----------
    M : (n, n) CSR matrix
        N (forward) or N^T (adjoint); its dtype sets the precision of the products.
    b : (n, w) float
        Right-hand sides (all channels and emissions side by side).
    rho : float
        Upper bound on the spectral radius of ``post M pre`` (:func:`spectral_bound`);
        its eigenvalues must be real. 0 gives the plain Neumann series.
    pre, post : (n, w) float, optional
        Row scales applied before / after M, per column (``D`` of each column's channel).
    tol : float
        Stop when ``max |b + T x_t - x_t| <= tol max |x_{t+1}|``.
    max_sweeps : int
    reach : (indptr, indices) of the pattern of ``M^T``, optional
        With it, each sweep computes only the rows the iterate can reach so far
        (the emitters and one more ring of neighbours per sweep) until they are
        half of all rows: a lamp's solve then costs its neighbourhood, not all of M.
        The result is the same.

    Returns
    -------
    x : (n, w) float64, or None
        None when ``rho >= 1`` or the sweeps did not converge within ``max_sweeps``.
    sweeps : int
        Products with M done.
    """
    if not 0.0 <= rho < 1.0:
        return None, 0
    b = np.ascontiguousarray(b, np.float64)
    n, w = b.shape
    post = np.ones((n, w)) if post is None else np.ascontiguousarray(post, np.float64)
    pre = None if pre is None else np.ascontiguousarray(pre, np.float64)
    # every iterate is zero off the rows swept so far (out too, before its first sweep)
    prev, x, out = b.copy(), b.copy(), np.zeros_like(b)
    change, size = np.empty(n), np.empty(n)
    support = _Support(reach, b)
    smallest = np.inf
    for sweep, omega in zip(range(1, max_sweeps + 1), _omegas(rho)):
        rows = support.rows()
        src = x if pre is None else pre * x
        _sweep(M.indptr, M.indices, M.data, rows, src, x, prev, b, post, omega, out, change, size)
        prev, x, out = x, out, prev
        step = float(change[:rows.size].max(initial=0.0))
        top = float(size[:rows.size].max(initial=0.0))
        if step <= tol * top:
            return x, sweep
        # a wrong bound on rho shows as residuals growing well past their smallest
        if not np.isfinite(step) or step > 10.0 * smallest:
            return None, sweep
        smallest = min(smallest, step)
    return None, max_sweeps
