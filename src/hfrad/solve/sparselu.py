"""Many right-hand sides through one SciPy sparse LU, blocked and in parallel.

The near-field solver (:mod:`hfrad.solve.nearfield`) needs ``A^{-1} X`` for
the k columns of ``X = D_c Q`` once per channel to set up its k x k
capacitance matrices. SuperLU (``scipy.sparse.linalg.splu``) factors ``A``
well, but its solve walks L and U once per right-hand side: the set-up reads
``nnz(L + U)`` entries k times per distinct channel (k right-hand sides). Here
the triangular solves take the right-hand sides in panels of
:data:`PANEL` columns stored row-major, so each entry of L and U is read once
per panel and applied to a contiguous row of the panel (vectorized), and the
panels run in parallel (numba ``prange``): the same flops, ~PANEL times less
traffic through L and U.

SuperLU factors ``Pr A Pc = L U`` (L unit lower, U upper, both CSC), so
``A x = b`` is ``x = Pc U^{-1} L^{-1} Pr b``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["PANEL", "PanelSolver"]

#: Right-hand sides per panel: a row of a panel is a few SIMD vectors, a panel of n rows
#: ``4 n PANEL`` bytes in float32 (``8 n PANEL`` in float64); L and U are read
#: ``ceil(k / PANEL)`` times per channel instead of k.
PANEL = 64


@njit(cache=True, nogil=True)
def _forward_unit_lower(indptr, indices, data, X):
    """X <- L^{-1} X in place; L unit lower triangular, CSC (its stored diagonal is skipped)."""
    n, w = X.shape
    for j in range(n):
        for p in range(indptr[j], indptr[j + 1]):
            i = indices[p]
            if i > j:
                v = data[p]
                for c in range(w):
                    X[i, c] -= v * X[j, c]


@njit(cache=True, nogil=True)
def _backward_upper(indptr, indices, data, diag, X):
    """X <- U^{-1} X in place; U upper triangular, CSC, with diagonal ``diag``."""
    n, w = X.shape
    for j in range(n - 1, -1, -1):
        inv = 1.0 / diag[j]
        for c in range(w):
            X[j, c] *= inv
        for p in range(indptr[j], indptr[j + 1]):
            i = indices[p]
            if i < j:
                v = data[p]
                for c in range(w):
                    X[i, c] -= v * X[j, c]


@njit(cache=True, parallel=True)
def _solve_panels(Lp, Li, Lx, Up, Ui, Ux, Ud, panels):
    """Every panel (P, n, w) through L then U, the panels in parallel."""
    for b in prange(panels.shape[0]):
        _forward_unit_lower(Lp, Li, Lx, panels[b])
        _backward_upper(Up, Ui, Ux, Ud, panels[b])


class PanelSolver:
    """L and U of one SuperLU factorization, laid out to take many right-hand sides at once.

    Parameters
    ----------
    lu : scipy.sparse.linalg.SuperLU
        From ``splu(A)``.
    dtype : numpy dtype
        Precision of the solves (float32 halves the traffic and doubles the
        SIMD width; L and U are rounded to it).
    panel : int
        Columns solved together (see :data:`PANEL`).
    order : (n,) int, optional
        ``lu`` factors ``A[order][:, order]`` (a symmetric permutation, e.g. another
        matrix's fill-reducing order reused); the solves are still with A.

    Notes
    -----
    Memory: a copy of L and U (12 bytes per stored entry in float64, 8 in
    float32) while the object lives, plus one copy of the right-hand sides
    per :meth:`solve`. Results equal ``lu.solve`` to the rounding of ``dtype``.
    """

    def __init__(self, lu, dtype=np.float64, panel: int = PANEL, order=None) -> None:
        self.dtype, self.panel = np.dtype(dtype), int(panel)
        L, U = lu.L.tocsc(), lu.U.tocsc()
        self._L = (L.indptr, L.indices, L.data.astype(self.dtype))
        self._U = (U.indptr, U.indices, U.data.astype(self.dtype), U.diagonal().astype(self.dtype))
        self.n = L.shape[0]
        self._rows = np.empty(self.n, np.int64)
        self._rows[lu.perm_r] = np.arange(self.n)      # (Pr b)[perm_r[i]] = b[i]
        self._cols = np.asarray(lu.perm_c, np.int64)   # x = Pc y: x[i] = y[perm_c[i]]
        if order is None:
            #: the fill-reducing order: ``A[order][:, order]`` factors without reordering (``A Pc = A[:, order]``)
            self.order = np.argsort(self._cols)
        else:
            # lu factors A[order][:, order]: A x = b is that matrix's system in y = x[order], b[order]
            order = np.asarray(order, np.int64)
            self.order = order
            self._rows = order[self._rows]
            self._cols = self._cols[np.argsort(order)]

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``A^{-1} X`` for X (n, m); returns (n, m) in the solver's dtype."""
        n, m = X.shape
        w = self.panel
        n_panels = -(-m // w)
        panels = np.zeros((n_panels, n, w), self.dtype)
        for b in range(n_panels):
            cols = slice(b * w, min((b + 1) * w, m))
            panels[b, :, : cols.stop - cols.start] = X[self._rows, cols]
        _solve_panels(*self._L, *self._U, panels)
        out = np.empty((n, m), self.dtype)
        for b in range(n_panels):
            cols = slice(b * w, min((b + 1) * w, m))
            out[:, cols] = panels[b][self._cols, : cols.stop - cols.start]
        return out

