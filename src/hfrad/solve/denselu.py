"""Baseline: dense LU of (I - R_c F) per channel (O(n^3) once, O(n^2) per solve)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ..errors import InputError
from ..validation import check_finite, check_trans


class LUFactorization:
    """``lu_factor(I - R_c F)`` for each channel; solve like :class:`HFactorization`.

    Parameters
    ----------
    form_factors : (n, n) float
    reflectance : (n, 3) float in [0, 1)
    """

    def __init__(self, form_factors, reflectance):
        F = check_finite(form_factors, "form_factors")
        rho = check_finite(reflectance, "reflectance")
        n = F.shape[0]
        if F.shape != (n, n) or rho.shape != (n, 3):
            raise InputError(f"expected form factors (n, n) and reflectance (n, 3); got {F.shape}, {rho.shape}")
        self.n_patches = n
        self._lu = [sla.lu_factor(np.eye(n) - rho[:, c:c + 1] * F, check_finite=False) for c in range(3)]

    def solve(self, exitance, trans: str = "N") -> np.ndarray:
        """Radiosity (n, 3) (or (n, 3, m)) for exitance (n,), (n, 3) or (n, 3, m), W/m^2.

        ``trans="T"`` solves the adjoint system, as in :meth:`HFactorization.solve`.
        """
        adjoint = check_trans(trans)
        E = check_finite(exitance, "exitance")
        if E.ndim == 1:
            E = np.repeat(E[:, None], 3, axis=1)
        if E.shape[0] != self.n_patches or E.shape[1] != 3:
            raise InputError(f"exitance must have shape ({self.n_patches}, 3[, m]); got {E.shape}")
        out = np.empty_like(E)
        for c in range(3):
            out[:, c] = sla.lu_solve(self._lu[c], E[:, c], trans=1 if adjoint else 0, check_finite=False)
        return out


def solve_direct(form_factors, reflectance, exitance) -> np.ndarray:
    """Exact (to rounding) radiosity ``B_c = (I - R_c F)^{-1} E_c``, (n, 3), W/m^2."""
    return LUFactorization(form_factors, reflectance).solve(exitance)
