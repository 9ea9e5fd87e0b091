"""The factorization object: solve (I - R_c F) B_c = E_c in O(nk) by Sherman-Morrison-Woodbury.

Colour without three factorizations (docs/method.md, section 6): G = diag(rho_max) F
is factored once, G ~= Q V^T, and channel c uses Q_c = D_c Q with
D_c = diag(rho_c / rho_max), so ``R_c F ~= Q_c V^T`` with the same error bound.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import scipy.linalg as sla

from ..errors import AccuracyWarning, FactorizationError, InputError
from ..lowrank.factors import LowRank
from ..resources import solve_threads
from ..validation import as_real_array, check_exitance, check_finite, check_reflectance, check_trans
from .bounds import ErrorEstimate, ResidualEstimate, estimate_errors, power_sigma_max_scaled, residual_estimate
from . import thin
from .readonly import read_only
from .samples import SolutionError
from .stats import FAILURE_PROBABILITY, PassStatistics

N_CHANNELS = 3
_RCOND_MIN = 1e-12   # below this the k x k system has no meaningful solution


def _channel_scale(reflectance: np.ndarray, rho_max: np.ndarray) -> np.ndarray:
    """(n, 3) D_c = rho_c / rho_max, 0 where rho_max = 0."""
    out = np.zeros_like(reflectance, dtype=np.float64)
    np.divide(reflectance, rho_max[:, None], out=out, where=rho_max[:, None] > 0)
    return out


def capacitance(Q: np.ndarray, V: np.ndarray, D: np.ndarray, dtype=None) -> np.ndarray:
    """Per-channel ``M_c = I_k - V^T D_c Q``, the k x k matrices of the Woodbury solve (eq. 4).

    Parameters
    ----------
    Q, V : (n, k) float, internal patch order
    D : (n, C) float
        Channel scales ``rho_c / rho_max`` in internal order.
    dtype : numpy dtype, optional
        Precision of the n x k x k products (default: the factors' dtype;
        ``benchmarks/bench_solve.py`` compares float32 with float64 here).

    Returns
    -------
    M : (C, k, k) float64

    Notes
    -----
    ``V^T D_c Q = V^T Q - V_S^T (1 - D_c)_S Q_S`` with S the patches where
    ``D_c != 1``: grey patches (``rho_c = rho_max``) are shared by every
    channel, so this costs ``n k^2 + sum_c |S_c| k^2`` multiply-adds instead
    of ``C n k^2`` where few patches are coloured (it is used when cheaper).
    """
    dt = np.dtype(Q.dtype if dtype is None else dtype)
    Qd, Vd = Q.astype(dt, copy=False), V.astype(dt, copy=False)
    n, k = Q.shape
    eye = np.eye(k)
    coloured = [np.flatnonzero(D[:, c] != 1.0) for c in range(D.shape[1])]
    M = np.empty((D.shape[1], k, k))
    if sum(map(len, coloured)) < (D.shape[1] - 1) * n:
        base = eye - Vd.T @ Qd
        for c, rows in enumerate(coloured):
            M[c] = base + Vd[rows].T @ ((1.0 - D[rows, c:c + 1]).astype(dt) * Qd[rows])
    else:
        for c in range(D.shape[1]):
            M[c] = eye - Vd.T @ (D[:, c:c + 1].astype(dt) * Qd)
    return M


def invert_capacitance(M: np.ndarray, what: str, dtype=np.float64) -> np.ndarray:
    """The inverse of one k x k capacitance matrix, after a singularity check.

    LU-factored (LAPACK getrf), checked and inverted (getri) in float64; the
    inverse is returned C-contiguous in ``dtype`` (the factors' dtype). An
    explicit inverse, not the LU: applying it is one matrix-vector product
    that streams its k^2 words in parallel, where two triangular solves of a
    single right-hand side are sequential, row after row
    (``benchmarks/bench_solve.py --relight`` compares them). With V's columns
    orthonormal (as the factorizers return them), ``||V^T D_c Q||_2 <= s =
    sigma_max(Q_c V^T)``, and for ``s < 1`` the condition number of ``M_c``
    is at most ``(1 + s) / (1 - s)``: the explicit inverse and its float32
    rounding lose accuracy only where ``s`` approaches 1 (the check below).

    Raises
    ------
    FactorizationError
        ``M`` is singular or nearly so (``what`` names it and its channel):
        R F has an eigenvalue near 1, which no physical scene has.
    """
    k = M.shape[0]
    if k == 0:
        return np.zeros((0, 0), dtype)
    lu, piv, info = sla.lapack.dgetrf(np.asarray(M, np.float64))
    anorm = float(np.abs(M).sum(axis=0).max())
    rcond = sla.lapack.dgecon(lu, anorm, norm="1")[0] if info == 0 else 0.0
    # 1 / (||M^-1|| max(||M||, 1)): a tiny M (an eigenvalue of Q_c V^T at 1) is singular too
    rcond *= anorm / max(anorm, 1.0)
    if info != 0 or not rcond > _RCOND_MIN:
        raise FactorizationError(f"{what} ({k} x {k}) is singular (reciprocal condition {rcond:.2e}); "
                                 "R F has an eigenvalue near 1 (reflectance too close to 1?)")
    # the blocked getri needs its workspace size: with the minimum (k) LAPACK runs the unblocked algorithm
    inv, info = sla.lapack.dgetri(lu, piv, lwork=max(int(sla.lapack.dgetri_lwork(k)[0]), k))
    return np.ascontiguousarray(inv, dtype)


def capacitance_applied(factor: np.ndarray, inverse: np.ndarray, X: np.ndarray, transpose: bool = False):
    """(k, C, m) ``M_c^{-1} factor^T X_c`` (``M_c^{-T}`` with ``transpose``) for every channel c.

    The first half of every Woodbury term: one streaming product with all ``C m``
    right-hand sides stacked (:mod:`hfrad.solve.thin`, reading ``factor`` once),
    then C products with the k x k inverses, in the factor's dtype.
    """
    n, C, m = X.shape
    k = factor.shape[1]
    T = thin.tmatmul(factor, X.reshape(n, C * m)).reshape(k, C, m)
    S = np.empty((k, C, m), factor.dtype)
    for c in range(C):
        S[:, c, :] = (inverse[c].T if transpose else inverse[c]) @ T[:, c, :]
    return S


def low_rank_correction(Q: np.ndarray, V: np.ndarray, D: np.ndarray, inverse: np.ndarray, X: np.ndarray,
                        adjoint: bool) -> np.ndarray:
    """The Woodbury term for every channel and right-hand side at once, reading Q and V once each.

    Forward: ``W_c = D_c Q M_c^{-1} V^T X_c``; adjoint:
    ``W_c = V M_c^{-T} Q^T D_c X_c``, with ``inverse[c]`` = ``M_c^{-1}``
    (:func:`invert_capacitance`). The plain solve is ``X + W``; the near-field
    split applies its sparse inverse to W.

    Parameters
    ----------
    Q, V : (n, k) float, internal order
    D : (n, C) float
    inverse : (C, k, k) float, the factors' dtype
    X : (n, C, m) float64, internal order

    Returns
    -------
    W : (n, C, m) float64

    Notes
    -----
    Two products with all ``C m`` right-hand sides stacked (k x n x Cm, then
    n x k x Cm, :mod:`hfrad.solve.thin`) and C products with the k x k
    inverses, all in the factors' dtype: the solve streams Q and V once and the
    inverses once (2nk + 3k^2 words, its memory-bandwidth limit; rows of V
    whose patches do not emit are not read).
    """
    n, C, m = X.shape
    k = Q.shape[1]
    if k == 0:
        return np.zeros_like(X, dtype=np.float64)
    first, second = (Q, V) if adjoint else (V, Q)
    if adjoint:
        X = D[:, :, None] * X
    S = capacitance_applied(first, inverse, X, transpose=adjoint)
    W = thin.matmul(second, S.reshape(k, C * m)).reshape(n, C, m)
    return W.astype(np.float64) if adjoint else D[:, :, None] * W


def _checked_arrays(perm, Q, V, rho_max, reflectance):
    """The constructor's arrays as int64 / float arrays of consistent shapes, or InputError naming the first bad one."""
    perm = np.asarray(perm)
    if perm.ndim != 1 or not (perm.dtype.kind in "iu" or perm.size == 0):
        raise InputError(f"perm must be a 1-D integer array (a permutation of the n patches); "
                         f"got shape {perm.shape}, dtype {perm.dtype}")
    perm = perm.astype(np.int64, copy=False)
    n = perm.size
    if n and (perm.min() < 0 or perm.max() >= n or np.bincount(perm, minlength=n).max() != 1):
        raise InputError(f"perm must be a permutation of 0..{n - 1} (each patch once)")
    Q = np.asarray(Q)
    if Q.ndim != 2 or Q.shape[0] != n or Q.dtype.kind != "f":
        raise InputError(f"Q must be a float array of shape ({n}, k) (n = len(perm)); "
                         f"got shape {Q.shape}, dtype {Q.dtype}")
    V = np.asarray(V)
    if V.shape != Q.shape or V.dtype.kind != "f":
        raise InputError(f"V must be a float array of Q's shape {Q.shape}; got shape {V.shape}, dtype {V.dtype}")
    rho_max = np.asarray(rho_max, dtype=np.float64)
    if rho_max.size != n:
        raise InputError(f"rho_max must have one entry per patch ({n}); got shape {rho_max.shape}")
    reflectance = np.asarray(reflectance, dtype=np.float64)
    if reflectance.shape != (n, N_CHANNELS):
        raise InputError(f"reflectance must have shape ({n}, {N_CHANNELS}); got {reflectance.shape}")
    return perm, Q, V.astype(Q.dtype, copy=False), rho_max.reshape(n), reflectance


class HFactorization:
    """A factored radiosity system: solve ``(I - R_c F) B_c = E_c`` for any E in O(nk).

    ``B~_c = E_c + D_c Q M_c^{-1} (V^T E_c)``, ``M_c = I_k - V^T D_c Q``
    (eq. 4 with ``Q_c = D_c Q``), computed in the internal (Z-order) patch
    order and returned in the user's.

    Parameters
    ----------
    perm : (n,) int
        Internal order: internal index t holds user patch ``perm[t]``.
    Q, V : (n, k) float, internal order
        ``G_int ~= Q V^T`` with ``G = diag(rho_max) F`` and
        ``G_int = G[perm][:, perm]``.
    rho_max : (n,) float, user order
        The reflectance bound the factorization was built for.
    reflectance : (n, 3) float in [0, 1), user order
        Must satisfy ``reflectance <= rho_max`` per patch.
    lowrank : LowRank
        Metadata of the factorization (eps, achieved error, norm, relative).
    capacitance : (3, k, k) float, optional
        The inverses ``M_c^{-1}`` (as stored in an .hfr file); computed from
        Q, V and the reflectance when not given.
    sigma_max : (3,) float, optional
        Cached power-iteration estimates of sigma_max(Q_c V^T).
    stats : PassStatistics, optional
        Row/column sums of F and the probe sketch recorded during the pass
        (internal order): what the guaranteed error bound is computed from.
    params : dict, optional
        Parameters of the run (block size, order, method...), for the record.

    Attributes
    ----------
    shape : (int, int)
        ``(n, n)``, the shape of ``I - R_c F``.
    n_patches : int
        n.
    rank : int
        k, the columns of Q and V.
    nbytes : int
        Bytes of the arrays a solve reads (Q, V, ``capacitance_inv``).
    dtype : numpy.dtype
        The factors' precision (float32 or float64).
    perm, inv_perm : (n,) int64
        Internal index t holds user patch ``perm[t]``; ``inv_perm`` is its inverse.
    Q, V : (n, k) ``dtype``, internal order
        The factors, ``G_int ~= Q V^T``.
    rho_max : (n,) float64, user order
    reflectance : (n, 3) float64, user order
    capacitance_inv : (3, k, k) ``dtype``
        The inverses ``M_c^{-1}`` of the Woodbury solve.
    lowrank : LowRank
        The factorization's record: ``eps``, ``achieved_error``, ``relative_error``.
    eps, achieved_error, relative_error : float
        As in ``lowrank``.
    stats : PassStatistics or None
        The pass statistics (row sums, probe sketch, sampled rows of F).
    areas : (n,) float or None
        Patch areas, m^2 (user order), weighting the error norms.
    solver : str
        The method ("woodbury"; the near-field split's subclass says its own).
    params, timings : dict
        The run's parameters and timings, for the record.
    scene : Scene or None
        The scene the factorization was built from (None when built from a matrix).

    Raises
    ------
    InputError
        ``perm`` is not a permutation of ``0..n-1``, Q and V are not both
        (n, k), ``rho_max`` does not have n entries, ``reflectance`` is not
        (n, 3), or ``capacitance`` is not (3, k, k).
    FactorizationError
        A capacitance matrix ``M_c`` is singular (R F has an eigenvalue near 1).

    Notes
    -----
    The costly figures are methods, computed on the first call and kept:
    :meth:`sigma_max` (a power iteration, O(nk) per step, unless stored),
    :meth:`error_estimate` with :meth:`error_bound` and :meth:`eq5_bound`
    (O(n k p) for the p probes, and ``sigma_max``).
    Immutable arrays: ``perm``, ``inv_perm``, ``Q``, ``V``, ``rho_max``,
    ``reflectance``, ``capacitance_inv``, ``lowrank.Q``/``lowrank.V`` and the
    pass statistics' arrays are read-only views (writing raises
    ``ValueError``; no data is copied): they were computed together, and
    :meth:`with_reflectance` is the way to a factorization with other
    reflectances. Arrays returned by :meth:`solve` are new and writable.
    Memory: Q and V (2 n k) and the three k x k inverses ``M_c^{-1}``
    (3 k^2, ``capacitance_inv``), all in the factors' dtype; nothing else
    n x k is kept. A solve of all three channels (and
    m emissions) reads Q and V once each: O(nk) per right-hand side.
    Set-up: ``n k^2`` multiply-adds (plus ``k^2`` per coloured patch and
    channel, :func:`capacitance`) and three k x k inversions. Aguerre & Fernández
    2016, eq. 2-5.
    """

    solver = "woodbury"

    def __init__(self, perm, Q, V, rho_max, reflectance, lowrank: LowRank, *, capacitance=None,
                 sigma_max=None, params: dict | None = None, scene=None, stats: PassStatistics | None = None):
        perm, Q, V, rho_max, reflectance = _checked_arrays(perm, Q, V, rho_max, reflectance)
        n = perm.size
        inv_perm = np.empty(n, np.int64)
        inv_perm[perm] = np.arange(n)
        self.perm, self.inv_perm = read_only(perm), read_only(inv_perm)
        self.Q, self.V = read_only(Q), read_only(V)
        self.rho_max, self.reflectance = read_only(rho_max), read_only(reflectance)
        # the LowRank's Q and V are the same data: read-only views there too (its info dict is shared)
        self.lowrank = (dataclasses.replace(lowrank, Q=read_only(lowrank.Q), V=read_only(lowrank.V))
                        if dataclasses.is_dataclass(lowrank) else lowrank)
        self.params = dict(params or {})
        self.scene = scene
        self.timings: dict = {}
        self._D = read_only(_channel_scale(self.reflectance, self.rho_max)[self.perm])
        self._sigma = None if sigma_max is None else read_only(np.asarray(sigma_max, np.float64))
        self._estimate: ErrorEstimate | None = None
        # the exact sampled rows are kept within a tenth of the factors' bytes (SAMPLE_SHARE)
        self.stats = None if stats is None else stats.frozen(self._stored_factor_bytes(Q))
        # last: the near-field subclass's override runs its set-up here, on the state above
        self.capacitance_inv = read_only(self._capacitance_inv(capacitance))

    def _stored_factor_bytes(self, Q: np.ndarray) -> int:
        """Bytes of what the solve keeps: Q, V and the k x k capacitances (the sampled rows' budget)."""
        return (2 * Q.shape[0] * Q.shape[1] + 3 * Q.shape[1] ** 2) * Q.itemsize

    def _capacitance_inv(self, stored) -> np.ndarray:
        """(3, k, k) ``M_c^{-1}``, ``M_c = I_k - V^T D_c Q``: ``stored`` checked, or computed."""
        k = self.rank
        if stored is not None:
            inv = np.ascontiguousarray(stored, self.dtype)
            if inv.shape != (N_CHANNELS, k, k):
                raise InputError(f"capacitance must have shape ({N_CHANNELS}, {k}, {k}); got {inv.shape}")
            return inv
        M = capacitance(self.Q, self.V, self._D)
        return np.stack([invert_capacitance(M[c], f"channel {c}: I - V^T Q_c", self.dtype)
                         for c in range(N_CHANNELS)])

    # -- sizes and accuracy ------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """``(n, n)``: the shape of the system ``I - R_c F`` this object solves (as SciPy's ``SuperLU.shape``)."""
        return (self.n_patches, self.n_patches)

    @property
    def n_patches(self) -> int:
        """n, the number of patches."""
        return int(self.perm.size)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays a solve reads: Q, V and the inverses ``capacitance_inv`` (``2 n k + 3 k^2`` words)."""
        return int(self.Q.nbytes + self.V.nbytes + self.capacitance_inv.nbytes)

    @property
    def rank(self) -> int:
        """k, the rank of the factorization."""
        return int(self.Q.shape[1])

    @property
    def dtype(self) -> np.dtype:
        """The factors' dtype (float32 or float64): the precision of Q, V and the solve's products."""
        return self.Q.dtype

    @property
    def eps(self) -> float:
        """The tolerance the factorization was asked for (``lowrank.eps``)."""
        return float(self.lowrank.eps)

    @property
    def achieved_error(self) -> float:
        """``||G - Q V^T||_F`` (absolute) as achieved; bounds ``||R_c F - Q_c V^T||_2``."""
        return float(self.lowrank.achieved_error)

    @property
    def relative_error(self) -> float:
        """``||G - Q V^T||_F / ||G||_F``."""
        return self.lowrank.relative_error

    def error_estimate(self) -> ErrorEstimate:
        """Accuracy figures of this factorization, per colour channel (computed on the first call, then cached).

        Returns
        -------
        ErrorEstimate
            ``bound``: an upper bound on the relative radiosity error of any
            solve, in the area-weighted norm, failing with probability
            ``failure_probability`` (1e-6); ``eq5_bound``: the paper's eq. 5,
            a secondary figure; and the quantities they are made of
            (docs/method.md, section 7).

        Warns
        -----
        AccuracyWarning
            Where a channel has no finite bound (``||R_c F||`` may reach 1, or
            the factorization error is too large).

        Notes
        -----
        The first call costs O(n k p) for the p probes and, unless
        :meth:`sigma_max` is known (stored in an .hfr file or called before), a
        power iteration on the factors for eq. 5 (O(nk) per step, a few
        hundred steps at most); later calls return the same object (the
        factorization is immutable).
        """
        if self._estimate is None:
            error = self.achieved_error + float(np.max(self._storage_error()))
            if self.stats is None:
                est = estimate_errors(error, self.sigma_max())
            else:
                est = estimate_errors(error, self.sigma_max(), operator_error=self._operator_error(),
                                      contraction=self.stats.contraction(self.reflectance[self.perm]),
                                      norm=self.stats.norm, failure_probability=FAILURE_PROBABILITY)
            bad = ~np.isfinite(est.bound)
            if bad.any():
                why = ("sigma_max + error >= 1, eq. 5 gives no bound" if est.kind == "eq5" else
                       f"contraction bound {np.round(est.contraction, 4).tolist()} and operator error "
                       f"{np.round(est.operator_error, 4).tolist()} give no bound")
                warnings.warn(f"no error bound for channels {np.flatnonzero(bad).tolist()}: {why}; "
                              "fac.solve(E, return_error=True) gives each solve's figure", AccuracyWarning, stacklevel=2)
            self._estimate = est
        return self._estimate

    def _storage_error(self) -> np.ndarray:
        """(3,) bound on what the stored solve matrices add to the operator error (none here)."""
        return np.zeros(N_CHANNELS)

    def _operator_error(self) -> np.ndarray:
        """(3,) probed ``||R_c F - Q_c V^T||`` of the operator this solve inverts (:meth:`PassStatistics.operator_error`)."""
        return self.stats.operator_error(self.Q, self.V, self._D)

    def _sigma_estimates(self) -> np.ndarray:
        """(3,) power-iteration estimates of sigma_max(Q_c V^T), for eq. 5."""
        return power_sigma_max_scaled(self.Q, self.V, self._D)

    def sigma_max(self) -> np.ndarray:
        """(3,) float, read-only: sigma_max(Q_c V^T) per channel (the near-field split: of ``D_c (N + Q V^T)``).

        The first call runs a power iteration per distinct channel, O(nk)
        per step (plus O(nnz(N)) with the near field), a few hundred steps at
        most, unless the value was given (an .hfr file stores it); later
        calls return the same array at no cost.
        """
        if self._sigma is None:
            self._sigma = read_only(self._sigma_estimates())
        return self._sigma

    def error_bound(self) -> np.ndarray:
        """(3,) float, read-only: the relative radiosity error bound per channel (``error_estimate().bound``).

        The first call computes :meth:`error_estimate` (O(n k p) for the
        probes and, unless :meth:`sigma_max` is known, its power iteration,
        O(nk) per step); later calls are free.
        """
        return self.error_estimate().bound

    def eq5_bound(self) -> np.ndarray:
        """(3,) float, read-only: the paper's eq. 5 figure per channel (``error_estimate().eq5_bound``).

        Costs as :meth:`error_bound` on the first call (the power
        iteration of :meth:`sigma_max`, O(nk) per step); later calls are free.
        """
        return self.error_estimate().eq5_bound

    # -- solving -------------------------------------------------------------
    def _validate(self, exitance, adjoint: bool) -> np.ndarray:
        E = as_real_array(exitance, "exitance")  # complex, bool, strings, objects: refused, not cast
        n = self.n_patches
        if E.ndim not in (1, 2, 3) or E.shape[0] != n or (E.ndim >= 2 and E.shape[1] != N_CHANNELS):
            raise InputError(f"exitance must have shape ({n},), ({n}, 3) or ({n}, 3, m) "
                             f"(patches in the scene's order); got {E.shape}")
        # finite, >= 0 unless adjoint, and at most MAX_EXITANCE (float32 radiosity would overflow);
        # the first index named is the patch
        return check_exitance(E, "exitance", signed=adjoint)

    def solve(self, exitance, trans: str = "N", *, transpose: bool | None = None, return_error: bool = False):
        """Radiosity ``B_c = (I - R_c F)^{-1} E_c`` for every channel (eq. 4).

        Parameters
        ----------
        exitance : (n,), (n, 3) or (n, 3, m) float >= 0, W/m^2, user patch order
            (n,) is a grey emission (the same for the three channels); (n, 3, m)
            is a batch of m emissions, solved together as matrix products.
        trans : {"N", "T"}
            "T" solves the adjoint ``(I - R_c F)^T x = e`` instead (inverse
            design), as in :func:`scipy.linalg.lu_solve`:
            ``x = e + V M_c^{-T} (Q^T D_c e)``, the same factors.
            Negative entries are allowed then.
        transpose : bool, optional
            Deprecated spelling of ``trans="T"``.
        return_error : bool
            Also return the error figure of this solution (:meth:`solution_error`).

        Returns
        -------
        radiosity : (n, 3) or (n, 3, m) float, W/m^2, user patch order
        error : SolutionError
            Only with ``return_error``: ``error.bound`` (3,) or (3, m) is the figure for
            ``||B~ - B||_A / ||B - E||_A``, the error relative to the reflected light.

        Raises
        ------
        InputError (a ValueError)
            Wrong shape (expected and got are named), NaN/inf, negative
            exitance, or an unknown ``trans``.

        Notes
        -----
        O(n k) per right-hand side; Q and V are read once for all channels
        and emissions together (:func:`low_rank_correction`). The error figure
        adds O(n m) for m stored rows (m <= k / 5 by the storage rule).
        """
        if transpose is not None:
            warnings.warn("solve(E, transpose=True) is deprecated; use solve(E, trans='T')",
                          DeprecationWarning, stacklevel=2)
            trans = "T" if transpose else "N"
        adjoint = check_trans(trans)
        E = self._validate(exitance, adjoint)
        if E.ndim == 1:
            E = np.repeat(E[:, None], N_CHANNELS, axis=1)
        batched = E.ndim == 3
        E3 = E if batched else E[:, :, None]
        with solve_threads():     # the cores other processes leave free (threads that compete spin-wait)
            out = self._solve(E3, adjoint)
            if not return_error:
                return out if batched else out[:, :, 0]
            error = self._solution_error(E3, out, adjoint, batched)
        return (out if batched else out[:, :, 0]), error

    def solution_error(self, exitance, radiosity, trans: str = "N") -> SolutionError:
        """The error figure of a solution of this factorization, from exact rows of F kept from the pass.

        ``||B~ - B|| <= ||r|| + (1 + gain) ||R F r||`` with ``r = E - (I - R F) B~``,
        both norms estimated from exact sampled rows of F and ``F R F`` (all rows on
        small scenes: then a bound); relative to the reflected light ``||B - E||``, in
        the area norm (docs/method.md, section 7b). No pass over F: O(n m) for m rows.

        Parameters
        ----------
        exitance : (n,), (n, 3) or (n, 3, m) float, W/m^2, user patch order
        radiosity : the same shape, W/m^2: ``fac.solve(exitance, trans)``
        trans : {"N", "T"}
            "T": ``radiosity`` solves the adjoint system; the figure is then in the dual
            (``1 / A``-weighted) norm.

        Returns
        -------
        SolutionError
            ``bound`` (3,) or (3, m): relative to the reflected light; ``kind``
            "exact-rows" (a bound), "sampled" (with ``failure_probability``),
            "sampled-estimate" (``trans="T"``: none stated; see :class:`SolutionError`),
            or "unavailable" (a file written without sampled rows: inf).
        """
        adjoint = check_trans(trans)
        E = self._validate(exitance, adjoint)
        if E.ndim == 1:
            E = np.repeat(E[:, None], N_CHANNELS, axis=1)
        B = check_finite(radiosity, "radiosity")
        if B.shape != E.shape:
            raise InputError(f"radiosity must have the exitance's shape {E.shape}; got {B.shape}")
        batched = E.ndim == 3
        return self._solution_error(E if batched else E[:, :, None], B if batched else B[:, :, None],
                                    adjoint, batched)

    def _solution_error(self, E: np.ndarray, B: np.ndarray, adjoint: bool, batched: bool) -> SolutionError:
        """The figure of (n, 3, m) solutions in the user's order (the body of :meth:`solution_error`)."""
        samples = None if self.stats is None else self.stats.samples
        if samples is None:
            shape = (N_CHANNELS, E.shape[2]) if batched else (N_CHANNELS,)
            inf = np.full(shape, np.inf)
            return SolutionError(bound=inf, absolute=inf, reflected=inf, kind="unavailable",
                                 failure_probability=None, rows=0)
        rho = np.asarray(self.reflectance, np.float64)[self.perm]
        err = samples.figure(self._to_internal(E), self._to_internal(B), rho,
                             self.stats.reflection_gain(rho), adjoint=adjoint)
        if batched:
            return err
        return dataclasses.replace(err, bound=err.bound[:, 0], absolute=err.absolute[:, 0],
                                   reflected=err.reflected[:, 0])

    def _solve(self, E: np.ndarray, adjoint: bool) -> np.ndarray:
        """The solve of validated (n, 3, m) exitance in the user's order (the body of :meth:`solve`)."""
        Ei = self._to_internal(E)                                         # (n, 3, m)
        B = Ei + low_rank_correction(self.Q, self.V, self._D, self.capacitance_inv, Ei, adjoint)   # eq. (4)
        return self._to_user(B)

    # np.take gathers whole rows (one copy of 3 m contiguous values per patch); fancy
    # indexing of an (n, 3, m) array goes through numpy's general indexing machinery
    def _to_internal(self, X: np.ndarray) -> np.ndarray:
        """Rows of X (user patch order) in the internal order."""
        return np.take(X, self.perm, axis=0)

    def _to_user(self, X: np.ndarray) -> np.ndarray:
        """Rows of X (internal order) in the user's patch order."""
        return np.take(X, self.inv_perm, axis=0)

    def as_linear_operator(self, channel: int):
        """``(I - R_c F)^{-1}`` of one channel as a :class:`scipy.sparse.linalg.LinearOperator`.

        ``matvec`` is the O(nk) Woodbury solve, ``rmatvec`` the adjoint one;
        vectors are in the user's patch order. Use it as a preconditioner
        ``M`` of an iterative solver of the exact system (e.g.
        ``scipy.sparse.linalg.gmres(I - R_c F, e, M=fac.as_linear_operator(c))``).

        Parameters
        ----------
        channel : int in {0, 1, 2}
            R, G or B.
        """
        from scipy.sparse.linalg import LinearOperator

        if channel not in range(N_CHANNELS):
            raise InputError(f"channel must be 0, 1 or 2 (R, G, B); got {channel!r}")
        n = self.n_patches

        def apply(x, adjoint: bool):
            x = np.asarray(x, dtype=np.float64).reshape(n, -1)
            E = np.zeros((n, N_CHANNELS, x.shape[1]))
            E[:, channel] = x                      # the other channels stay zero: their solves cost O(nk) only
            return self._solve(E, adjoint)[:, channel]

        return LinearOperator((n, n), matvec=lambda x: apply(x, False), rmatvec=lambda x: apply(x, True),
                              matmat=lambda X: apply(X, False), rmatmat=lambda X: apply(X, True),
                              dtype=np.float64)

    def residual(self, exitance, radiosity, *, form_factors=None, progress=None,
                 processes: int | None = 1) -> ResidualEstimate:
        """The guaranteed figure of one solution: its residual with the exact F, and the error bound it gives.

        ``r = E - (I - R_c F) B~`` and ``||B~ - B|| <= ||r|| / (1 - ||R_c F||)``
        (docs/method.md, section 7), in the area-weighted norm when the patch
        areas are known. Uses this factorization's reflectance (which may
        differ from its scene's after :meth:`with_reflectance`).

        Parameters
        ----------
        exitance, radiosity : (n, 3) float, W/m^2, user patch order
        form_factors : (n, n) float, optional
            The exact F (user order). Without it F is streamed again from the
            factorization's scene (every visibility ray: slower than the precompute's
            form factors, which spend a share of eps on fewer rays for weak pairs).
        progress : callable (done, total), optional
        processes : int or None
            Form-factor worker processes when F is streamed (as in
            :func:`hfrad.factorize`: None = one per core for large scenes; a
            script then needs an ``if __name__ == "__main__":`` guard).

        Returns
        -------
        ResidualEstimate
            ``residual`` (relative, per channel) and ``bound`` (guaranteed
            relative radiosity error of ``radiosity``, per channel).
        """
        E = self._validate(exitance, False)
        B = check_finite(radiosity, "radiosity")
        if E.shape != (self.n_patches, N_CHANNELS) or B.shape != E.shape:
            raise InputError(f"exitance and radiosity must both have shape ({self.n_patches}, 3); "
                             f"got {E.shape} and {B.shape}")
        areas = self.areas
        if form_factors is not None:
            F = check_finite(form_factors, "form_factors")
            if F.shape != (self.n_patches, self.n_patches):
                raise InputError(f"form_factors must have shape ({self.n_patches}, {self.n_patches}); got {F.shape}")
            return residual_estimate([(0, self.n_patches, F)], self.reflectance, E, B, areas=areas)
        if self.scene is None:
            raise InputError("this factorization has no scene to recompute F from; pass form_factors=F")
        from ..formfactors.blocks import iter_column_blocks

        samples = self.params.get("samples")
        kwargs = {} if samples is None else {"samples": samples}
        blocks = iter_column_blocks(self.scene, order=self.perm, progress=progress, processes=processes,
                                    **kwargs)
        return residual_estimate(blocks, self.reflectance, E, B, perm=self.perm, areas=areas)

    @property
    def areas(self) -> np.ndarray | None:
        """(n,) patch areas (m^2, user order) weighting the error norm, or None (plain 2-norm)."""
        if self.scene is not None:
            return np.asarray(self.scene.areas)
        if self.stats is not None and self.stats.weights is not None:
            return self.stats.weights[self.inv_perm]
        return None

    def save(self, path) -> "pathlib.Path":  # noqa: F821 - resolved lazily
        """Write this factorization (with its scene's patches) to an ``.hfr`` file, atomically."""
        from .hfr import save_hfr

        return save_hfr(self, path)

    def _checked_reflectance(self, reflectance) -> np.ndarray:
        """(n, 3) float64 reflectance, validated and <= rho_max (InputError naming the patch)."""
        rho = check_reflectance(reflectance, self.n_patches)
        over = rho.max(axis=1) > self.rho_max * (1 + 1e-12)
        if over.any():
            i = int(np.flatnonzero(over)[0])
            raise InputError(f"patch {i} reflectance {rho[i].tolist()} exceeds rho_max "
                             f"{self.rho_max[i]:.6g} of this factorization; refactorize with the "
                             "new reflectance (factorize again)")
        return rho

    def with_reflectance(self, reflectance) -> "HFactorization":
        """The same factorization with new reflectances, without refactoring.

        Allowed when ``reflectance <= rho_max`` everywhere (only the k x k
        matrices ``M_c`` and their inverses are recomputed: O(n k^2 + k^3)).

        Raises
        ------
        InputError (a ValueError)
            Wrong shape, values outside [0, 1), or a patch whose reflectance
            exceeds the rho_max the factorization was built for (a new
            factorization is needed then).
        """
        rho = self._checked_reflectance(reflectance)
        return HFactorization(self.perm, self.Q, self.V, self.rho_max, rho, self.lowrank,
                              params=self.params, scene=self.scene, stats=self.stats)

    def __repr__(self) -> str:
        return (f"HFactorization(n_patches={self.n_patches}, rank={self.rank}, "
                f"relative_error={self.relative_error:.3g}, dtype={self.dtype.name})")
