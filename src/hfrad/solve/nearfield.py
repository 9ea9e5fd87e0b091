"""Solves with the near-field split: Woodbury around the sparse ``I - D_c N``.

With ``G = N + Q V^T`` (N sparse near field, :mod:`hfrad.lowrank.nearfield`)
and ``D_c = diag(rho_c / rho_max)``, channel c solves

    (A_c - U_c V^T) B_c = E_c,    A_c = I - D_c N  (sparse),  U_c = D_c Q.

Sherman-Morrison-Woodbury around ``A_c``:

    B_c = x_c + Z_c K_c^{-1} V^T x_c,   x_c = A_c^{-1} E_c,
    Z_c = A_c^{-1} D_c Q  (n x k),      K_c = I_k - V^T Z_c  (k x k, inverted once).

Set-up (once): SciPy's SuperLU factors ``A_c`` (``scipy.sparse.linalg.splu``)
and takes the k columns of ``D_c Q`` in panels
(:class:`~hfrad.solve.sparselu.PanelSolver`) to give ``Z_c`` and ``K_c``; the
LU is then dropped. A relighting solve applies ``A_c^{-1}`` once, by the
Chebyshev-accelerated Neumann series of ``D_c N`` (:mod:`hfrad.solve.neumann`:
every channel and emission in one pass over N per sweep, on every core; only the rows a
local emission has reached so far), and reads V (its rows under a nonzero ``x``) and
``Z_c`` once. Channels with equal ``D_c`` (grey reflectances) share one
``Z``. Where the factorization's error leaves room, each ``Z_c`` is stored as
16-bit integers with a scale per row (:class:`~hfrad.solve.quantized.QuantizedRows`):
half the bytes to read, and ``K_c`` is computed from the stored ``Z_c``, so the solve is
Woodbury's exact inverse of the operator ``A_c - A_c Z_c V^T`` whose distance to
``I - R_c F`` the error figures measure. A series that does not converge falls back to SuperLU (factored then).
The adjoint solve (``trans="T"``) applies ``A_c^{-T}`` twice instead
(``B = x + A^{-T} V K^{-T} Q^T D x``) and keeps no second n x k matrix.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import FactorizationError, InputError
from ..lowrank.hf import SLAB_ROWS, spare_threads
from ..lowrank.factors import LowRank
from . import thin
from .bounds import power_sigma_max
from .neumann import neumann_solve, spectral_bound
from .quantized import QuantizedRows
from .readonly import read_only, read_only_csr
from .sparselu import PanelSolver
from .woodbury import (N_CHANNELS, HFactorization, capacitance_applied, invert_capacitance,
                       low_rank_correction)

__all__ = ["NearFieldFactorization", "SOLVER", "QUANTIZE_SHARE"]

#: How the solve works, as recorded in .hfr files and reports.
SOLVER = "woodbury+neumann(I - D_c N)"
#: ``Z_c`` is stored in 16 bits when the operator error that adds (its bound
#: ``(1 + ||N||_2) ||Z_c - Z~_c||_F ||V||_2``, :attr:`NearFieldFactorization.quantization_error`)
#: is at most this share of the factorization's achieved error: the error figures then grow by
#: at most 1%.
QUANTIZE_SHARE = 0.01


def _lu_solve(lu, X: np.ndarray, trans: str = "N") -> np.ndarray:
    """``A^{-1} X`` (or ``A^{-T} X``) column by column.

    A loop of single-column solves: SciPy's SuperLU solve with many columns is
    the slower of the two for this use (``benchmarks/`` compares them).
    """
    if X.ndim == 1 or X.shape[1] == 1:
        return lu.solve(np.ascontiguousarray(X, dtype=np.float64), trans=trans)
    out = np.empty(X.shape, np.float64, order="F")
    for j in range(X.shape[1]):
        out[:, j] = lu.solve(np.ascontiguousarray(X[:, j], dtype=np.float64), trans=trans)
    return out


def _checked_near_field(N, n: int) -> sp.csr_matrix:
    """N as float64 CSR (no copy when it is one), or InputError unless it is an (n, n) matrix."""
    if not (sp.issparse(N) or isinstance(N, np.ndarray)) or N.ndim != 2 or N.shape != (n, n):
        raise InputError(f"N (the near field) must be a sparse or dense ({n}, {n}) matrix in the internal "
                         f"order; got {type(N).__name__} of shape {getattr(N, 'shape', None)}")
    return sp.csr_matrix(N, dtype=np.float64)


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
        The inverses ``K_c^{-1}`` (as stored in an .hfr file).
    near_solution : (d, n, k) float or QuantizedRows, optional
        ``Z_c = A_c^{-1} D_c Q`` for the d distinct channels (as stored in an
        .hfr file). With ``capacitance`` it skips the set-up; otherwise both are
        computed (a sparse LU and a solve with k right-hand sides per distinct channel).
    quantize : bool or None
        Store the computed ``Z_c`` as 16-bit rows (:class:`QuantizedRows`); None
        (default) does for float32 factors where the operator error that adds
        (:attr:`quantization_error`) is at most ``QUANTIZE_SHARE`` of the
        achieved error (float64 factors keep float64 ``Z_c``).

    Raises
    ------
    InputError
        As :class:`HFactorization`; also N not (n, n), ``near_solution`` not
        (d, n, k) for the d distinct channels.
    FactorizationError
        ``I - D_c N`` or a capacitance matrix ``K_c`` is singular.

    Notes
    -----
    Immutable as :class:`HFactorization`: ``N`` (its ``data``, ``indices``,
    ``indptr``), ``Z`` (array or :class:`QuantizedRows`) and
    ``capacitance_inv`` are read-only too.
    Memory: Q, V and one ``Z`` per distinct channel (n k each, the factors'
    dtype, or 2 bytes an entry quantized), N (float64 and a copy in the factors' dtype) and the three k x k
    inverses ``K_c^{-1}``. Set-up holds one channel's SuperLU factors and
    their panel copy at a time. A forward solve reads V, each distinct Z
    once, and N once per sweep of the series for all channels and emissions.
    """

    solver = SOLVER

    def __init__(self, perm, Q, V, N, rho_max, reflectance, lowrank: LowRank, *, capacitance=None,
                 near_solution=None, quantize: bool | None = None, sigma_max=None, params: dict | None = None,
                 scene=None, stats=None):
        self._set_state(perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene, stats)
        self._sources = self._channel_sources()
        #: for each channel, its Z in the stack of distinct channels
        self._stored = [self.distinct_channels.index(s) for s in self._sources]
        self.N = read_only_csr(_checked_near_field(N, self.n_patches))
        # the sweeps read N in the factors' precision (float32: half the traffic)
        self._sweep_N = read_only_csr(self.N.astype(self.dtype))
        self._sweep_NT = None
        self._lus: dict[int, object] = {}
        #: sweeps of the Neumann series in the last solve (0 when SuperLU solved it)
        self.last_sweeps = 0
        self._quantization_error: np.ndarray | None = None
        self._quantize = quantize
        with spare_threads():   # BLAS threads that other processes leave free (hfrad.lowrank.hf)
            Z, K_inv = self._near_solution(near_solution, capacitance, quantize)
        self.Z = Z if isinstance(Z, QuantizedRows) else read_only(Z)   # QuantizedRows holds read-only arrays
        self.capacitance_inv = read_only(K_inv)

    @property
    def distinct_channels(self) -> list[int]:
        """The channels with their own ``D_c`` (one ``Z`` each; grey scenes have one)."""
        return sorted(set(self._sources))

    def _channel_sources(self) -> list[int]:
        """For each channel, the first channel with the same ``D_c`` (grey scenes share one Z and K)."""
        src = []
        for c in range(N_CHANNELS):
            src.append(next(s for s in range(c + 1) if np.array_equal(self._D[:, s], self._D[:, c])))
        return src

    def _factor(self, c: int):
        """SuperLU of ``A_c = I - D_c N`` (a fresh factorization; callers keep or drop it)."""
        A = (sp.identity(self.n_patches, format="csr") - sp.diags(self._D[:, c]) @ self.N).tocsc()
        try:
            # N's pattern is symmetric (near is a symmetric relation): minimum degree on A^T + A, and
            # SuperLU's symmetric mode (diagonal pivots preferred, a threshold of 0.1 still guards a small
            # one; A is diagonally dominant, so the diagonal pivots are stable and the row
            # permutation search of the general mode is wasted work)
            return splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1,
                        options={"SymmetricMode": True})
        except RuntimeError as exc:
            raise FactorizationError(f"channel {c}: I - D_c N is singular ({exc})") from exc

    def _near_solution(self, stored_Z, stored_K, quantize: bool | None):
        """``Z`` (distinct channels, n, k; array or QuantizedRows) and ``K_c^{-1}`` (3, k, k): as stored, or computed."""
        distinct = self.distinct_channels
        shape = (len(distinct), self.n_patches, self.rank)
        if stored_Z is not None and stored_K is not None:
            Z = stored_Z if isinstance(stored_Z, QuantizedRows) else np.asarray(stored_Z, self.dtype)
            if Z.shape != shape:
                raise InputError(f"near_solution must have shape {shape} (one (n, k) A_c^-1 D_c Q per "
                                 f"distinct channel {distinct}); got {Z.shape}")
            return Z, super()._capacitance_inv(stored_K)
        Z = np.empty(shape, self.dtype)
        for z, c in enumerate(distinct):
            if self.rank:
                Z[z] = self._ainv_dq(c)
        if quantize is not False and self.rank:
            coded = QuantizedRows.stack([QuantizedRows.encode(Zz) for Zz in Z])
            error = self._quantization_bound(coded)
            if quantize or (self.dtype == np.float32 and error.max() <= QUANTIZE_SHARE * self.achieved_error):
                Z, self._quantization_error = coded, error
        K_inv = np.empty((N_CHANNELS, self.rank, self.rank), self.dtype)
        for z, c in enumerate(distinct):
            if self.rank:   # K from the Z the solve reads: Woodbury then inverts A_c - A_c Z_c V^T exactly
                K = np.eye(self.rank) - self._vt_times(Z[z])
                K_inv[c] = invert_capacitance(K, f"channel {c}: I - V^T A_c^-1 D_c Q", self.dtype)
        for c, s in enumerate(self._sources):
            K_inv[c] = K_inv[s]
        return Z, K_inv

    def _vt_times(self, Zz, slab: int = SLAB_ROWS) -> np.ndarray:
        """(k, k) float64 ``V^T Z``: products of row slabs in the factors' dtype, summed in float64.

        As the plain solver's capacitance (:func:`~hfrad.solve.woodbury.capacitance`): a float64
        product would be the same ``2 n k^2`` flops at half the float32 rate plus float64 copies
        of V and of each Z (``8 n k`` bytes each); a slab's copy is ``slab k`` entries.
        Summing per slab keeps float32 rounding at that of a ``slab``-long dot product.
        """
        K = np.zeros((self.rank, self.rank))
        for a in range(0, self.n_patches, slab):
            rows = slice(a, min(a + slab, self.n_patches))
            part = Zz.decode(rows) if isinstance(Zz, QuantizedRows) else Zz[rows]
            K += (self.V[rows].T @ part.astype(self.dtype, copy=False)).astype(np.float64)
        return K

    def _quantization_bound(self, coded: QuantizedRows) -> np.ndarray:
        """(3,) bound on ``||A_c (Z_c - coded_c) V^T||_2``: ``(1 + ||N||_2) ||dZ_c||_F ||V||_2``.

        ``||N||_2 <= sqrt(max row sum * max column sum)`` (N >= 0) and ``D_c <= 1``;
        ``||V||_2`` by power iteration (from below: 1% margin).
        """
        absN = abs(self.N)
        norm_N = float(np.sqrt(absN.sum(axis=1).max() * absN.sum(axis=0).max())) if self.N.nnz else 0.0
        norm_V = 1.01 * power_sigma_max(self.V, np.eye(self.rank, dtype=self.dtype))
        per_z = [(1 + norm_N) * coded[z].error_bound() * norm_V for z in range(coded.shape[0])]
        return np.array([per_z[z] for z in self._stored])

    @cached_property
    def quantization_error(self) -> np.ndarray:
        """(3,) float, read-only: upper bound on the operator error that 16-bit ``Z_c`` add (0 for float ``Z_c``).

        Known from the set-up when it quantized; otherwise (a loaded file) the
        first access computes it from the stored scales, with a power
        iteration for ``||V||_2`` (O(nk) per step); later accesses are free.
        """
        if self._quantization_error is not None:
            return read_only(self._quantization_error)
        return read_only(self._quantization_bound(self.Z) if isinstance(self.Z, QuantizedRows)
                         else np.zeros(N_CHANNELS))

    @property
    def near_solution_storage(self) -> str:
        """How ``Z_c`` is stored: ``"int16 rows"`` or the factors' dtype name."""
        return "int16 rows" if isinstance(self.Z, QuantizedRows) else self.Z.dtype.name

    def _ainv_dq(self, c: int, chunk: int = 1024) -> np.ndarray:
        """(n, k) ``A_c^{-1} D_c Q`` in the factors' dtype: k right-hand sides through SuperLU in panels.

        The LU and its panel copy live only for this call (one channel at a time).
        In float32 the panels are ~1e-6 relative, far below the factorization's eps.
        """
        solver = PanelSolver(self._factor(c), self.dtype)
        d = self._D[:, c:c + 1].astype(self.dtype)
        out = np.empty((self.n_patches, self.rank), self.dtype)
        for j in range(0, self.rank, chunk):
            cols = slice(j, min(j + chunk, self.rank))
            out[:, cols] = solver.solve(d * self.Q[:, cols])
        return out

    def _storage_error(self) -> np.ndarray:
        return self.quantization_error

    def _operator_error(self) -> np.ndarray:
        """(3,) probed error of the operator the solve inverts: ``D_c N + A_c Z_c V^T`` against ``R_c F``."""
        return self.stats.operator_error(self.Q, self.V, self._D, near=self.N, low_rank=self._applied_low_rank)

    def _applied_low_rank(self, c: int, W: np.ndarray) -> np.ndarray:
        """``A_c Z_c W`` (n, p), float64: the low-rank part ``U_c = A_c Z_c`` (``D_c Q`` up to rounding
        or quantization) applied to W (k, p)."""
        Zz = self.Z[self._stored[c]]
        Y = (Zz.matmul(W) if isinstance(Zz, QuantizedRows) else Zz @ W.astype(self.dtype)).astype(np.float64)
        return Y - self._D[:, c:c + 1] * (self.N @ Y)

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

    @cached_property
    def near_spectral_bound(self) -> float:
        """Upper bound on the spectral radius of every ``D_c N`` (that of N).

        The first access runs a power iteration on ``|N|`` (O(nnz(N)) per
        step, :func:`~hfrad.solve.neumann.spectral_bound`); later ones are free.
        """
        return spectral_bound(self.N)

    def _sweep_transposed(self) -> sp.csr_matrix:
        """N^T in the sweeps' precision (the adjoint's sweeps; its pattern guides the forward ones), made once."""
        if self._sweep_NT is None:
            self._sweep_NT = read_only_csr(self._sweep_N.T.tocsr())
        return self._sweep_NT

    def _near_inverse(self, X: np.ndarray, adjoint: bool) -> np.ndarray:
        """``A_c^{-1} X_c`` (or ``A_c^{-T} X_c``) for X (n, 3, m), every channel: the Neumann series,
        SuperLU where it does not converge."""
        n, C, m = X.shape
        scale = np.repeat(self._D, m, axis=1)                    # (n, 3 m), column c * m + j
        b = X.reshape(n, C * m)
        N, NT = self._sweep_N, self._sweep_transposed()
        # the rows reached from row j by a sweep with M are the nonzeros of M's column j: M^T's pattern
        if adjoint:
            x, sweeps = neumann_solve(NT, b, rho=self.near_spectral_bound, pre=scale, reach=(N.indptr, N.indices))
        else:
            x, sweeps = neumann_solve(N, b, rho=self.near_spectral_bound, post=scale, reach=(NT.indptr, NT.indices))
        if x is not None:
            self.last_sweeps = sweeps
            return x.reshape(n, C, m)
        self.last_sweeps = 0
        trans = "T" if adjoint else "N"
        out = np.empty((n, C, m))
        for c, s in enumerate(self._sources):
            if s not in self._lus:
                self._lus[s] = self._factor(s)
            out[:, c, :] = _lu_solve(self._lus[s], X[:, c, :], trans).reshape(n, m)
        return out

    def _add_far_correction(self, x: np.ndarray) -> np.ndarray:
        """``x_c + Z_c K_c^{-1} V^T x_c`` for x (n, 3, m), in place: V read once, each distinct ``Z`` once."""
        n, C, m = x.shape
        S = capacitance_applied(self.V, self.capacitance_inv, x)                         # (k, 3, m)
        which = self._stored[:C]
        if isinstance(self.Z, QuantizedRows):
            self.Z.add_products(x, S, which)
            return x
        for z in set(which):
            chans = [c for c in range(C) if which[c] == z]
            W = thin.matmul(self.Z[z], S[:, chans, :].reshape(self.rank, len(chans) * m))
            x[:, chans, :] += W.reshape(n, len(chans), m)
        return x

    def _solve(self, E: np.ndarray, adjoint: bool) -> np.ndarray:
        """Radiosity ``B_c = (I - R_c F)^{-1} E_c`` per channel (see module docstring); E (n, 3, m), user order."""
        Ei = self._to_internal(E)                                          # (n, 3, m)
        x = self._near_inverse(Ei, adjoint)
        if self.rank == 0:
            return self._to_user(x)
        # the adjoint uses D_c Q where the forward solve's operator has A_c Z_c: they differ by the
        # stored Z_c's rounding (quantization_error bounds it), far below the factorization error
        if adjoint:   # B = x + A^{-T} V K^{-T} Q^T D x
            W = low_rank_correction(self.Q, self.V, self._D, self.capacitance_inv, x, adjoint=True)
            sweeps = self.last_sweeps
            out = x + self._near_inverse(W, adjoint=True)
            self.last_sweeps += sweeps
        else:         # B = x + Z K^{-1} V^T x
            out = self._add_far_correction(x)
        return self._to_user(out)

    def with_reflectance(self, reflectance) -> "NearFieldFactorization":
        """The same factorization with new reflectances <= rho_max (new sparse LUs and K_c)."""
        rho = self._checked_reflectance(reflectance)
        return NearFieldFactorization(self.perm, self.Q, self.V, self.N, self.rho_max, rho, self.lowrank,
                                      quantize=self._quantize, params=self.params, scene=self.scene,
                                      stats=self.stats)

    def __repr__(self) -> str:
        return (f"NearFieldFactorization(n_patches={self.n_patches}, rank={self.rank}, "
                f"near_entries={self.N.nnz}, relative_error={self.relative_error:.3g}, dtype={self.dtype.name}, "
                f"near_solution={self.near_solution_storage!r})")
