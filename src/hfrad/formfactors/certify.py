"""A certificate of an approximate F from a sample of its exact rows.

For an approximation ``F~`` of F (an H-matrix, a sampled far field, a factorization) the
error that the solver's bounds need is the area-weighted Frobenius norm of

    D = A^{1/2} diag(rho) (F - F~) A^{-1/2},     ||D||_F^2 = sum_i e_i,
    e_i = A_i rho_i^2 sum_j (F - F~)_ij^2 / A_j

(A the patch areas, rho the rows' ``rho_max``; the same norm as
:class:`~hfrad.formfactors.farfield.FarFieldCertificate`'s). ``e_i`` needs row i of F
exactly: a few hundred such rows, drawn at random, estimate ``||D||_F`` without bias and
give an upper figure that fails with a stated probability.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["RowCertificate", "FAILURE", "DEFENSIVE_SHARE", "upper_margin", "row_errors"]

#: The upper figure's stated failure probability (the far field's ``CERTIFICATE_FAILURE``).
FAILURE = 0.025
#: Share of an importance-weighted draw spread evenly over all rows: a defensive mixture, so that
#: ``e_i / pi_i`` is at most ``n / DEFENSIVE_SHARE`` times ``e_i`` where the weights miss a row
#: (the far field's certificate mixes the same share).
DEFENSIVE_SHARE = 0.3


@dataclass(frozen=True)
class RowCertificate:
    """Which exact rows to compute, and what they say about ``||D||_F``.

    Each of the ``m`` slots draws one row; its total ``y_k = e_{rows[k]} * scale[k]`` has the
    expectation ``||D||_F^2`` (stratified: ``scale = m N_k``, ``N_k`` the size of the slot's
    stratum of the internal order; importance-weighted: ``scale = 1 / pi``, the Horvitz-Thompson
    (Hansen-Hurwitz) weight of a draw with replacement), and the slots are independent.

    Attributes
    ----------
    rows : (m,) int
        Internal positions of the rows to compute exactly, one per slot (a weighted draw may
        repeat a row: compute ``np.unique(rows)`` and index back).
    scale : (m,) float
        What each slot's ``e`` is multiplied by.
    n : int
    seed : int
    weighted : bool
        Drawn by importance (``weights`` given) or stratified.
    """

    rows: np.ndarray
    scale: np.ndarray
    n: int
    seed: int
    weighted: bool

    @classmethod
    def draw(cls, n: int, m: int, weights=None, seed: int = 0) -> "RowCertificate":
        """``m`` rows of n to certify with.

        Parameters
        ----------
        n : int >= 1
            Rows of F.
        m : int >= 2
            Slots (a variance needs two). Stratified: at most n (m = n computes every row).
        weights : (n,) float >= 0 or None
            None: one row drawn uniformly from each of m equal strata of the internal order
            (consecutive positions: Z-order keeps neighbours together, so each stratum is a region
            of the scene); dependable where the error is spread over many rows, not where a few
            rows hold much of it (6 rows of 600 with a third of ``||D||_F^2``: the upper figure
            fell below in a third of the redraws, tests/test_row_certificate.py).
            Given: m rows drawn independently with probability
            ``pi_i = DEFENSIVE_SHARE / n + (1 - DEFENSIVE_SHARE) w_i / sum(w)``; the weights
            should grow with the rows' expected error (``e_i``): the closer, the smaller the
            variance. All zero: uniform.
        seed : int
            The same seed draws the same rows.

        Raises
        ------
        InputError
            n, m or weights out of range.
        """
        n, m, w = _check_draw(n, m, weights)
        rng = np.random.default_rng([int(seed), n, m])
        if w is None:
            rows, scale = _stratified(n, m, rng)
        else:
            pi = _mixture(w)
            cdf = np.cumsum(pi)
            rows = np.minimum(np.searchsorted(cdf, rng.random(m) * cdf[-1], side="right"), n - 1)
            scale = 1.0 / pi[rows]
        return cls(rows.astype(np.int64), scale, n, int(seed), w is not None)

    def estimate(self, exact_rows, approx_rows, rho, areas, *, failure: float = FAILURE) -> tuple[float, float]:
        """(estimate, upper figure) of ``||D||_F`` from the rows at :attr:`rows`.

        Parameters
        ----------
        exact_rows, approx_rows : (m, n) float
            Rows ``rows`` of F and of the approximation ``F~`` (in slot order, columns in the
            internal order).
        rho : (n,) float
            ``rho_max`` of each patch (internal order).
        areas : (n,) float > 0, m^2
            Patch areas (internal order).
        failure : float in (0, 1)
            The upper figure is below ``||D||_F`` with probability at most this (Cantelli's
            inequality with the slots' sample variance: :func:`upper_margin`).

        Returns
        -------
        (float, float)
            ``sqrt(mean(y))``, whose square is an unbiased estimate of ``||D||_F^2``, and
            ``sqrt(mean(y) + upper_margin(y, failure))``.
        """
        d, rho, areas = self._check_rows(exact_rows, approx_rows, rho, areas, failure)
        y = row_errors(d, self.rows, rho, areas) * self.scale
        mean = float(y.mean())
        return math.sqrt(mean), math.sqrt(mean + upper_margin(y, failure))

    def _check_rows(self, exact_rows, approx_rows, rho, areas, failure):
        m, n = self.rows.size, self.n
        exact = np.asarray(exact_rows, np.float64)
        approx = np.asarray(approx_rows, np.float64)
        for name, a in (("exact_rows", exact), ("approx_rows", approx)):
            if a.shape != (m, n):
                raise InputError(f"{name} must have shape ({m}, {n}) (one row of n per slot); got {a.shape}")
        rho = np.asarray(rho, np.float64).reshape(-1)
        areas = np.asarray(areas, np.float64).reshape(-1)
        if rho.shape != (n,) or areas.shape != (n,):
            raise InputError(f"rho and areas must have shape ({n},); got {rho.shape} and {areas.shape}")
        if not (areas > 0).all():
            raise InputError("areas must be > 0")
        if not (0.0 < failure < 1.0):
            raise InputError(f"failure must be in (0, 1); got {failure!r}")
        return exact - approx, rho, areas


def row_errors(d: np.ndarray, rows: np.ndarray, rho: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """(m,) ``e_i = A_i rho_i^2 sum_j d_ij^2 / A_j`` of the rows ``d = (F - F~)[rows]`` (m, n), float64.

    Each row's share of ``||D||_F^2`` (see the module's docstring); callers that compute the exact
    rows a few at a time (the hierarchical precompute) sum these and scale them by the slots'
    :attr:`RowCertificate.scale`.
    """
    d = np.asarray(d, np.float64) * rho[rows, None]
    return areas[rows] * np.einsum("ij,ij->i", d, d / areas[None, :])


def _check_draw(n, m, weights):
    if int(n) != n or n < 1:
        raise InputError(f"n must be an integer >= 1; got {n!r}")
    if int(m) != m or m < 2:
        raise InputError(f"m must be an integer >= 2 (a variance needs two slots); got {m!r}")
    if weights is None:
        return int(n), max(min(int(m), int(n)), 2), None
    w = np.asarray(weights, np.float64)
    if w.shape != (n,):
        raise InputError(f"weights must have shape ({n},); got {w.shape}")
    if not (np.isfinite(w).all() and (w >= 0).all()):
        raise InputError("weights must be finite and >= 0")
    return int(n), int(m), w


def _stratified(n: int, m: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """One row uniformly from each of m near-equal strata of ``0..n-1``; ``scale = m N_k``."""
    edges = np.floor(np.linspace(0, n, m + 1)).astype(np.int64)
    sizes = np.diff(edges)
    if (sizes == 0).any():       # n < m: a single row drawn m times over the whole range
        rows = rng.integers(0, n, m)
        return rows, np.full(m, float(n))
    rows = edges[:-1] + np.floor(rng.random(m) * sizes).astype(np.int64)
    return np.minimum(rows, edges[1:] - 1), m * sizes.astype(np.float64)


def _mixture(w: np.ndarray) -> np.ndarray:
    """(n,) ``DEFENSIVE_SHARE / n + (1 - DEFENSIVE_SHARE) w / sum(w)`` (uniform if w sums to 0)."""
    n, total = w.size, float(w.sum())
    if not (total > 0):
        return np.full(n, 1.0 / n)
    return DEFENSIVE_SHARE / n + (1.0 - DEFENSIVE_SHARE) * w / total


def upper_margin(y: np.ndarray, failure: float) -> float:
    """What to add to the mean of the iid slots ``y`` so that their expectation lies above it but
    with probability ``failure``: ``sqrt(1 / failure - 1)`` standard errors (Cantelli's one-sided
    inequality, which holds for any distribution of the mean; here with the slots' sample variance).

    Not the normal quantile: the errors sit in few rows, so the slots are skewed (skewness ~7 on
    6 blocks of the 40K Cornell box) and a sample that misses the heavy rows also understates the
    variance; Student's t with Johnson's skewness term, Hall's transformation and the bootstrap-t
    put the upper figure below the measured error in 18-20% of 50 redraws at a stated 2.5%, this
    bound in none (benchmarks/README.md, "A dependable certificate")."""
    m = y.size
    if m < 2:
        return math.inf
    return math.sqrt((1.0 / failure - 1.0) * float(y.var(ddof=1)) / m)
