"""Target quantities as affine functions of the emitter intensities, through the factorization.

Radiosity is linear in the emission, so with ``E(s) = E_0 + sum_e s_e E_e``
(``E_0`` the fixed background, ``E_e`` emitter e at unit intensity) every
target quantity is ``q(s) = q_0 + M s``. The columns of ``M`` come from one
batched solve ``fac.solve([E_1 ... E_m])`` (m right-hand sides, O(m n k); no
dense inverse, no form-factor matrix). When the goals need fewer rows than
there are emitters, :func:`adjoint_response` gets the same rows by transposed
solves, one per row, each row's response to every emitter at once.

Irradiance
----------
The radiosity equation per channel c is ``B_c = E_c + rho_c H_c`` with
``H_c = F B_c`` the irradiance (W/m^2 arriving per unit area). Hence

    H_c = (B_c - E_c) / rho_c          where rho_c > 0.

This is exact for the factorized system too, not an approximation on top of
it: the Woodbury solve returns the exact solution of ``(I - D_c Q V^T) B = E``
with ``D_c = diag(rho_c / rho_max)``, so ``(B - E) / rho_c = diag(1/rho_max) Q
V^T B``, the factorization's own ``F~ B`` (F~ = diag(1/rho_max) G~ approximates
F to the factorization's error). It costs nothing beyond the solve.

Where rho_c = 0 the quotient is 0/0: a black patch reflects nothing, so its
radiosity carries no trace of the light it receives, and (if all channels are
black, rho_max = 0) neither does the factorization (its rows of G are zero).
For those patches the irradiance is computed from its meaning, ``H = F[i, :]
B``, with the patch's exact row of form factors (same kernel and visibility
samples as the precompute): O(|T0| n) form factors for the |T0| black target
patches only.

Photometry
----------
All quantities are luminance-weighted with the same conversion the false-colour
renderer uses (:func:`hfrad.render.falsecolor.photometric`): ``radiosity`` and
``irradiance`` in W/m^2 (Rec. 709 weights), ``irradiance_lux`` x 683 lm/W, as
``hfrad render --falsecolor --unit lux``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..formfactors.blocks import FormFactorEngine
from ..formfactors.visibility import DEFAULT_SAMPLES
from ..progress import ProgressCallback, report
from ..render.falsecolor import photometric
from .spec import DesignSpec, Target

#: memory for one batch of right-hand sides and radiosities (bytes); more emitters take several batches
BATCH_BYTES = 256 * 2**20

_UNITS = {"radiosity": "W/m2", "irradiance": "W/m2", "irradiance_lux": "lux"}


@dataclass
class Response:
    """``q_t(s) = offset[t] + matrix[t] @ s`` for every target t.

    Attributes
    ----------
    matrix : list of (p_t, m) float
        Target quantity per unit intensity of each emitter, per target patch.
    offset : list of (p_t,) float
        The quantity due to the fixed background emission alone.
    weight : list of (p_t,) float
        Area weights of the target patches (sum 1), for means.
    evaluations : int
        Radiosity solves used (right-hand sides).
    seconds : float
        Wall time of the solves and of the quantities.
    quantities : Quantities
        The evaluator used (holds the form-factor rows of black target patches).
    rows : list of str
        Per target, what the rows are: ``"patches"`` (one per target patch),
        ``"mean"`` (one row, the area-weighted mean; weight [1]) or ``"none"``
        (no rows: a target without goals). The forward method always gives
        ``"patches"``; the adjoint method only what the goals need.
    method : {"forward", "adjoint"}
    """

    matrix: list
    offset: list
    weight: list
    evaluations: int
    seconds: float
    quantities: "Quantities"
    rows: list = None
    method: str = "forward"

    def __post_init__(self) -> None:
        if self.rows is None:
            self.rows = ["patches"] * len(self.matrix)

    @property
    def complete(self) -> bool:
        """True when every target patch has its row (the report's min/max come from them)."""
        return all(r == "patches" for r in self.rows)

    def values(self, s: np.ndarray) -> list:
        """Per-target (p_t,) quantities at intensities ``s``."""
        return [a + M @ s for M, a in zip(self.matrix, self.offset)]


def emitter_exitance(spec: DesignSpec, scene, emitters: range | None = None) -> np.ndarray:
    """(n, 3, m) float: exitance of each emitter (or of ``emitters`` only) at unit intensity, W/m^2."""
    emitters = range(len(spec.emitters)) if emitters is None else emitters
    E = np.zeros((scene.n_patches, 3, len(emitters)))
    for col, j in enumerate(emitters):
        E[spec.emitters[j].patches, :, col] = spec.emitters[j].color
    return E


def background_exitance(spec: DesignSpec, scene) -> np.ndarray:
    """(n, 3) float: the scene's emission on patches no emitter selects (zero for ``background: none``)."""
    E = np.zeros((scene.n_patches, 3))
    if spec.background == "scene":
        E[:] = scene.emission
        for e in spec.emitters:
            E[e.patches] = 0.0
    return E


def design_exitance(spec: DesignSpec, scene, intensity) -> np.ndarray:
    """(n, 3) float: the emission of a design, background plus ``intensity[e] * color[e]``."""
    E = background_exitance(spec, scene)
    for e, s in zip(spec.emitters, np.asarray(intensity, float)):
        E[e.patches] += s * e.color
    return E


class Quantities:
    """Evaluates target quantities from radiosity (see module docstring).

    Parameters
    ----------
    fac : HFactorization
    patches : (p,) int
        Patches whose irradiance will be asked for. The exact form-factor rows
        of those with zero reflectance in some channel are computed here, once.
    """

    def __init__(self, fac, patches) -> None:
        self.reflectance = np.asarray(fac.reflectance, dtype=np.float64)
        rows = np.unique(np.asarray(patches, dtype=np.int64))
        black = rows[(self.reflectance[rows] <= 0).any(axis=1)]
        self._row_of = {int(i): r for r, i in enumerate(black)}
        self.F_rows = np.zeros((0, fac.n_patches))
        self.form_factor_seconds = 0.0
        if black.size:
            t0 = time.perf_counter()
            samples = (fac.params or {}).get("samples") or DEFAULT_SAMPLES
            engine = FormFactorEngine(fac.scene, samples=samples)
            try:
                self.F_rows = engine.block(black, np.arange(fac.n_patches))
            finally:
                engine.close()
            self.form_factor_seconds = time.perf_counter() - t0

    @classmethod
    def for_targets(cls, fac, targets: tuple[Target, ...]) -> "Quantities":
        need = [t.patches for t in targets if t.quantity != "radiosity"]
        return cls(fac, np.concatenate(need) if need else np.zeros(0, np.int64))

    def form_factor_row(self, i: int) -> np.ndarray:
        """(n,) exact F[i, :] of a target patch with zero reflectance in some channel."""
        return self.F_rows[self._row_of[int(i)]]

    @property
    def black_patches(self) -> int:
        """Number of patches whose irradiance comes from form-factor rows (rho_c = 0)."""
        return len(self._row_of)

    def irradiance(self, P: np.ndarray, B: np.ndarray, E: np.ndarray) -> np.ndarray:
        """(p, 3, m) irradiance H of patches ``P`` (W/m^2) for radiosity ``B`` and exitance ``E``, (n, 3, m)."""
        rho = self.reflectance[P][:, :, None]
        H = np.divide(B[P] - E[P], rho, out=np.zeros(B[P].shape), where=rho > 0)   # H = (B - E) / rho
        black = np.flatnonzero((self.reflectance[P] <= 0).any(axis=1))
        if black.size:
            F = np.array([self.form_factor_row(i) for i in P[black]])
            H[black] = np.einsum("rn,ncm->rcm", F, B)                              # H = F B, by definition
        return H

    def __call__(self, target: Target, B: np.ndarray, E: np.ndarray) -> np.ndarray:
        """(p_t, m) quantity of ``target`` for radiosity ``B`` and exitance ``E``, both (n, 3, m)."""
        if target.quantity == "radiosity":
            return photometric(np.moveaxis(B[target.patches], 1, 2))
        H = self.irradiance(target.patches, B, E)
        return photometric(np.moveaxis(H, 1, 2), _UNITS[target.quantity])


def irradiance_field(fac, radiosity: np.ndarray, exitance: np.ndarray) -> np.ndarray:
    """(n, 3) irradiance H of every patch, W/m^2, from a solve's radiosity and its exitance (n, 3).

    ``(B - E) / rho``, and ``F B`` from exact form-factor rows where rho = 0
    (see the module docstring); e.g. for a false-colour picture of illuminance.
    """
    everything = np.arange(fac.n_patches)
    B = np.asarray(radiosity, np.float64)[:, :, None]
    E = np.asarray(exitance, np.float64)[:, :, None]
    return Quantities(fac, everything).irradiance(everything, B, E)[:, :, 0]


def response(fac, spec: DesignSpec, *, progress: ProgressCallback = None,
             batch_bytes: int = BATCH_BYTES) -> Response:
    """The affine map from intensities to every target quantity (batched solves).

    Parameters
    ----------
    fac : HFactorization
        With its scene (``fac.scene``), e.g. from :func:`hfrad.load`.
    spec : DesignSpec
    progress : callable (done, total), optional
        Right-hand sides solved so far, of m (+1 for a background).
    batch_bytes : int
        Memory for one batch of right-hand sides and their radiosities
        (float64); more emitters are solved in several batches.

    Returns
    -------
    Response

    Notes
    -----
    m = len(spec.emitters) right-hand sides, plus one for a non-zero
    background: O((m + 1) n k), in batches of ``fac.solve``. Never forms
    ``(I - RF)^-1``. Memory: the batch, plus (target patches) x m quantities.
    """
    t0 = time.perf_counter()
    scene = fac.scene
    n, m = scene.n_patches, len(spec.emitters)
    E0 = background_exitance(spec, scene)
    with_background = bool(E0.any())
    columns = m + int(with_background)
    chunk = max(1, int(batch_bytes // (2 * n * 3 * 8)))      # E and B of one batch, float64
    quantities = Quantities.for_targets(fac, spec.targets)
    q_all = [np.empty((len(t.patches), columns)) for t in spec.targets]
    for start in range(0, columns, chunk):
        stop = min(columns, start + chunk)
        batch = emitter_exitance(spec, scene, range(start, min(stop, m)))
        if stop > m:                                          # the background is the last column
            batch = np.concatenate([batch, E0[:, :, None]], axis=2)
        B = np.asarray(fac.solve(batch), dtype=np.float64)
        for q, t in zip(q_all, spec.targets):
            q[:, start:stop] = quantities(t, B, batch)
        report(progress, stop, columns)
    matrix = [q[:, :m] for q in q_all]
    offset = [q[:, m] if with_background else np.zeros(len(q)) for q in q_all]
    weight = [scene.areas[t.patches] / scene.areas[t.patches].sum() for t in spec.targets]
    return Response(matrix, offset, weight, columns, time.perf_counter() - t0, quantities)


# -- the adjoint method ---------------------------------------------------------------------------
def adjoint_rows(spec: DesignSpec) -> list[str]:
    """Per target, the rows the goals need: every patch (min, max, uniformity), the mean only, or none."""
    return ["patches" if (t.min, t.max, t.uniformity) != (None, None, None)
            else "mean" if t.mean is not None else "none" for t in spec.targets]


def adjoint_solves(spec: DesignSpec) -> int:
    """Right-hand sides of the adjoint method (one per row the goals need)."""
    return sum(len(t.patches) if r == "patches" else int(r == "mean")
               for t, r in zip(spec.targets, adjoint_rows(spec)))


def _solve_adjoint(fac, g: np.ndarray) -> np.ndarray:
    """``(I - R_c F)^T x = g`` per channel, by whichever spelling this factorization's solve takes."""
    import inspect
    if "trans" in inspect.signature(fac.solve).parameters:
        return fac.solve(g, trans="T")
    return fac.solve(g, trans="T")


def adjoint_response(fac, spec: DesignSpec, *, progress: ProgressCallback = None,
                     batch_bytes: int = BATCH_BYTES) -> Response:
    """The rows of the affine map that the goals need, by adjoint (transposed) solves.

    A target quantity is a linear read-out of the radiosity, ``q_r = sum_c g_rc . B_c
    (+ d_rc . E_c)``, and ``B_c = A_c^{-1} E_c`` with ``A_c = I - R_c F``, so
    ``q_r = sum_c (A_c^{-T} g_rc + d_rc) . E_c``: one transposed solve per row r
    gives that row's response to *every* emitter at once. Cheaper than the
    forward method when the goals need fewer rows than there are emitters (many
    emitters, few target patches or only means). The read-outs g, d:

    - radiosity of patch i: ``g = W_c e_i`` (W: luminance weights, x 683 for lux);
    - irradiance, rho_ic > 0: ``H = (B - E) / rho``, so ``g = W_c e_i / rho_ic``, ``d = -g``;
    - irradiance, rho_ic = 0: ``H = F[i] B``, so ``g = W_c F[i]`` (exact form-factor row);
    - a mean: the area-weighted sum of its patches' read-outs.

    Returns
    -------
    Response
        With ``rows`` from :func:`adjoint_rows` and ``method='adjoint'``.
    """
    t0 = time.perf_counter()
    scene = fac.scene
    n, m = scene.n_patches, len(spec.emitters)
    kinds = adjoint_rows(spec)
    quantities = Quantities.for_targets(fac, spec.targets)
    rho = quantities.reflectance
    E0 = background_exitance(spec, scene)
    # every row as (target, patches, weights)
    rows = []
    for j, (t, kind) in enumerate(zip(spec.targets, kinds)):
        w = scene.areas[t.patches] / scene.areas[t.patches].sum()
        if kind == "patches":
            rows += [(j, t.patches[k:k + 1], np.ones(1)) for k in range(len(t.patches))]
        elif kind == "mean":
            rows.append((j, t.patches, w))
    R = len(rows)
    out = np.empty((R, m))
    base = np.empty(R)
    chunk = max(1, int(batch_bytes // (2 * n * 3 * 8)))
    for start in range(0, R, chunk):
        part = rows[start:start + chunk]
        g = np.zeros((n, 3, len(part)))
        d = np.zeros((n, 3, len(part)))
        for col, (j, P, w) in enumerate(part):
            t = spec.targets[j]
            W = photometric(np.eye(3), _UNITS[t.quantity])                     # (3,) luminance weights x units
            if t.quantity == "radiosity":
                g[P, :, col] += w[:, None] * W
                continue
            black = (rho[P] <= 0).any(axis=1)
            lit = ~black
            coef = np.divide(W, rho[P[lit]], out=np.zeros((int(lit.sum()), 3)), where=rho[P[lit]] > 0)
            g[P[lit], :, col] += w[lit, None] * coef                            # H = (B - E) / rho
            d[P[lit], :, col] -= w[lit, None] * coef
            for i, wi in zip(P[black], w[black]):
                g[:, :, col] += wi * np.outer(quantities.form_factor_row(i), W)   # H = F B
        X = np.asarray(_solve_adjoint(fac, g), dtype=np.float64) + d               # q_r = sum X_r * E
        for e_index, e in enumerate(spec.emitters):
            out[start:start + len(part), e_index] = e.color @ X[e.patches].sum(axis=0)
        base[start:start + len(part)] = np.einsum("nc,ncr->r", E0, X)
        report(progress, start + len(part), R)
    matrix, offset, weight, k = [], [], [], 0
    for t, kind in zip(spec.targets, kinds):
        count = len(t.patches) if kind == "patches" else int(kind == "mean")
        matrix.append(out[k:k + count])
        offset.append(base[k:k + count])
        weight.append(scene.areas[t.patches] / scene.areas[t.patches].sum() if kind == "patches" else np.ones(count))
        k += count
    return Response(matrix, offset, weight, R, time.perf_counter() - t0, quantities, kinds, "adjoint")
