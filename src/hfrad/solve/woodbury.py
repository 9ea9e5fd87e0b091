"""The factorization object: solve (I - R_c F) B_c = E_c in O(nk) by Sherman-Morrison-Woodbury.

Colour without three factorizations (METHOD.md section 3): G = diag(rho_max) F
is factored once, G ~= Q V^T, and channel c uses Q_c = D_c Q with
D_c = diag(rho_c / rho_max), so ``R_c F ~= Q_c V^T`` with the same error bound.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg as sla

from ..errors import AccuracyWarning, FactorizationError
from ..factorize.lowrank import LowRank
from ..validation import check_reflectance
from .bounds import eq5_bound, power_sigma_max

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
                 sigma_max=None, params: dict | None = None, scene=None):
        self._set_state(perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene)
        self.Y = woodbury_factors(self.Q, self.V, self._D) if Y is None else np.asarray(Y, self.Q.dtype)

    def _set_state(self, perm, Q, V, rho_max, reflectance, lowrank, sigma_max, params, scene) -> None:
        """Everything but the solver's own factors (shared with the near-field subclass)."""
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

    @property
    def sigma_max(self) -> np.ndarray:
        """(3,) float: sigma_max(Q_c V^T) per channel, power iteration on the factors (cached)."""
        if self._sigma is None:
            self._sigma = np.array([power_sigma_max(self.Q * self._D[:, c:c + 1].astype(self.dtype), self.V)
                                    for c in range(N_CHANNELS)])
        return self._sigma

    @property
    def error_bound(self) -> np.ndarray:
        """(3,) float: eq. 5 bound on ``||B~_c - B_c|| / ||B_c||`` per channel.

        ``eps_abs / (1 - sigma)`` with ``eps_abs`` the achieved absolute
        Frobenius error (>= the 2-norm error of every channel) and, to stay
        conservative, ``sigma = sigma_max(Q_c V^T) + eps_abs`` (Weyl: an upper
        bound on sigma_max(R_c F) when the power estimate has converged).
        ``inf`` with an AccuracyWarning where ``sigma >= 1``.
        """
        e = self.achieved_error
        sigma = self.sigma_max + e
        bound = eq5_bound(e, sigma)
        ok = np.isfinite(bound)
        if not ok.all():
            warnings.warn(f"sigma_max + error >= 1 for channels {np.flatnonzero(~ok).tolist()} "
                          f"(sigma estimates {sigma.round(4).tolist()}); eq. 5 gives no bound",
                          AccuracyWarning, stacklevel=2)
        return bound

    # -- solving -------------------------------------------------------------
    def _validate(self, exitance, transpose: bool) -> np.ndarray:
        E = np.asarray(exitance, dtype=np.float64)
        n = self.n_patches
        if E.ndim not in (1, 2, 3) or E.shape[0] != n or (E.ndim >= 2 and E.shape[1] != N_CHANNELS):
            raise ValueError(f"exitance must have shape ({n},), ({n}, 3) or ({n}, 3, m) "
                             f"(patches in the scene's order); got {E.shape}")
        if not np.isfinite(E).all():
            bad = int(np.flatnonzero(~np.isfinite(E.reshape(n, -1)).all(axis=1))[0])
            raise ValueError(f"exitance has a NaN or infinite value at patch {bad}")
        if not transpose and (E < 0).any():
            bad = int(np.flatnonzero((E.reshape(n, -1) < 0).any(axis=1))[0])
            raise ValueError(f"exitance must be >= 0 (W/m^2); patch {bad} has a negative value")
        return E

    def solve(self, exitance, *, transpose: bool = False) -> np.ndarray:
        """Radiosity ``B_c = (I - R_c F)^{-1} E_c`` for every channel (eq. 4).

        Parameters
        ----------
        exitance : (n,), (n, 3) or (n, 3, m) float >= 0, W/m^2, user patch order
            (n,) is a grey emission (the same for the three channels); (n, 3, m)
            is a batch of m emissions, solved together as matrix products.
        transpose : bool
            Solve the adjoint ``(I - R_c F)^T x = e`` instead (inverse design):
            ``(I - V Q_c^T)^{-1} = I - V Y_c^T``, so ``x = e - V (Y_c^T e)``.
            Negative entries are allowed then.

        Returns
        -------
        radiosity : (n, 3) or (n, 3, m) float, W/m^2, user patch order

        Raises
        ------
        ValueError
            Wrong shape (expected and got are named), NaN/inf, or negative exitance.

        Notes
        -----
        O(n k) per right-hand side and channel.
        """
        E = self._validate(exitance, transpose)
        if E.ndim == 1:
            E = np.repeat(E[:, None], N_CHANNELS, axis=1)
        batched = E.ndim == 3
        Ei = E[self.perm] if batched else E[self.perm][:, :, None]   # (n, 3, m), internal order
        m = Ei.shape[2]
        # One pass over the shared factor for all channels and emissions at once,
        # then one pass over each channel's own factor: the solve is bandwidth bound.
        E2 = Ei.reshape(len(Ei), N_CHANNELS * m).astype(self.dtype)
        if transpose:
            # (I - V Q_c^T)^{-1} = I - V Y_c^T:  x = e - V (Y_c^T e)
            W = np.concatenate([self.Y[c].T @ E2[:, c * m:(c + 1) * m] for c in range(N_CHANNELS)], axis=1)
            B = Ei - (self.V @ W).reshape(Ei.shape)
        else:
            W = self.V.T @ E2                                                  # (k, 3m)
            B = Ei.copy()
            for c in range(N_CHANNELS):
                B[:, c, :] -= self.Y[c] @ W[:, c * m:(c + 1) * m]           # eq. (4)
        out = B[self.inv_perm]
        return out if batched else out[:, :, 0]

    def _checked_reflectance(self, reflectance) -> np.ndarray:
        """(n, 3) float64 reflectance, validated and <= rho_max (ValueError naming the patch)."""
        rho = check_reflectance(reflectance, self.n_patches)
        over = rho.max(axis=1) > self.rho_max * (1 + 1e-12)
        if over.any():
            i = int(np.flatnonzero(over)[0])
            raise ValueError(f"patch {i} reflectance {rho[i].tolist()} exceeds rho_max "
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
                              params=self.params, scene=self.scene)

    def __repr__(self) -> str:
        return (f"HFactorization(n_patches={self.n_patches}, rank={self.rank}, "
                f"relative_error={self.relative_error:.3g}, dtype={self.dtype.name})")
