"""Solves with the near-field split: Woodbury around a sparse LU of ``I - D_c N``.

With ``G = N + Q V^T`` (N sparse near field, :mod:`hfrad.factorize.nearfield`)
and ``D_c = diag(rho_c / rho_max)``, channel c solves

    (A_c - U_c V^T) B_c = E_c,    A_c = I - D_c N  (sparse),  U_c = D_c Q.

Sherman-Morrison-Woodbury around ``A_c`` (factored once by SciPy's SuperLU,
``scipy.sparse.linalg.splu``):

    B_c = x_c + A_c^{-1} U_c K_c^{-1} V^T x_c,   x_c = A_c^{-1} E_c,
    K_c = I_k - V^T A_c^{-1} U_c                 (k x k, inverted once).

A solve reads Q and V once each (2nk words, for the three channels together)
plus two sparse triangular solve pairs per channel; nothing else n x k is kept.
Setting up K_c costs one sparse solve with k right-hand sides per channel
(:class:`~hfrad.solve.sparselu.PanelSolver`: panels of columns through L and U).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import FactorizationError
from ..factorize.lowrank import LowRank
from .sparselu import PanelSolver
from .woodbury import N_CHANNELS, HFactorization, invert_capacitance, low_rank_correction

__all__ = ["NearFieldFactorization", "SOLVER"]

#: How the solve works, as recorded in .hfr files and reports.
SOLVER = "woodbury+splu(I - D_c N)"


def _lu_solve(lu, X: np.ndarray, trans: str = "N") -> np.ndarray:
    """``A^{-1} X`` (or ``A^{-T} X``) column by column.

    SuperLU's multi-right-hand-side solve is measured 6-10x slower here than a
    loop of single solves (2,000 patches, 570 columns: 6.3 s vs 1.0 s).
    """
    if X.ndim == 1 or X.shape[1] == 1:
        return lu.solve(np.ascontiguousarray(X, dtype=np.float64), trans=trans)
    out = np.empty(X.shape, np.float64, order="F")
    for j in range(X.shape[1]):
        out[:, j] = lu.solve(np.ascontiguousarray(X[:, j], dtype=np.float64), trans=trans)
    return out


class NearFieldFactorization(HFactorization):
    """A factored radiosity system ``G = N + Q V^T``: solve ``(I - R_c F) B_c = E_c``.

    Same interface as :class:`~hfrad.solve.woodbury.HFactorization` (``solve``,
    ``solve(trans="T")``, ``with_reflectance``, ``rank``, ``error_estimate()``).

    Parameters
    ----------
    perm : (n,) int
        Internal order: internal index t holds user patch ``perm[t]``.
    Q, V : (n, k) float, internal order
        ``G_int - N ~= Q V^T``.
    N : (n, n) sparse, internal order
        The near field of ``G_int = diag(rho_max) F`` (internal order).
    rho_max, reflectance, lowrank, sigma_max, params, scene
        As for :class:`HFactorization`.
    capacitance : (3, k, k) float, optional
        The inverses ``K_c^{-1}`` (as stored in an .hfr file); computed
        (one sparse solve with k right-hand sides per channel) when not given.

    Notes
    -----
    Memory: Q, V (2 n k in the factor dtype), N, its three sparse LU factors
    and the three k x k inverses ``K_c^{-1}`` (in the factors' dtype).
    Per solve O(n k + nnz(LU)) per right-hand side and channel.
    """

    solver = SOLVER

    def __init__(self, perm, Q, V, N, rho_max, reflectance, lowrank: LowRank, *, capacitance=None,
                 sigma_max=None, params: dict | None = None, scene=None, stats=None):
        self._set_state(perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene, stats)
        self._sources = self._channel_sources()
        self.N = sp.csr_matrix(N, dtype=np.float64)
        self._splu = self._factor_near()
        self.capacitance_inv = self._capacitance_inv(capacitance)

    def _channel_sources(self) -> list[int]:
        """For each channel, the first channel with the same ``D_c`` (grey scenes share one LU and K)."""
        src = []
        for c in range(N_CHANNELS):
            src.append(next(s for s in range(c + 1) if np.array_equal(self._D[:, s], self._D[:, c])))
        return src

    def _factor_near(self) -> list:
        """SuperLU of ``A_c = I - D_c N`` per distinct channel (shared by channels with equal ``D_c``)."""
        eye = sp.identity(self.n_patches, format="csr")
        lus = []
        for c, s in enumerate(self._sources):
            if s != c:
                lus.append(lus[s])
                continue
            A = (eye - sp.diags(self._D[:, c]) @ self.N).tocsc()
            try:
                # N's pattern is symmetric (near is a symmetric relation): minimum degree on A^T + A
                lus.append(splu(A, permc_spec="MMD_AT_PLUS_A"))
            except RuntimeError as exc:
                raise FactorizationError(f"channel {c}: I - D_c N is singular ({exc})") from exc
        return lus

    def _capacitance_inv(self, stored) -> np.ndarray:
        """(3, k, k) ``K_c^{-1}``, ``K_c = I_k - V^T A_c^{-1} D_c Q``: ``stored`` checked, or computed."""
        if stored is not None or self.rank == 0:
            return super()._capacitance_inv(stored)
        out = np.empty((N_CHANNELS, self.rank, self.rank), self.dtype)
        for c, s in enumerate(self._sources):
            if s != c:
                out[c] = out[s]
                continue
            K = np.eye(self.rank) - self._v_ainv_dq(c)
            out[c] = invert_capacitance(K, f"channel {c}: I - V^T A_c^-1 D_c Q", self.dtype)
        return out

    def _v_ainv_dq(self, c: int, chunk: int = 1024) -> np.ndarray:
        """(k, k) float64 ``V^T A_c^{-1} D_c Q``, k right-hand sides through the sparse LU in panels.

        In the factors' precision (float32: ~1e-6 relative, far below the factorization's
        eps), ``chunk`` columns at a time so that only n x chunk of ``A_c^{-1} D_c Q`` is held.
        """
        solver = PanelSolver(self._splu[c], self.dtype)
        d = self._D[:, c:c + 1].astype(self.dtype)
        out = np.empty((self.rank, self.rank))
        for j in range(0, self.rank, chunk):
            cols = slice(j, min(j + chunk, self.rank))
            out[:, cols] = self.V.T @ solver.solve(d * self.Q[:, cols])
        return out

    def _power_sigma(self, c: int, rtol: float = 1e-6, max_iter: int = 300) -> float:
        """sigma_max(D_c (N + Q V^T)) by power iteration on A^T A, O(nk + nnz(N)) per step."""
        d, N, Q, V = self._D[:, c], self.N, self.Q.astype(np.float64), self.V.astype(np.float64)
        x = np.full(self.n_patches, 1.0 / np.sqrt(max(self.n_patches, 1)))
        sigma = 0.0
        for _ in range(max_iter):
            y = d * (N @ x + Q @ (V.T @ x))                       # A x
            z = N.T @ (d * y) + V @ (Q.T @ (d * y))              # A^T A x
            nz = float(np.linalg.norm(z))
            if nz == 0.0:
                return 0.0
            new, x = np.sqrt(nz), z / nz                         # ||A^T A x|| -> sigma^2
            if abs(new - sigma) <= rtol * new:
                break
            sigma = new
        return float(np.linalg.norm(d * (N @ x + Q @ (V.T @ x))))

    def _sigma_estimates(self) -> np.ndarray:
        """(3,) sigma_max(D_c (N + Q V^T)) per channel, for eq. 5 (the achieved error is ``||G - N - Q V^T||_F``)."""
        sigma = np.empty(N_CHANNELS)
        for c, s in enumerate(self._sources):
            sigma[c] = sigma[s] if s != c else self._power_sigma(c)
        return sigma

    def _solve(self, E: np.ndarray, adjoint: bool) -> np.ndarray:
        """Radiosity ``B_c = (I - R_c F)^{-1} E_c`` per channel (see module docstring); E (n, 3, m), user order."""
        trans = "T" if adjoint else "N"
        Ei = E[self.perm]                                                  # (n, 3, m), internal order
        # x_c = A_c^{-1} E_c (or A_c^{-T}); forward B = x + A^{-1} D Q K^{-1} V^T x,
        # adjoint B = x + A^{-T} V K^{-T} Q^T D x
        x = np.stack([_lu_solve(self._splu[c], Ei[:, c, :], trans) for c in range(N_CHANNELS)], axis=1)
        if self.rank == 0:
            return x[self.inv_perm]
        W = low_rank_correction(self.Q, self.V, self._D, self.capacitance_inv, x, adjoint)
        out = x + np.stack([_lu_solve(self._splu[c], W[:, c, :], trans) for c in range(N_CHANNELS)], axis=1)
        return out[self.inv_perm]

    def with_reflectance(self, reflectance) -> "NearFieldFactorization":
        """The same factorization with new reflectances <= rho_max (new sparse LUs and K_c)."""
        rho = self._checked_reflectance(reflectance)
        return NearFieldFactorization(self.perm, self.Q, self.V, self.N, self.rho_max, rho, self.lowrank,
                                      params=self.params, scene=self.scene, stats=self.stats)

    def __repr__(self) -> str:
        return (f"NearFieldFactorization(n_patches={self.n_patches}, rank={self.rank}, "
                f"near_entries={self.N.nnz}, relative_error={self.relative_error:.3g}, dtype={self.dtype.name})")
