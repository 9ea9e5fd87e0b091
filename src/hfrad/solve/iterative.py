"""Baseline iterative radiosity solvers on a dense F: Jacobi, Gauss-Seidel, Southwell, GMRES.

Each solves ``(I - R_c F) B_c = E_c`` for the three channels to a relative
residual ``||E_c - (I - R_c F) B_c||_2 / ||E_c||_2 <= rtol`` and reports the
iteration counts. They converge because ``I - R F`` is strictly diagonally
dominant by rows when F's rows sum to <= 1 and rho < 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse.linalg as spla

from ..errors import InputError


@dataclass
class IterativeResult:
    """Output of an iterative solver.

    Attributes
    ----------
    radiosity : (n, 3) float, W/m^2
    iterations : (3,) int
        Sweeps (Jacobi, Gauss-Seidel), single-patch relaxations (Southwell)
        or inner iterations (GMRES), per channel.
    residual : (3,) float
        Final relative residual per channel.
    converged : bool
    """

    radiosity: np.ndarray
    iterations: np.ndarray
    residual: np.ndarray
    converged: bool


def _inputs(form_factors, reflectance, exitance):
    F = np.ascontiguousarray(form_factors, dtype=np.float64)
    rho = np.asarray(reflectance, np.float64)
    E = np.asarray(exitance, np.float64)
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise InputError(f"form_factors must be a square (n, n) matrix; got shape {F.shape}")
    n = F.shape[0]
    if E.ndim == 1:
        E = np.repeat(E[:, None], 3, axis=1)
    if rho.shape != (n, 3):
        raise InputError(f"reflectance must have shape ({n}, 3) (n from form_factors); got {rho.shape}")
    if E.shape != (n, 3):
        raise InputError(f"exitance must have shape ({n},) or ({n}, 3) (n from form_factors); "
                         f"got {np.shape(exitance)}")
    return F, rho, np.ascontiguousarray(E)


def _rel_residual(F, rho, E, B) -> np.ndarray:
    r = np.linalg.norm(E - B + rho * (F @ B), axis=0)
    e = np.linalg.norm(E, axis=0)
    return np.divide(r, e, out=r.copy(), where=e > 0)


def jacobi(form_factors, reflectance, exitance, *, rtol: float = 1e-6, max_iter: int = 10_000) -> IterativeResult:
    """Jacobi sweeps ``B <- E + R F B`` (light bounce by bounce); O(n^2) per sweep.

    Parameters
    ----------
    form_factors : (n, n) float
    reflectance : (n, 3) float in [0, 1)
    exitance : (n,) or (n, 3) float, W/m^2
    rtol : float
        Target relative residual.
    max_iter : int
    """
    F, rho, E = _inputs(form_factors, reflectance, exitance)
    B = E.copy()
    it = np.zeros(3, np.int64)
    res = _rel_residual(F, rho, E, B)
    for _ in range(max_iter):
        active = res > rtol
        if not active.any():
            break
        B[:, active] = E[:, active] + rho[:, active] * (F @ B[:, active])
        it[active] += 1
        res = _rel_residual(F, rho, E, B)
    return IterativeResult(B, it, res, bool((res <= rtol).all()))


@numba.njit(cache=True)
def _gs_sweep(F, rho, E, B):
    n = F.shape[0]
    for i in range(n):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for j in range(n):
            if j != i:
                f = F[i, j]
                s0 += f * B[j, 0]
                s1 += f * B[j, 1]
                s2 += f * B[j, 2]
        fii = F[i, i]
        B[i, 0] = (E[i, 0] + rho[i, 0] * s0) / (1.0 - rho[i, 0] * fii)
        B[i, 1] = (E[i, 1] + rho[i, 1] * s1) / (1.0 - rho[i, 1] * fii)
        B[i, 2] = (E[i, 2] + rho[i, 2] * s2) / (1.0 - rho[i, 2] * fii)


def gauss_seidel(form_factors, reflectance, exitance, *, rtol: float = 1e-6,
                 max_iter: int = 10_000) -> IterativeResult:
    """Gauss-Seidel sweeps (numba), the three channels in one pass over F; O(n^2) per sweep."""
    F, rho, E = _inputs(form_factors, reflectance, exitance)
    B = E.copy()
    rho = np.ascontiguousarray(rho)
    it = np.zeros(3, np.int64)
    res = _rel_residual(F, rho, E, B)
    while (res > rtol).any() and it.max() < max_iter:
        _gs_sweep(F, rho, E, B)
        it[res > rtol] += 1
        res = _rel_residual(F, rho, E, B)
    return IterativeResult(B, it, res, bool((res <= rtol).all()))


@numba.njit(cache=True)
def _southwell(FT, rho, e, w, rtol, max_iter):
    """Shoot from the patch of largest unshot power w_i |r_i| until ||r|| <= rtol ||e||."""
    n = FT.shape[0]
    B = np.zeros(n)
    r = e.copy()
    target2 = (rtol * np.sqrt(np.sum(e * e))) ** 2
    norm2 = np.sum(r * r)
    i = int(np.argmax(w * np.abs(r)))
    it = 0
    while norm2 > target2 and it < max_iter:
        delta = r[i] / (1.0 - rho[i] * FT[i, i])
        B[i] += delta
        norm2 = 0.0
        best = -1.0
        nxt = 0
        for j in range(n):
            if j == i:
                r[j] = 0.0
            else:
                r[j] += rho[j] * FT[i, j] * delta      # column i of R F, row i of F^T
            norm2 += r[j] * r[j]
            p = w[j] * abs(r[j])
            if p > best:
                best = p
                nxt = j
        i = nxt
        it += 1
    return B, it, np.sqrt(norm2)


def southwell(form_factors, reflectance, exitance, *, areas=None, rtol: float = 1e-6,
              max_iter: int | None = None) -> IterativeResult:
    """Progressive refinement (Southwell relaxation, numba), one patch per iteration, O(n) each.

    Parameters
    ----------
    areas : (n,) float, m^2, optional
        Patches shoot in order of unshot power ``A_i |r_i|`` (Cohen et al. 1988);
        equal weights if omitted.
    max_iter : int, optional
        Relaxations per channel; default ``1000 n``.
    """
    F, rho, E = _inputs(form_factors, reflectance, exitance)
    n = F.shape[0]
    FT = np.ascontiguousarray(F.T)
    w = np.ones(n) if areas is None else np.asarray(areas, np.float64).reshape(n)
    max_iter = 1000 * max(n, 1) if max_iter is None else max_iter
    B = np.zeros_like(E)
    it = np.zeros(3, np.int64)
    for c in range(3):
        B[:, c], it[c], _ = _southwell(FT, np.ascontiguousarray(rho[:, c]), np.ascontiguousarray(E[:, c]),
                                       w, rtol, max_iter)
    res = _rel_residual(F, rho, E, B)
    return IterativeResult(B, it, res, bool((res <= rtol * (1 + 1e-6)).all()))


def gmres(form_factors, reflectance, exitance, *, rtol: float = 1e-6, restart: int = 50,
          max_iter: int = 1000) -> IterativeResult:
    """GMRES (scipy) on ``x -> x - R_c (F x)`` per channel; O(n^2) per inner iteration."""
    F, rho, E = _inputs(form_factors, reflectance, exitance)
    n = F.shape[0]
    B = np.zeros_like(E)
    it = np.zeros(3, np.int64)
    for c in range(3):
        rc = rho[:, c]
        op = spla.LinearOperator((n, n), matvec=lambda x, rc=rc: x - rc * (F @ x), dtype=np.float64)
        count = [0]

        def cb(_, count=count):
            count[0] += 1
        if np.any(E[:, c]):
            B[:, c], _ = spla.gmres(op, E[:, c], rtol=rtol, atol=0.0, restart=min(restart, max(n, 1)),
                                    maxiter=max_iter, callback=cb, callback_type="pr_norm")
        it[c] = count[0]
    res = _rel_residual(F, rho, E, B)
    return IterativeResult(B, it, res, bool((res <= rtol * (1 + 1e-6)).all()))
