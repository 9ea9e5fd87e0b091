"""The factorization object: solve (I - R_c F) B_c = E_c in O(nk) by Sherman-Morrison-Woodbury.

Colour without three factorizations (docs/method.md, section 6): G = diag(rho_max) F
is factored once, G ~= Q V^T, and channel c uses Q_c = D_c Q with
D_c = diag(rho_c / rho_max), so ``R_c F ~= Q_c V^T`` with the same error bound.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg as sla

from ..errors import AccuracyWarning, FactorizationError, InputError
from ..factorize.lowrank import LowRank
from ..validation import check_finite, check_reflectance, check_trans
from .bounds import ErrorEstimate, ResidualEstimate, estimate_errors, power_sigma_max, residual_estimate
from .stats import FAILURE_PROBABILITY, PassStatistics

N_CHANNELS = 3
_RCOND_MIN = 1e-12   # below this the k x k system has no meaningful solution


def _channel_scale(reflectance: np.ndarray, rho_max: np.ndarray) -> np.ndarray:
    """(n, 3) D_c = rho_c / rho_max, 0 where rho_max = 0."""
    out = np.zeros_like(reflectance, dtype=np.float64)
    np.divide(reflectance, rho_max[:, None], out=out, where=rho_max[:, None] > 0)
    return out


def woodbury_factors(Q: np.ndarray, V: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Per-channel ``Y_c = -Q_c (I_k - V^T Q_c)^{-1}``, ``Q_c = D_c Q``  (eq. 4).

    Parameters
    ----------
    Q, V : (n, k) float, internal patch order
    D : (n, 3) float
        Channel scales ``rho_c / rho_max`` in internal order.

    Returns
    -------
    Y : (3, n, k) array in the dtype of Q

    Raises
    ------
    FactorizationError
        ``I - V^T Q_c`` is singular (RF has an eigenvalue at 1: not a physical scene).
    """
    n, k = Q.shape
    Y = np.empty((D.shape[1], n, k), Q.dtype)
    V64 = V.astype(np.float64, copy=False)
    for c in range(D.shape[1]):
        Qc = Q.astype(np.float64) * D[:, c:c + 1]
        M = np.eye(k) - V64.T @ Qc                                    # I_k - V^T Q_c
        lu, piv, info = sla.lapack.dgetrf(M.T)
        anorm = float(np.abs(M).sum(axis=0).max()) if k else 1.0
        rcond = sla.lapack.dgecon(lu, anorm, norm="I")[0] if k and info == 0 else float(info == 0)
        # 1 / (||M^-1|| max(||M||, 1)): a tiny M (an eigenvalue of Q_c V^T at 1) is singular too
        rcond *= anorm / max(anorm, 1.0)
        if info != 0 or not rcond > _RCOND_MIN:
            raise FactorizationError(
                f"channel {c}: I - V^T Q_c ({k} x {k}) is singular (reciprocal condition "
                f"{rcond:.2e}); R F has an eigenvalue near 1 (reflectance too close to 1?)")
        # Y_c^T = -M^{-T} Q_c^T                                       # eq. (4)
        Y[c] = -sla.lu_solve((lu, piv), Qc.T, check_finite=False).T
    return Y


class HFactorization:
    """A factored radiosity system: solve ``(I - R_c F) B_c = E_c`` for any E in O(nk).

    ``B~_c = E_c - Y_c (V^T E_c)``, ``Y_c = -Q_c (I_k - V^T Q_c)^{-1}`` (eq. 4),
    computed in the internal (Z-order) patch order and returned in the user's.

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
    Y : (3, n, k) float, optional
        Precomputed Woodbury factors (as stored in an .hfr file).
    sigma_max : (3,) float, optional
        Cached power-iteration estimates of sigma_max(Q_c V^T).
    stats : PassStatistics, optional
        Row/column sums of F and the probe sketch recorded during the pass
        (internal order): what the guaranteed error bound is computed from.
    params : dict, optional
        Parameters of the run (block size, order, method...), for the record.

    Notes
    -----
    ``solver`` names the method ("woodbury"; the near-field split's subclass says its own).
    Memory O(nk) (Q, V and three Y_c in the factor dtype). Each right-hand side
    costs O(nk). Aguerre & Fernández 2016, eq. 2-5.
    """

    solver = "woodbury"

    def __init__(self, perm, Q, V, rho_max, reflectance, lowrank: LowRank, *, Y=None,
                 sigma_max=None, params: dict | None = None, scene=None, stats: PassStatistics | None = None):
        self._set_state(perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene, stats)
        self.Y = woodbury_factors(self.Q, self.V, self._D) if Y is None else np.asarray(Y, self.Q.dtype)

    def _set_state(self, perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene, stats) -> None:
        """What every solver of a factorization holds (shared with the near-field solver)."""
        self.perm = np.asarray(perm, dtype=np.int64)
        n = self.perm.size
        self.inv_perm = np.empty(n, np.int64)
        self.inv_perm[self.perm] = np.arange(n)
        self.Q = np.asarray(Q)
        self.V = np.asarray(V, dtype=self.Q.dtype)
        self.rho_max = np.asarray(rho_max, dtype=np.float64).reshape(n)
        self.reflectance = np.asarray(reflectance, dtype=np.float64).reshape(n, N_CHANNELS)
        self.lowrank = lowrank
        self.params = dict(params or {})
        self.scene = scene
        self.timings: dict = {}
        self._D = _channel_scale(self.reflectance, self.rho_max)[self.perm]
        self._sigma = None if sigma_max is None else np.asarray(sigma_max, np.float64)
        self._estimate: ErrorEstimate | None = None
        self.stats = stats

    # -- sizes and accuracy ------------------------------------------------
    @property
    def n_patches(self) -> int:
        return int(self.perm.size)

    @property
    def rank(self) -> int:
        """k, the rank of the factorization."""
        return int(self.Q.shape[1])

    @property
    def dtype(self) -> np.dtype:
        return self.Q.dtype

    @property
    def eps(self) -> float:
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
        """Accuracy figures of this factorization, per colour channel (computed once, cached).

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
        O(n k p) for the probes and a power iteration on the factors for eq. 5
        (O(nk) per step, a few hundred steps at most).
        """
        if self._estimate is None:
            if self._sigma is None:
                self._sigma = self._sigma_estimates()
            if self.stats is None:
                est = estimate_errors(self.achieved_error, self._sigma)
            else:
                est = estimate_errors(self.achieved_error, self._sigma,
                                      operator_error=self.stats.operator_error(self.Q, self.V, self._D,
                                                                               near=getattr(self, "N", None)),
                                      contraction=self.stats.contraction(self.reflectance[self.perm]),
                                      norm=self.stats.norm, failure_probability=FAILURE_PROBABILITY)
            bad = ~np.isfinite(est.bound)
            if bad.any():
                why = ("sigma_max + error >= 1, eq. 5 gives no bound" if est.kind == "eq5" else
                       f"contraction bound {np.round(est.contraction, 4).tolist()} and operator error "
                       f"{np.round(est.operator_error, 4).tolist()} give no bound")
                warnings.warn(f"no error bound for channels {np.flatnonzero(bad).tolist()}: {why}; "
                              "fac.residual(E, B) gives the per-solution figure", AccuracyWarning, stacklevel=2)
            self._estimate = est
        return self._estimate

    def _sigma_estimates(self) -> np.ndarray:
        """(3,) power-iteration estimates of sigma_max(Q_c V^T), for eq. 5."""
        return np.array([power_sigma_max(self.Q * self._D[:, c:c + 1].astype(self.dtype), self.V)
                         for c in range(N_CHANNELS)])

    @property
    def sigma_max(self) -> np.ndarray:
        """(3,) float: sigma_max(Q_c V^T) per channel (stored by :meth:`error_estimate`)."""
        return self.error_estimate().sigma_max

    @property
    def error_bound(self) -> np.ndarray:
        """(3,) float: the relative radiosity error bound per channel (see :meth:`error_estimate`)."""
        return self.error_estimate().bound

    @property
    def eq5_bound(self) -> np.ndarray:
        """(3,) float: the paper's eq. 5 figure per channel (see :meth:`error_estimate`)."""
        return self.error_estimate().eq5_bound

    # -- solving -------------------------------------------------------------
    def _validate(self, exitance, adjoint: bool) -> np.ndarray:
        E = np.asarray(exitance, dtype=np.float64)
        n = self.n_patches
        if E.ndim not in (1, 2, 3) or E.shape[0] != n or (E.ndim >= 2 and E.shape[1] != N_CHANNELS):
            raise InputError(f"exitance must have shape ({n},), ({n}, 3) or ({n}, 3, m) "
                             f"(patches in the scene's order); got {E.shape}")
        if not np.isfinite(E).all():
            bad = int(np.flatnonzero(~np.isfinite(E.reshape(n, -1)).all(axis=1))[0])
            raise InputError(f"exitance has a NaN or infinite value at patch {bad}")
        if not adjoint and (E < 0).any():
            bad = int(np.flatnonzero((E.reshape(n, -1) < 0).any(axis=1))[0])
            raise InputError(f"exitance must be >= 0 (W/m^2); patch {bad} has a negative value")
        return E

    def solve(self, exitance, trans: str = "N", *, transpose: bool | None = None) -> np.ndarray:
        """Radiosity ``B_c = (I - R_c F)^{-1} E_c`` for every channel (eq. 4).

        Parameters
        ----------
        exitance : (n,), (n, 3) or (n, 3, m) float >= 0, W/m^2, user patch order
            (n,) is a grey emission (the same for the three channels); (n, 3, m)
            is a batch of m emissions, solved together as matrix products.
        trans : {"N", "T"}
            "T" solves the adjoint ``(I - R_c F)^T x = e`` instead (inverse
            design), as in :func:`scipy.linalg.lu_solve`:
            ``(I - V Q_c^T)^{-1} = I - V Y_c^T``, so ``x = e - V (Y_c^T e)``.
            Negative entries are allowed then.
        transpose : bool, optional
            Deprecated spelling of ``trans="T"``.

        Returns
        -------
        radiosity : (n, 3) or (n, 3, m) float, W/m^2, user patch order

        Raises
        ------
        InputError (a ValueError)
            Wrong shape (expected and got are named), NaN/inf, negative
            exitance, or an unknown ``trans``.

        Notes
        -----
        O(n k) per right-hand side and channel.
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
        out = self._solve(E if batched else E[:, :, None], adjoint)
        return out if batched else out[:, :, 0]

    def _solve(self, E: np.ndarray, adjoint: bool) -> np.ndarray:
        """The solve of validated (n, 3, m) exitance in the user's order (the body of :meth:`solve`)."""
        Ei = E[self.perm]                                                 # (n, 3, m), internal order
        m = Ei.shape[2]
        # One pass over the shared factor for all channels and emissions at once,
        # then one pass over each channel's own factor: the solve is bandwidth bound.
        E2 = Ei.reshape(len(Ei), N_CHANNELS * m).astype(self.dtype)
        if adjoint:
            # (I - V Q_c^T)^{-1} = I - V Y_c^T:  x = e - V (Y_c^T e)
            W = np.concatenate([self.Y[c].T @ E2[:, c * m:(c + 1) * m] for c in range(N_CHANNELS)], axis=1)
            B = Ei - (self.V @ W).reshape(Ei.shape)
        else:
            W = self.V.T @ E2                                                  # (k, 3m)
            B = Ei.copy()
            for c in range(N_CHANNELS):
                B[:, c, :] -= self.Y[c] @ W[:, c * m:(c + 1) * m]           # eq. (4)
        return B[self.inv_perm]

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

    def residual(self, exitance, radiosity, *, form_factors=None, progress=None) -> ResidualEstimate:
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
            factorization's scene (as slow as the precompute's form factors).
        progress : callable (done, total), optional

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
        blocks = iter_column_blocks(self.scene, order=self.perm, progress=progress, **kwargs)
        return residual_estimate(blocks, self.reflectance, E, B, perm=self.perm, areas=areas)

    @property
    def areas(self) -> np.ndarray | None:
        """(n,) patch areas (m^2, user order) weighting the error norm, or None (plain 2-norm)."""
        if self.scene is not None:
            return np.asarray(self.scene.areas)
        if self.stats is not None and self.stats.weights is not None:
            return self.stats.weights[self.inv_perm]
        return None

    def save(self, path) -> "Path":
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
        inverses are recomputed: O(n k^2)).

        Raises
        ------
        ValueError
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
