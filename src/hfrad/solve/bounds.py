"""Accuracy figures: sigma_max, the eq. 5 bound and the a-posteriori residual."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

__all__ = ["ErrorEstimate", "estimate_errors", "power_sigma_max", "eq5_bound", "residual_norm"]


@dataclass(frozen=True)
class ErrorEstimate:
    """Accuracy figures of a factorization, per colour channel (R, G, B).

    Attributes
    ----------
    bound : (3,) float
        The relative radiosity error figure to quote, in the norm ``norm``.
    norm : str
        The norm of ``bound``.
    eq5_bound : (3,) float
        Aguerre & Fernández 2016, eq. 5: ``eps / (1 - sigma)`` with the
        achieved Frobenius error (a secondary figure; inf where sigma >= 1).
    sigma_max : (3,) float
        Power-iteration estimate of sigma_max(Q_c V^T).
    """

    bound: np.ndarray
    norm: str
    eq5_bound: np.ndarray
    sigma_max: np.ndarray

    def as_dict(self) -> dict:
        """JSON-ready figures (inf becomes None)."""
        def num(a):
            return [float(x) if np.isfinite(x) else None for x in np.atleast_1d(a)]
        return {"error_bound": num(self.bound), "error_norm": self.norm, "eq5_bound": num(self.eq5_bound),
                "sigma_max": num(self.sigma_max)}


def estimate_errors(achieved_error: float, sigma_max) -> ErrorEstimate:
    """The figures of :class:`ErrorEstimate` from the achieved Frobenius error and sigma_max(Q_c V^T).

    eq. 5 uses ``sigma = sigma_max(Q_c V^T) + error`` (Weyl: an upper bound on
    sigma_max(R_c F) when the power estimate has converged).
    """
    sigma = np.asarray(sigma_max, dtype=np.float64)
    eq5 = eq5_bound(achieved_error, sigma + achieved_error)
    return ErrorEstimate(bound=eq5, norm="2", eq5_bound=eq5, sigma_max=sigma)


def power_sigma_max(Q: np.ndarray, V: np.ndarray, *, rtol: float = 1e-7, max_iter: int = 500) -> float:
    """Largest singular value of ``Q V^T`` by power iteration on the factors, O(nk) per step."""
    k = Q.shape[1]
    if k == 0:
        return 0.0
    x = np.ones(V.shape[0]) / math.sqrt(V.shape[0])
    Q64, V64 = Q.astype(np.float64), V.astype(np.float64)
    sigma = 0.0
    for _ in range(max_iter):
        y = Q64 @ (V64.T @ x)                   # A x
        z = V64 @ (Q64.T @ y)                   # A^T A x
        nz = np.linalg.norm(z)
        if nz == 0.0:
            return 0.0
        new = math.sqrt(nz)                     # ||A^T A x|| -> sigma^2 as x converges
        x = z / nz
        if abs(new - sigma) <= rtol * new:
            sigma = new
            break
        sigma = new
    return float(np.linalg.norm(Q64 @ (V64.T @ x)))


def eq5_bound(error: float, sigma_max) -> np.ndarray:
    """``error / (1 - sigma_max)`` (eq. 5), inf where ``sigma_max >= 1``.

    Parameters
    ----------
    error : float
        Absolute 2-norm (or Frobenius, which bounds it) error ``||RF - Q V^T||``.
    sigma_max : float or (c,) float
        Largest singular value of RF (an upper estimate keeps the bound valid).
    """
    s = np.atleast_1d(np.asarray(sigma_max, dtype=np.float64))
    out = np.full(s.shape, np.inf)
    ok = s < 1.0
    out[ok] = error / (1.0 - s[ok])
    return out


def residual_norm(blocks: Iterable[tuple[int, int, np.ndarray]], reflectance, exitance, radiosity,
                  *, perm=None) -> np.ndarray:
    """A-posteriori ``||(I - R_c F) B~_c - E_c||_2 / ||E_c||_2`` per channel, streaming F.

    Parameters
    ----------
    blocks : iterable of (start, stop, Fblock)
        Column blocks of F: ``F[:, start:stop]`` in user order, or, when
        ``perm`` is given, ``F[perm][:, perm[start:stop]]`` (internal order).
    reflectance : (n, 3) float, user order
    exitance, radiosity : (n, 3) float, W/m^2, user order
    perm : (n,) int, optional

    Returns
    -------
    (3,) float: relative residual per channel (0 where E_c = 0 and the residual is 0).

    Notes
    -----
    One pass over F, O(n^2) time, O(n b) memory.
    """
    rho = np.asarray(reflectance, np.float64)
    E = np.asarray(exitance, np.float64)
    B = np.asarray(radiosity, np.float64)
    if perm is not None:
        rho, E, B = rho[perm], E[perm], B[perm]
    FB = np.zeros_like(B)
    for start, stop, Fb in blocks:
        FB += np.asarray(Fb, np.float64) @ B[start:stop]
    r = B - rho * FB - E
    nr, ne = np.linalg.norm(r, axis=0), np.linalg.norm(E, axis=0)
    return np.divide(nr, ne, out=np.where(nr > 0, np.inf, 0.0), where=ne > 0)
