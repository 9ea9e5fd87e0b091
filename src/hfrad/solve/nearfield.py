"""Solves with the near-field split: Woodbury around the sparse ``I - D_c N``.

With ``G = N + Q V^T`` (N sparse near field, :mod:`hfrad.lowrank.nearsplit`)
and ``D_c = diag(rho_c / rho_max)``, channel c solves

    (A_c - U_c V^T) B_c = E_c,    A_c = I - D_c N  (sparse),  U_c = D_c Q.

Sherman-Morrison-Woodbury around ``A_c``:

    B_c = x_c + Z_c K_c^{-1} V^T x_c,   x_c = A_c^{-1} E_c,
    Z_c = A_c^{-1} D_c Q  (n x k),      K_c = I_k - V^T Z_c  (k x k, inverted once).

Set-up (once): SciPy's SuperLU factors ``A_c`` (``scipy.sparse.linalg.splu``;
the channels after the first in its fill-reducing order, as every ``A_c`` has N's
pattern) and takes the k columns of ``D_c Q`` in panels
(:class:`~hfrad.solve.sparselu.PanelSolver`) to give ``Z_c`` and ``K_c``; the
LU is then dropped. Above :data:`hfrad.memory.NEAR_LU_MOST_ENTRIES` entries a row of N
(clustered meshes, whose LUs hold 10-17 times N's entries) the set-up sweeps the
Neumann series instead (:class:`NeumannColumns`, :func:`near_setup_runner`): no LU at all.
The set-up is pure functions (:func:`channel_solver`,
:func:`near_columns`, :func:`row_maxima`, :func:`column_products`) that a runner
runs in this process (:class:`InProcess`) or as Dask tasks
(:mod:`hfrad.distributed.assembly`), with the same result. A relighting solve applies ``A_c^{-1}`` once, by the
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

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import FactorizationError, InputError
from ..memory import NEUMANN_COLUMNS
from ..lowrank.hf import SLAB_ROWS
from ..resources import spare_threads
from ..lowrank.factors import LowRank
from . import thin
from .bounds import power_sigma_max
from .neumann import neumann_solve, spectral_bound
from .quantized import QuantizedRows
from .readonly import read_only, read_only_csr
from .sparselu import PanelSolver
from .woodbury import (N_CHANNELS, HFactorization, capacitance_applied, invert_capacitance,
                       low_rank_correction)

__all__ = ["NearFieldFactorization", "SOLVER", "QUANTIZE_SHARE", "InProcess", "NeumannColumns", "neumann_channel",
           "SETUP_TOL", "near_setup_runner", "channel_solver", "solver_order",
           "near_columns", "row_maxima", "column_products", "factor_near"]

#: How the solve works, as recorded in .hfr files and reports.
SOLVER = "woodbury+neumann(I - D_c N)"
#: ``Z_c`` is stored in 16 bits when the operator error that adds (its bound
#: ``(1 + ||N||_2) ||Z_c - Z~_c||_F ||V||_2``, :meth:`NearFieldFactorization.quantization_error`)
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


def near_operator(N: sp.csr_matrix, d: np.ndarray) -> sp.csc_matrix:
    """``A_c = I - D_c N`` (CSC) for the channel scale ``d`` (n,)."""
    return (sp.identity(N.shape[0], format="csr") - sp.diags(d) @ N).tocsc()


def factor_near(N: sp.csr_matrix, d: np.ndarray, channel: int = 0, order=None):
    """SuperLU of ``A_c = I - D_c N`` (``A_c[order][:, order]`` when ``order`` is given: no reordering).

    N's pattern is symmetric (near is a symmetric relation): minimum degree on
    ``A^T + A``, and SuperLU's symmetric mode (diagonal pivots preferred, a threshold
    of 0.1 still guards a small one; A is diagonally dominant, so the diagonal pivots
    are stable and the row permutation search of the general mode is wasted work).
    Every channel's ``A_c`` has N's pattern, so one channel's fill-reducing order
    serves the others (``order``): the ordering is about half of a factorization's time.

    Raises
    ------
    FactorizationError
        ``A_c`` is singular (``channel`` names it).
    """
    A = near_operator(N, d)
    spec = "MMD_AT_PLUS_A"
    if order is not None:
        A, spec = A[order][:, order].tocsc(), "NATURAL"
    try:
        return splu(A, permc_spec=spec, diag_pivot_thresh=0.1, options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise FactorizationError(f"channel {channel}: I - D_c N is singular ({exc})") from exc


# -- The set-up in pieces: pure functions, run in this process or as Dask tasks ---------------------

def channel_solver(N: sp.csr_matrix, d: np.ndarray, dtype, channel: int = 0, order=None) -> PanelSolver:
    """Piece 1, once per distinct channel: ``A_c = I - D_c N`` factored, L and U laid out for panels.

    ``order`` (n,) reuses another channel's fill-reducing order (:attr:`PanelSolver.order`).
    """
    return PanelSolver(factor_near(N, d, channel, order), dtype, order=order)


def solver_order(solver: PanelSolver) -> np.ndarray:
    """(n,) int64 the fill-reducing order of a channel's factors (to factor the other channels without reordering)."""
    return solver.order


def near_columns(solver: PanelSolver, d: np.ndarray, Q_cols: np.ndarray) -> np.ndarray:
    """Piece 2, per channel and column panel: ``Z_c[:, cols] = A_c^{-1} D_c Q[:, cols]``, (n, w) in Q's dtype.

    Each column is solved on its own (:class:`PanelSolver`): any split of the k columns
    gives the same Z. In float32 the panels are ~1e-6 relative, far below the factorization's eps.
    """
    return solver.solve(d[:, None].astype(Q_cols.dtype) * Q_cols)


def row_maxima(Z_cols: np.ndarray) -> np.ndarray:
    """(n,) largest magnitude per row of a column panel (the 16-bit scales are the maxima over panels)."""
    return np.abs(Z_cols).max(axis=1) if Z_cols.shape[1] else np.zeros(Z_cols.shape[0], Z_cols.dtype)


def column_products(Z_cols: np.ndarray, V: np.ndarray, scale=None, slab: int = SLAB_ROWS):
    """Piece 3, per channel and column panel: the stored ``Z_c[:, cols]`` and ``V^T`` times it.

    Parameters
    ----------
    Z_cols : (n, w) float
    V : (n, k) float, the factors' dtype
    scale : (n,) float32, optional
        Whole rows' 16-bit scales (:meth:`QuantizedRows.row_scale`): the panel is stored
        coded and the product taken with the decoded values, which the solve reads.

    Returns
    -------
    codes : (n, w) int16 or None
        None without ``scale`` (``Z_cols`` is stored as it is).
    VtZ : (k, w) float64
        Products of row slabs in the factors' dtype, summed in float64: a float64
        product would be the same ``2 n k w`` flops at half the float32 rate plus
        float64 copies of V and Z; summing per slab keeps float32 rounding at that
        of a ``slab``-long dot product.
    """
    n, w = Z_cols.shape
    codes = None if scale is None else QuantizedRows.encode_with(Z_cols, scale)
    out = np.zeros((V.shape[1], w))
    for a in range(0, n, slab):
        rows = slice(a, min(a + slab, n))
        part = Z_cols[rows] if codes is None else codes[rows].astype(np.float32) * scale[rows, None]
        out += (V[rows].T @ part.astype(V.dtype, copy=False)).astype(np.float64)
    return codes, out


#: Relative residual (max norm) at which a column panel's Neumann sweeps stop in the set-up: Z_c is then
#: within ~``SETUP_TOL / (1 - rho)`` of ``A_c^{-1} D_c Q``, as close as the LU path's float32 panels
#: (~1e-6), and far below the 16-bit storage's rounding (~1.5e-5 of a row's largest entry).
SETUP_TOL = 1e-7


class NeumannColumns:
    """``A_c^{-1} X`` for ``A_c = I - D_c N`` by the Chebyshev-accelerated Neumann series over N
    (:func:`hfrad.solve.neumann.neumann_solve`): the ``solve`` of a channel's solver that
    :func:`~hfrad.solve.nearfield.near_columns` calls, without a sparse LU.

    Each column panel (a Dask task, or ``NEUMANN_COLUMNS`` columns in this process) sweeps N itself (float64,
    every core), so nothing waits for a factorization: on Dask the set-up's critical path is one
    panel's sweeps instead of one channel's LU and one panel's triangular solves, and in this
    process no LU is held (:func:`near_setup_runner`). Where the series does not converge (the bound
    on the spectral radius of ``D_c N`` not below 1, or ``MAX_SWEEPS`` reached) the panel is
    solved by the channel's LU instead (:func:`channel_solver`).

    Parameters
    ----------
    N : (n, n) float64 CSR
        The near field (internal order).
    d : (n,) float64
        The channel's scale ``rho_c / rho_max``.
    dtype : numpy dtype
        Of the returned columns (the factors').
    channel : int
    rho : float
        Upper bound on the spectral radius of ``N`` (:func:`~hfrad.solve.neumann.spectral_bound`;
        it bounds ``D_c N``'s too, ``0 <= D_c <= 1``).
    tol : float
        The sweeps' stopping residual (:data:`SETUP_TOL`).
    """

    def __init__(self, N, d, dtype, channel: int, rho: float, tol: float = SETUP_TOL) -> None:
        self.N, self.d, self.dtype = N, np.asarray(d, np.float64), np.dtype(dtype)
        self.channel, self.rho, self.tol = int(channel), float(rho), float(tol)
        #: sweeps of the last solve (0: it fell back to the LU)
        self.last_sweeps = 0

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``A_c^{-1} X`` for X (n, w); (n, w) in ``dtype``."""
        n, w = X.shape
        post = np.broadcast_to(self.d[:, None], (n, w))
        x, sweeps = neumann_solve(self.N, X, rho=self.rho, post=post, tol=self.tol)
        if x is None:   # no convergence: the exact solve
            self.last_sweeps = 0
            return channel_solver(self.N, self.d, self.dtype, self.channel).solve(X)
        self.last_sweeps = sweeps
        return x.astype(self.dtype)


def neumann_channel(N, d, dtype, channel: int, rho: float, tol: float = SETUP_TOL) -> NeumannColumns:
    """Piece 1 without a factorization: the channel's :class:`NeumannColumns` (nothing computed yet)."""
    return NeumannColumns(N, d, dtype, channel, rho, tol)


class InProcess:
    """Runs the set-up's pieces here, one after the other (the local backend).

    A runner has ``scatter(x)`` (data many pieces read), ``submit(fn, *args)`` (a piece;
    arguments may be what ``scatter``/``submit`` returned), ``gather(xs)`` (results as
    arrays), ``release(x)``, and two choices: ``columns`` (column panel width; None:
    all k at once) and ``share_order`` (factor the first distinct channel, then the
    others in its fill-reducing order: less work; False factors all at once: a
    shorter critical path). :mod:`hfrad.distributed.assembly` has the Dask one.

    Parameters
    ----------
    neumann : bool
        No sparse LUs: each channel's ``A_c^{-1} D_c Q`` by Neumann sweeps over N
        (:class:`NeumannColumns`, N's spectral bound computed once); see :func:`near_setup_runner`.
    """

    columns = None

    def __init__(self, neumann: bool = False) -> None:
        self.neumann = bool(neumann)
        self.share_order = not self.neumann
        # the sweeps' work arrays are n x (columns) float64: panels keep them small at any rank
        self.columns = NEUMANN_COLUMNS if self.neumann else None
        self._rho = None

    def scatter(self, x):
        return x

    def submit(self, fn, *args):
        if self.neumann and fn is channel_solver:
            N, d, dtype, channel = args[:4]
            if self._rho is None:    # one bound serves every channel (0 <= D_c <= 1)
                self._rho = spectral_bound(N)
            return neumann_channel(N, d, dtype, channel, self._rho)
        return fn(*args)

    def gather(self, xs):
        return list(xs)

    def release(self, x) -> None:
        pass


def near_setup_runner(n: int, entries: int) -> InProcess:
    """The in-process runner of the near field's set-up for ``entries`` a row of N: Neumann sweeps, no LUs
    (:class:`NeumannColumns`), above :data:`hfrad.memory.NEAR_LU_MOST_ENTRIES` entries a row or where one
    channel's LU (:func:`hfrad.memory.near_lu_bytes`) would take more than half the memory available;
    SuperLU otherwise (the channels after the first in its order)."""
    from ..memory import available_bytes, near_factored, near_lu_bytes

    factored = near_factored(entries) and near_lu_bytes(n, entries) <= 0.5 * available_bytes()
    return InProcess(neumann=not factored)


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
        (:meth:`quantization_error`) is at most ``QUANTIZE_SHARE`` of the
        achieved error (float64 factors keep float64 ``Z_c``).
    runner : optional
        Where the set-up's pieces run (:class:`InProcess`, the default, or
        :class:`hfrad.distributed.assembly.DaskRunner`); the result is the same.

    Attributes
    ----------
    shape, n_patches, rank, dtype, perm, inv_perm, Q, V, rho_max, reflectance, lowrank, stats, solver
        As for :class:`HFactorization`.
    nbytes : int
        Bytes of the arrays a solve reads: V, ``Z``, N and its copy in the
        factors' dtype, and ``capacitance_inv`` (Q too: the adjoint solve reads it; not
        the transposed copy of N the first solve makes, as many bytes as that copy of N).
    near_entries : int
        The stored entries of N (as SciPy's ``SuperLU.nnz`` counts its factors').
    N : (n, n) float64 CSR, internal order
        The near field, read-only.
    Z : (d, n, k) ``dtype`` or QuantizedRows
        ``A_c^{-1} D_c Q`` for the d :attr:`distinct_channels`.
    distinct_channels : list of int
        The channels with their own ``D_c`` (grey scenes have one).
    capacitance_inv : (3, k, k) ``dtype``
        The inverses ``K_c^{-1}``.
    near_solution_storage : str
        ``"int16 rows"`` or the dtype name of ``Z``.
    last_sweeps : int
        Sweeps of the Neumann series in the last solve (0: SuperLU solved it).

    Raises
    ------
    InputError
        As :class:`HFactorization`; also N not (n, n), ``near_solution`` not
        (d, n, k) for the d distinct channels.
    FactorizationError
        ``I - D_c N`` or a capacitance matrix ``K_c`` is singular.

    Notes
    -----
    Costly figures are methods computed once, as for :class:`HFactorization`, and
    :meth:`quantization_error` (a power iteration for a loaded file's 16-bit ``Z``)
    and :meth:`near_spectral_bound` (a power iteration on ``|N|``).
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
                 scene=None, stats=None, runner=None):
        # what the set-up needs beside the parent's arguments: read by _capacitance_inv, which the
        # parent's constructor calls once the shared state (perm, Q, V, D_c, ...) is in place
        self._setup = (N, near_solution, quantize, runner)
        super().__init__(perm, Q, V, rho_max, reflectance, lowrank, capacitance=capacitance, sigma_max=sigma_max,
                         params=params, scene=scene, stats=stats)

    def _stored_factor_bytes(self, Q: np.ndarray) -> int:
        """:meth:`HFactorization._stored_factor_bytes` and the near field N (values and column indices)
        and one ``Z_c`` in 16 bits (the least it is stored as): the sampled rows' budget counts them."""
        N = self._setup[0] if hasattr(self, "_setup") else self.N     # during the constructor: not set up yet
        nnz = N.nnz if sp.issparse(N) else int(np.count_nonzero(N))
        return super()._stored_factor_bytes(Q) + 12 * nnz + 2 * Q.shape[0] * Q.shape[1]

    def _capacitance_inv(self, stored) -> np.ndarray:
        """The near-field set-up (N, Z per distinct channel), then ``K_c^{-1}`` (3, k, k): stored or computed."""
        N, near_solution, quantize, runner = self._setup
        del self._setup
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
        self._spectral: float | None = None
        self._quantize = quantize
        if runner is None:
            runner = near_setup_runner(self.n_patches, round(self.N.nnz / max(1, self.n_patches)))
        #: how ``Z_c`` was found: "neumann" (sweeps) or "lu" (SuperLU)
        self.near_setup = ("stored" if near_solution is not None
                           else "neumann" if getattr(runner, "neumann", False) else "lu")
        with spare_threads():   # BLAS threads that other processes leave free (hfrad.resources)
            Z, K_inv = self._near_solution(near_solution, stored, quantize, runner)
        self.Z = Z if isinstance(Z, QuantizedRows) else read_only(Z)   # QuantizedRows holds read-only arrays
        return K_inv

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
        return factor_near(self.N, self._D[:, c], c)

    def _near_solution(self, stored_Z, stored_K, quantize: bool | None, runner):
        """``Z`` (distinct channels, n, k; array or QuantizedRows) and ``K_c^{-1}`` (3, k, k): as stored, or computed."""
        distinct = self.distinct_channels
        shape = (len(distinct), self.n_patches, self.rank)
        if stored_Z is not None and stored_K is not None:
            Z = stored_Z if isinstance(stored_Z, QuantizedRows) else np.asarray(stored_Z, self.dtype)
            if Z.shape != shape:
                raise InputError(f"near_solution must have shape {shape} (one (n, k) A_c^-1 D_c Q per "
                                 f"distinct channel {distinct}); got {Z.shape}")
            return Z, super()._capacitance_inv(stored_K)
        if not self.rank:
            return np.empty(shape, self.dtype), np.empty((N_CHANNELS, 0, 0), self.dtype)
        return self._near_setup(quantize, runner)

    def _near_setup(self, quantize: bool | None, runner):
        """The set-up in pieces (:func:`channel_solver`, :func:`near_columns`, :func:`column_products`) on ``runner``.

        Per distinct channel c: factor ``A_c``; solve the column panels of ``D_c Q``; the
        rows' 16-bit scales from the panels' row maxima; whether to store ``Z`` coded
        (:data:`QUANTIZE_SHARE`); then per panel the stored ``Z_c`` columns and
        ``V^T Z_c`` columns; ``K_c = I - V^T Z_c`` is inverted here. The panels are
        independent columns, so any runner and panel width give the same ``Z``, and
        ``K_c`` equal to float32 rounding (the products' blocking).
        """
        distinct, k, n = self.distinct_channels, self.rank, self.n_patches
        width = k if runner.columns is None else max(int(runner.columns), 1)
        panels = [slice(j, min(j + width, k)) for j in range(0, k, width)]
        N = runner.scatter(self.N)
        V = runner.scatter(np.asarray(self.V))
        Qp = [runner.scatter(np.ascontiguousarray(self.Q[:, cols])) for cols in panels]
        d = {c: np.ascontiguousarray(self._D[:, c]) for c in distinct}
        cols, order = {}, None
        for c in distinct:
            solver = runner.submit(channel_solver, N, d[c], self.dtype, c, order)
            if runner.share_order and order is None and len(distinct) > 1:
                order = runner.submit(solver_order, solver)
            for j in range(len(panels)):
                cols[c, j] = runner.submit(near_columns, solver, d[c], Qp[j])
            runner.release(solver)      # the LU lives until its panels are solved (one channel at a time here)
        maxima = runner.gather([runner.submit(row_maxima, cols[c, j]) for c in distinct for j in range(len(panels))])
        scales = [QuantizedRows.row_scale(np.max(maxima[z * len(panels):(z + 1) * len(panels)], axis=0))
                  for z in range(len(distinct))]
        error = self._quantization_bound_of(scales)
        coded = quantize is not False and (
            quantize or (self.dtype == np.float32 and error.max() <= QUANTIZE_SHARE * self.achieved_error))
        parts = runner.gather([runner.submit(column_products, cols[c, j], V, scales[z] if coded else None)
                               for z, c in enumerate(distinct) for j in range(len(panels))])
        if not coded:
            Zs = runner.gather([cols[c, j] for c in distinct for j in range(len(panels))])
        for key in cols:
            runner.release(cols[key])
        Z = (np.empty((len(distinct), n, k), np.int16) if coded else np.empty((len(distinct), n, k), self.dtype))
        K_inv = np.empty((N_CHANNELS, k, k), self.dtype)
        for z, c in enumerate(distinct):
            VtZ = np.empty((k, k))
            for j, sl in enumerate(panels):
                i = z * len(panels) + j
                Z[z, :, sl] = parts[i][0] if coded else Zs[i]
                VtZ[:, sl] = parts[i][1]
            # K from the Z the solve reads: Woodbury then inverts A_c - A_c Z_c V^T exactly
            K_inv[c] = invert_capacitance(np.eye(k) - VtZ, f"channel {c}: I - V^T A_c^-1 D_c Q", self.dtype)
        for c, s in enumerate(self._sources):
            K_inv[c] = K_inv[s]
        if coded:
            self._quantization_error = read_only(error)
            return QuantizedRows(Z, np.stack(scales)), K_inv
        return Z, K_inv

    def _vt_times(self, Zz, slab: int = SLAB_ROWS) -> np.ndarray:
        """(k, k) float64 ``V^T Z`` of a stored (n, k) Z (array or QuantizedRows), as :func:`column_products`."""
        if isinstance(Zz, QuantizedRows):
            return column_products(Zz.decode(), self.V, slab=slab)[1]
        return column_products(np.asarray(Zz), self.V, slab=slab)[1]

    def _quantization_bound(self, coded: QuantizedRows) -> np.ndarray:
        """(3,) bound on ``||A_c (Z_c - coded_c) V^T||_2`` (:meth:`_quantization_bound_of` its scales)."""
        return self._quantization_bound_of([coded.scale[z] for z in range(coded.shape[0])])

    def _quantization_bound_of(self, scales) -> np.ndarray:
        """(3,) ``(1 + ||N||_2) ||dZ_c||_F ||V||_2`` for 16-bit ``Z_c`` with row scales ``scales[z]`` (n,).

        ``||N||_2 <= sqrt(max row sum * max column sum)`` (N >= 0) and ``D_c <= 1``;
        ``||dZ_c||_F`` by :meth:`QuantizedRows.scale_error`; ``||V||_2`` by power
        iteration (from below: 1% margin).
        """
        absN = abs(self.N)
        norm_N = float(np.sqrt(absN.sum(axis=1).max() * absN.sum(axis=0).max())) if self.N.nnz else 0.0
        norm_V = 1.01 * power_sigma_max(self.V, np.eye(self.rank, dtype=self.dtype))
        per_z = [(1 + norm_N) * QuantizedRows.scale_error(sc, self.rank) * norm_V for sc in scales]
        return np.array([per_z[z] for z in self._stored])

    def quantization_error(self) -> np.ndarray:
        """(3,) float, read-only: upper bound on the operator error that 16-bit ``Z_c`` add (0 for float ``Z_c``).

        Known from the set-up when it quantized; otherwise (a loaded file) the
        first call computes it from the stored scales, with a power
        iteration for ``||V||_2`` (O(nk) per step); later calls are free.
        """
        if self._quantization_error is None:
            self._quantization_error = read_only(self._quantization_bound(self.Z) if isinstance(self.Z, QuantizedRows)
                                                 else np.zeros(N_CHANNELS))
        return self._quantization_error

    @property
    def near_entries(self) -> int:
        """The stored entries of N."""
        return int(self.N.nnz)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays a solve reads (see the class's Attributes)."""
        Z = self.Z.codes.nbytes + self.Z.scale.nbytes if isinstance(self.Z, QuantizedRows) else self.Z.nbytes
        near = sum(M.data.nbytes + M.indices.nbytes + M.indptr.nbytes for M in (self.N, self._sweep_N))
        return int(super().nbytes + Z + near)

    @property
    def near_solution_storage(self) -> str:
        """How ``Z_c`` is stored: ``"int16 rows"`` or the factors' dtype name."""
        return "int16 rows" if isinstance(self.Z, QuantizedRows) else self.Z.dtype.name

    def _storage_error(self) -> np.ndarray:
        return self.quantization_error()

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

    def near_spectral_bound(self) -> float:
        """Upper bound on the spectral radius of every ``D_c N`` (that of N).

        The first call runs a power iteration on ``|N|`` (O(nnz(N)) per
        step, :func:`~hfrad.solve.neumann.spectral_bound`); later ones are free.
        """
        if self._spectral is None:
            self._spectral = spectral_bound(self.N)
        return self._spectral

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
            x, sweeps = neumann_solve(NT, b, rho=self.near_spectral_bound(), pre=scale, reach=(N.indptr, N.indices))
        else:
            x, sweeps = neumann_solve(N, b, rho=self.near_spectral_bound(), post=scale, reach=(NT.indptr, NT.indices))
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
                f"near_entries={self.near_entries}, relative_error={self.relative_error:.3g}, dtype={self.dtype.name}, "
                f"near_solution={self.near_solution_storage!r})")
