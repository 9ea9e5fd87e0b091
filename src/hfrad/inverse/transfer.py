"""Target quantities as affine functions of the emitter intensities, through the factorization.

Radiosity is linear in the emission, so with ``E(s) = E_0 + sum_e s_e E_e``
(``E_0`` the fixed background, ``E_e`` emitter e at unit intensity) every
target quantity is ``q(s) = q_0 + M s``. The columns of ``M`` come from one
batched solve ``fac.solve([E_1 ... E_m])`` (m right-hand sides, O(m n k); no
dense inverse, no form-factor matrix).

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
    """

    matrix: list
    offset: list
    weight: list
    evaluations: int
    seconds: float
    quantities: "Quantities"

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
            rows = [self._row_of[int(i)] for i in P[black]]
            H[black] = np.einsum("rn,ncm->rcm", self.F_rows[rows], B)              # H = F B, by definition
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
