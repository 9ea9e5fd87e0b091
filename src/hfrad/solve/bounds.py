"""Accuracy figures: the guaranteed error bounds, the eq. 5 figure and the a-posteriori residual.

docs/method.md, section 7 explains them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import numpy as np

__all__ = ["ErrorEstimate", "ResidualEstimate", "estimate_errors", "solution_bound", "relative_bound",
           "contraction_bound", "reflection_gain_bound", "power_sigma_max", "power_sigma_max_scaled", "eq5_bound",
           "residual_norm", "residual_estimate", "USEFUL_BOUND", "is_useful", "not_useful_channels", "percent",
           "accuracy_lines", "solution_line"]


def _figures(a) -> list:
    return [float(x) if np.isfinite(x) else None for x in np.atleast_1d(a)]


@dataclass(frozen=True)
class ErrorEstimate:
    """Accuracy figures of a factorization, per colour channel (R, G, B); docs/method.md, section 7.

    Attributes
    ----------
    bound : (3,) float
        Upper bound on the relative radiosity error ``||B~ - B|| / ||B||`` of
        any solve, in the norm ``norm``; inf where there is none.
    norm : {"area", "2"}
        ``"area"``: ``||x|| = sqrt(sum_i A_i x_i^2)`` (areas known, reciprocity);
        ``"2"``: the plain 2-norm (a matrix given without areas).
    kind : {"probes", "eq5"}
        ``"probes"``: the factorization error measured by random probes during
        the single pass, times the bound on ``||(I - R_c F)^{-1}||``; guaranteed
        except with probability ``failure_probability``. ``"eq5"``: no probes
        were recorded (an older file): ``bound`` is the eq. 5 figure, not
        guaranteed (sigma_max is an estimate from below).
    failure_probability : float or None
        Probability that ``bound`` is not an upper bound (None: no guarantee).
    operator_error : (3,) float or None
        Upper bound on ``||R_c F - Q_c V^T||`` in ``norm`` (same failure probability).
    contraction : (3,) float or None
        Upper bound on ``||R_c F||`` in ``norm``: ``max_i rho_c,i`` times the
        largest row sum of F (area norm) or ``sqrt(max row sum * max column sum)``.
    eq5_bound : (3,) float
        Aguerre & Fernández 2016, eq. 5: ``eps / (1 - sigma)`` with the
        achieved Frobenius error and ``sigma = sigma_max(Q_c V^T) + eps``
        (a secondary figure, kept for comparison with the paper).
    sigma_max : (3,) float
        Power-iteration estimate of sigma_max(Q_c V^T).

    The arrays are float64 copies of what was given, read-only: a
    factorization caches its estimate and hands these out.
    """

    bound: np.ndarray
    norm: str
    kind: str
    failure_probability: float | None
    operator_error: np.ndarray | None
    contraction: np.ndarray | None
    eq5_bound: np.ndarray
    sigma_max: np.ndarray

    def __post_init__(self) -> None:
        for name in ("bound", "operator_error", "contraction", "eq5_bound", "sigma_max"):
            value = getattr(self, name)
            if value is not None:
                value = np.array(value, dtype=np.float64)
                value.flags.writeable = False
                object.__setattr__(self, name, value)   # a frozen dataclass: set once, here

    def as_dict(self) -> dict:
        """JSON-ready figures (inf becomes None)."""
        return {"error_bound": _figures(self.bound), "error_norm": self.norm, "error_bound_kind": self.kind,
                "failure_probability": self.failure_probability,
                "operator_error": None if self.operator_error is None else _figures(self.operator_error),
                "contraction": None if self.contraction is None else _figures(self.contraction),
                "eq5_bound": _figures(self.eq5_bound), "sigma_max": _figures(self.sigma_max)}


def relative_bound(delta) -> np.ndarray:
    """``||B - B~|| / ||B||`` from ``delta >= ||B - B~|| / ||B~||``: ``delta / (1 - delta)``, inf if delta >= 1."""
    d = np.atleast_1d(np.asarray(delta, dtype=np.float64))
    out = np.full(d.shape, np.inf)
    ok = d < 1.0
    out[ok] = d[ok] / (1.0 - d[ok])
    return out


def solution_bound(operator_error, contraction) -> np.ndarray:
    """Relative radiosity error bound from ``||R_c F - G~_c|| <= operator_error`` and ``||R_c F|| <= contraction``.

    ``B - B~ = (I - R_c F)^{-1} (R_c F - G~_c) B~`` and
    ``||(I - R_c F)^{-1}|| <= 1 / (1 - contraction)``, so
    ``||B - B~|| / ||B~|| <= operator_error / (1 - contraction)``; then
    :func:`relative_bound`. inf where ``contraction >= 1``.
    """
    e = np.asarray(operator_error, dtype=np.float64)
    k = np.asarray(contraction, dtype=np.float64)
    delta = np.divide(e, 1.0 - k, out=np.full(e.shape, np.inf), where=k < 1.0)
    return relative_bound(delta)


def estimate_errors(achieved_error: float, sigma_max, *, operator_error=None, contraction=None,
                    norm: str = "2", failure_probability: float | None = None) -> ErrorEstimate:
    """Assemble an :class:`ErrorEstimate`; without probe figures the bound falls back to eq. 5."""
    sigma = np.asarray(sigma_max, dtype=np.float64)
    eq5 = eq5_bound(achieved_error, sigma + achieved_error)
    if operator_error is None or contraction is None:
        return ErrorEstimate(bound=eq5, norm="2", kind="eq5", failure_probability=None, operator_error=None,
                             contraction=None, eq5_bound=eq5, sigma_max=sigma)
    return ErrorEstimate(bound=solution_bound(operator_error, contraction), norm=norm, kind="probes",
                         failure_probability=failure_probability,
                         operator_error=np.asarray(operator_error, np.float64),
                         contraction=np.asarray(contraction, np.float64), eq5_bound=eq5, sigma_max=sigma)


@dataclass(frozen=True)
class ResidualEstimate:
    """The a-posteriori figures of one solution B~ (per channel), from one pass over the exact F.

    Attributes
    ----------
    residual : (3,) float
        ``||E - (I - R_c F) B~|| / ||E||`` in ``norm``.
    bound : (3,) float
        Guaranteed (deterministic) bound on ``||B~ - B|| / ||B||`` in ``norm``:
        ``||r|| / ((1 - contraction) ||B~||)`` through :func:`relative_bound`.
    contraction : (3,) float
        Upper bound on ``||R_c F||`` from this pass's row (and column) sums.
    norm : {"area", "2"}
    """

    residual: np.ndarray
    bound: np.ndarray
    contraction: np.ndarray
    norm: str

    def as_dict(self) -> dict:
        return {"residual": _figures(self.residual), "residual_bound": _figures(self.bound),
                "residual_norm": self.norm, "contraction": _figures(self.contraction)}


def contraction_bound(reflectance, row_sums, col_sums=None, *, weighted: bool = True) -> np.ndarray:
    """(3,) upper bound on ``||R_c F||`` per channel from the row (and column) sums of F >= 0.

    Area-weighted norm (``weighted``): reciprocity ``A_i F_ij = A_j F_ji`` makes
    ``A^{1/2} F A^{-1/2}`` symmetric, so its 2-norm is the spectral radius of F,
    at most the largest row sum. Plain 2-norm: ``||F||_2 <= sqrt(||F||_1 ||F||_inf)``.
    Then ``||R_c F|| <= max_i rho_c,i ||F||``.
    """
    rho = np.asarray(reflectance, dtype=np.float64).reshape(-1, 3)
    if rho.size == 0:
        return np.zeros(3)
    row = float(np.max(row_sums))
    norm_F = row if weighted else math.sqrt(row * float(np.max(col_sums)))
    return rho.max(axis=0) * norm_F


def reflection_gain_bound(reflectance, row_sums, col_sums=None, *, weighted: bool = True,
                          spectral=None) -> np.ndarray:
    """(3,) upper bound on ``||(I - R_c F)^{-1} R_c F||`` per channel: the most that the
    interreflections can multiply a vector's norm by, beside the vector itself.

    ``(I - M)^{-1} M = M + M^2 + ...``, so ``||.|| <= kappa / (1 - kappa)`` for ``kappa``
    of :func:`contraction_bound` (inf when ``kappa >= 1``). In the area norm a second,
    often much smaller figure: in the *balanced* norm with weights ``A_i / rho_i``,
    ``R F`` is similar to the symmetric ``R^{1/2} A^{1/2} F A^{-1/2} R^{1/2}`` (reciprocity),
    so its norm is its spectral radius, at most ``kappa_b = max_i rho_i sum_j F_ij`` (not
    ``max rho * max sum``: the brightest patch need not see the most); back to the area
    norm costs ``sqrt(max rho / min rho)``. The smaller of the two, per channel.

    ``spectral`` ((3,), optional): a smaller upper bound on that spectral radius than ``kappa_b``
    (:meth:`hfrad.solve.samples.SampledRows.spectral_bound`, one power step of Collatz-Wielandt);
    the smaller of the two is used.
    """
    rho = np.asarray(reflectance, dtype=np.float64).reshape(-1, 3)
    if rho.size == 0:
        return np.zeros(3)
    out = _geometric_tail(contraction_bound(rho, row_sums, col_sums, weighted=weighted))
    if weighted:
        kappa_b = (rho * np.asarray(row_sums, np.float64)[:, None]).max(axis=0)
        if spectral is not None:
            kappa_b = np.minimum(kappa_b, np.asarray(spectral, np.float64))
        lo, hi = rho.min(axis=0), rho.max(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            change = np.where(lo > 0, np.sqrt(hi / np.where(lo > 0, lo, 1.0)), np.inf)
            out = np.minimum(out, change * _geometric_tail(kappa_b))
    return out


def _geometric_tail(kappa: np.ndarray) -> np.ndarray:
    """``kappa / (1 - kappa)`` where ``kappa < 1``, else inf."""
    kappa = np.asarray(kappa, np.float64)
    return np.divide(kappa, 1.0 - kappa, out=np.full(kappa.shape, np.inf), where=kappa < 1.0)


def power_sigma_max(Q: np.ndarray, V: np.ndarray, *, row_scale: np.ndarray | None = None, rtol: float = 1e-7,
                    max_iter: int = 500) -> float:
    """Largest singular value of ``diag(row_scale) Q V^T`` (``Q V^T`` without it) by power iteration on
    the factors, O(nk) per step, in float64 (float64 Q and V are used without a copy)."""
    k = Q.shape[1]
    if k == 0:
        return 0.0
    Q64, V64 = Q.astype(np.float64, copy=False), V.astype(np.float64, copy=False)
    d = np.ones(Q.shape[0]) if row_scale is None else np.asarray(row_scale, np.float64)
    d2 = d * d
    x = np.ones(V.shape[0]) / math.sqrt(V.shape[0])
    sigma = 0.0
    for _ in range(max_iter):
        z = V64 @ (Q64.T @ (d2 * (Q64 @ (V64.T @ x))))    # A^T A x
        nz = np.linalg.norm(z)
        if nz == 0.0:
            return 0.0
        new = math.sqrt(nz)                     # ||A^T A x|| -> sigma^2 as x converges
        x = z / nz
        if abs(new - sigma) <= rtol * new:
            break
        sigma = new
    return float(np.linalg.norm(d * (Q64 @ (V64.T @ x))))


def power_sigma_max_scaled(Q: np.ndarray, V: np.ndarray, D: np.ndarray, **kwargs) -> np.ndarray:
    """(C,) :func:`power_sigma_max` of ``diag(D[:, c]) Q V^T`` for every column c of D.

    One float64 copy of Q and V for every channel (not one per channel); equal columns of D
    are iterated once. Matrix-vector products, not one product with C columns: OpenBLAS
    streams an n x k matrix several times slower through a 3-column GEMM than through GEMV.
    """
    Q64, V64 = Q.astype(np.float64), V.astype(np.float64)
    sigma = np.zeros(D.shape[1])
    for c in range(D.shape[1]):
        same = next((e for e in range(c) if np.array_equal(D[:, e], D[:, c])), None)
        sigma[c] = sigma[same] if same is not None else power_sigma_max(Q64, V64, row_scale=D[:, c], **kwargs)
    return sigma


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


def _stream_FB(blocks, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pass over column blocks of F: ``F B`` (n, 3), row sums and column sums of F."""
    n = B.shape[0]
    FB, rows, cols = np.zeros_like(B), np.zeros(n), np.zeros(n)
    for start, stop, Fb in blocks:
        Fb = np.asarray(Fb, np.float64)
        FB += Fb @ B[start:stop]
        rows += Fb.sum(axis=1)
        cols[start:stop] = Fb.sum(axis=0)
    return FB, rows, cols


def residual_estimate(blocks: Iterable[tuple[int, int, np.ndarray]], reflectance, exitance, radiosity,
                      *, perm=None, areas=None) -> ResidualEstimate:
    """The guaranteed per-solution figure: residual of B~ with the exact F, and the error bound it gives.

    ``B - B~ = (I - R_c F)^{-1} r`` with ``r = E - (I - R_c F) B~``, so
    ``||B - B~|| <= ||r|| / (1 - ||R_c F||)``; ``||R_c F||`` is bounded by this
    pass's own row sums (:func:`contraction_bound`).

    Parameters
    ----------
    blocks : iterable of (start, stop, Fblock)
        Column blocks of F, user order, or internal order when ``perm`` is given.
    reflectance : (n, 3) float, user order
    exitance, radiosity : (n, 3) float, W/m^2, user order
    perm : (n,) int, optional
    areas : (n,) float, m^2, user order, optional
        Patch areas: the area-weighted norm. Without them the plain 2-norm.

    Notes
    -----
    One pass over F, O(n^2) time, O(n b) memory.
    """
    rho = np.asarray(reflectance, np.float64)
    E = np.asarray(exitance, np.float64)
    B = np.asarray(radiosity, np.float64)
    w = None if areas is None else np.asarray(areas, np.float64)
    if perm is not None:
        rho, E, B = rho[perm], E[perm], B[perm]
        w = None if w is None else w[perm]
    FB, rows, cols = _stream_FB(blocks, B)
    r = E - (B - rho * FB)
    sw = np.ones(len(B)) if w is None else np.sqrt(w)
    norm = (lambda x: np.linalg.norm(sw[:, None] * x, axis=0))
    nr, ne, nb = norm(r), norm(E), norm(B)
    kappa = contraction_bound(rho, rows, cols, weighted=w is not None)
    delta = np.divide(nr, (1.0 - kappa) * nb, out=np.full(3, np.inf), where=(kappa < 1.0) & (nb > 0))
    delta[(nr == 0) & (kappa < 1.0)] = 0.0
    residual = np.divide(nr, ne, out=np.where(nr > 0, np.inf, 0.0), where=ne > 0)
    return ResidualEstimate(residual=residual, bound=relative_bound(delta), contraction=kappa,
                            norm="2" if w is None else "area")


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
    return residual_estimate(blocks, reflectance, exitance, radiosity, perm=perm).residual


#: A relative error bound at or above this (100%) says nothing: the error could be as large as the answer.
USEFUL_BOUND = 1.0

#: The relative error the advice for a lower ``eps`` aims at when the a-priori bound is of no use (10%).
ADVICE_TARGET = 0.1


def is_useful(bound) -> bool:
    """Whether every channel's relative error bound is finite and below :data:`USEFUL_BOUND`."""
    b = np.atleast_1d(np.asarray(bound, dtype=np.float64))
    return bool(b.size) and bool(np.all(np.isfinite(b) & (b < USEFUL_BOUND)))


def not_useful_channels(bound) -> str:
    """The channels whose figure is not below 100% (or none), in words: ``[0.941, inf, 1.2]`` ->
    ``'G and B are not below 100%'``; ``'no channel is below 100%'`` when every channel fails."""
    b = np.atleast_1d(np.asarray(bound, dtype=np.float64))
    bad = ~(np.isfinite(b) & (b < USEFUL_BOUND))
    names = ("R", "G", "B") if b.size == 3 else tuple(f"channel {k}" for k in range(b.size))
    if bad.all():
        return "no channel is below 100%" if b.size > 1 else "not below 100%"
    failing = [name for name, f in zip(names, bad) if f]
    listed = failing[0] if len(failing) == 1 else ", ".join(failing[:-1]) + " and " + failing[-1]
    return f"{listed} {'is' if len(failing) == 1 else 'are'} not below 100%"


def percent(values) -> str:
    """``[0.0031, 1.55, inf]`` -> ``'0.31%, 155%, none'``: relative figures as percentages."""
    return ", ".join(f"{100 * float(v):.3g}%" if np.isfinite(v) else "none" for v in np.atleast_1d(values))


def _eps_for(estimate: ErrorEstimate, achieved_error: float, target: float = ADVICE_TARGET) -> float | None:
    """The ``eps`` that would bring the a-priori bound to about ``target``, or None when none can.

    The bound is ``delta / (1 - delta)`` with ``delta = operator_error / (1 - contraction)``,
    and the probed operator error scales with the achieved factorization error
    (Cornell box, 300 patches: 5.2, 5.1 and 4.7 times it at eps 0.02, 0.01, 0.005).
    """
    if estimate.operator_error is None or estimate.contraction is None or not achieved_error > 0:
        return None
    kappa = float(np.max(estimate.contraction))
    op = float(np.max(estimate.operator_error))
    if not (kappa < 1.0 and op > 0 and np.isfinite(op)):
        return None
    delta = target / (1.0 + target)
    return achieved_error * delta * (1.0 - kappa) / op


def solution_line(error) -> str:
    """The per-solve figure in words (:class:`~hfrad.solve.samples.SolutionError`, one solve)."""
    norm = "area norm" if error.norm == "reflected" else "2-norm"
    if error.kind == "unavailable":
        return ("no per-solve error figure: this file has no sampled rows of F (written by an older hfrad); "
                "`hfrad solve --residual` gives one, or precompute again")
    how = ("a bound: every row of F is stored" if error.kind == "exact-rows" else
           f"an estimate from {error.rows} exact rows of F, no stated failure probability"
           if error.failure_probability is None else
           f"from {error.rows} exact rows of F; may fail with probability {error.failure_probability:.2g}")
    if not is_useful(error.bound):
        return (f"error of this solution: no useful figure ({percent(error.bound)} of the reflected light, R,G,B; "
                f"{how}); precompute with a lower --eps")
    return f"error of this solution: at most {percent(error.bound)} of the reflected light (R,G,B; {norm}; {how})"


def accuracy_lines(estimate: ErrorEstimate, *, residual: ResidualEstimate | None = None,
                   achieved_error: float | None = None, solution=None) -> list[str]:
    """The accuracy figures in words, the figure a user can rely on first (docs/method.md, section 7).

    0. With ``solution`` (:class:`~hfrad.solve.samples.SolutionError`): the per-solve
       figure from the stored rows of F, relative to the reflected light.
    1. With ``residual``: the guaranteed bound of that one solution.
    2. The a-priori bound for any light, when it says something (every
       channel below 100%); otherwise "no useful a-priori bound" with what to
       do: the solution's residual, or a lower ``eps`` (estimated from the
       achieved error when ``achieved_error`` is given).
    3. The paper's eq. 5 figure, marked as not guaranteed.

    Parameters
    ----------
    estimate : ErrorEstimate
        ``fac.error_estimate()``.
    residual : ResidualEstimate, optional
        ``fac.residual(E, B)`` of a solution.
    solution : SolutionError, optional
        ``fac.solve(E, return_error=True)[1]`` of one solve.
    achieved_error : float, optional
        ``fac.relative_error``: the achieved relative Frobenius error of the factorization.

    Returns
    -------
    list of str
    """
    lines = [] if solution is None else [solution_line(solution)]
    if residual is not None:
        if is_useful(residual.bound):
            lines.append(f"guaranteed bound of this solution (--residual): at most {percent(residual.bound)} (R,G,B; relative, "
                         f"{residual.norm} norm; guaranteed, a posteriori with the exact form factors)")
        else:
            lines.append(f"no useful bound on the error of this solution: the a-posteriori figure is "
                         f"{percent(residual.bound)} (R,G,B); precompute with a lower --eps")
    norm = f"{estimate.norm} norm"
    if estimate.kind == "probes" and is_useful(estimate.bound):
        lines.append(f"a-priori bound on the relative radiosity error of any solve: at most {percent(estimate.bound)} "
                     f"(R,G,B; {norm}; guaranteed except with probability {estimate.failure_probability:g})")
    elif estimate.kind == "probes":
        eps = None if achieved_error is None else _eps_for(estimate, achieved_error)
        todo = ("`hfrad solve --residual` gives the guaranteed figure of one solution"
                + (f"; for an a-priori bound of about {100 * ADVICE_TARGET:.0f}%, precompute with --eps {eps:.2g} "
                   "or lower" if eps is not None else
                   "; the reflectance times the form factors' row sums reaches 1, so no eps gives an a-priori bound"))
        lines.append(f"no useful a-priori bound on the relative radiosity error of a solve (the guaranteed figure is "
                     f"{percent(estimate.bound)}, R,G,B: {not_useful_channels(estimate.bound)}); {todo}")
    else:
        lines.append("no a-priori bound on the relative radiosity error in this file (written without pass "
                     "statistics); `hfrad solve --residual` gives the guaranteed figure of one solution")
    lines.append(f"eq. 5 bound (the paper's estimate, not guaranteed): {percent(estimate.eq5_bound)} "
                 f"(sigma_max {', '.join(f'{v:.3g}' for v in np.atleast_1d(estimate.sigma_max))})")
    return lines
