"""Luminaires in a factorized scene: precompute once, relight any dimming in O(m L).

For L luminaires (dimming w_l) the light arriving at patch i directly is
``H_i = sum_l w_l H_direct,il`` (lux, :mod:`hfrad.lighting.direct`); its first
reflection is the exitance

    E_l = rho * H_direct,l * colour_l / 683 lm/W         (n, 3) W/m^2 per luminaire

and the interreflected radiosity ``B_l = (I - R F)^{-1} E_l`` (eq. 4), the L
columns in one batched ``fac.solve`` (O(n k L), once). Light is linear in the
dimming, so any dimming is ``B(w) = sum_l w_l B_l (+ B_0)``, ``B_0`` the scene's
own emission when ``background="scene"``. At sensors (a :class:`SensorSet`)
the illuminance is the direct light plus the gathered radiosity
(:mod:`hfrad.lighting.gather`)::

    E_v(w) = sum_l w_l (D_l + 683 Y(G B_l)) + 683 Y(G B_0) = R w + r_0    (lux)

``R`` (m, L) is stored, so a relighting is one (m, L) product. 683 lm/W and
the Rec. 709 luminance Y are the conversion of ``hfrad render --unit lux``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..progress import ProgressCallback, report
from ..render.falsecolor import LUMINOUS_EFFICACY, photometric
from .direct import NEAR_RATIO, SPACING, caster_for, direct_illuminance, patch_direct_illuminance
from .gather import GatherOperator, gather_operator
from .limits import check_area_points, check_lighting_size
from .sensors import SensorSet

__all__ = ["LightingModel", "SensorResponse"]

BACKGROUNDS = ("none", "scene")


@dataclass
class SensorResponse:
    """``lux(w) = matrix @ w + offset`` at one set of sensors.

    Attributes
    ----------
    sensors : SensorSet
    matrix : (m, L) float, lux per unit dimming (direct + indirect)
    direct : (m, L) float, lux per unit dimming (direct only)
    offset : (m,) float, lux from the scene's own emission (0 unless background="scene")
    gather : GatherOperator
    seconds : dict
    """

    sensors: SensorSet
    matrix: np.ndarray
    direct: np.ndarray
    offset: np.ndarray
    gather: GatherOperator = field(repr=False)
    seconds: dict = field(default_factory=dict)

    def illuminance(self, dimming) -> np.ndarray:
        """(m,) lux for ``dimming`` (L,): one (m, L) product."""
        return self.matrix @ np.asarray(dimming, np.float64) + self.offset


class LightingModel:
    """Catalogue luminaires in a factorized scene (module docstring).

    Parameters
    ----------
    fac : HFactorization
        With its scene (``hfrad.load("room.hfr")`` or ``hfrad.factorize(scene)``).
    luminaires : sequence of Luminaire
    background : {"none", "scene"}
        ``none``: only the luminaires light the scene; ``scene``: the scene's
        own emitting patches (area lights, daylit windows) add a fixed part.
    samples : int
        Sample points per patch edge for the direct light on patches.
    spacing, near_ratio : float
        Area-source sampling of large luminaires (:mod:`hfrad.lighting.direct`).
    progress : callable (done, total), optional
        Luminaires done.

    Attributes
    ----------
    patch_direct : (n, L) float, lux per unit dimming on every patch
    radiosity_basis : (n, 3, L) float, W/m^2 per unit dimming
    exitance_basis : (n, 3, L) float, W/m^2 per unit dimming: the luminaires' light reflected once
    background_radiosity, background_exitance : (n, 3) float, W/m^2
    timings : dict
    """

    def __init__(self, fac, luminaires, *, background: str = "none", samples: int = 3, spacing: float = SPACING,
                 near_ratio: float = NEAR_RATIO, progress: ProgressCallback = None) -> None:
        if fac.scene is None:
            raise InputError("the factorization carries no scene; load it from an .hfr file or build it "
                             "with hfrad.factorize(scene)")
        if background not in BACKGROUNDS:
            raise InputError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")
        self.luminaires = list(luminaires)
        if not self.luminaires and background == "none":
            raise InputError("no luminaires and background 'none': nothing lights the scene")
        check_lighting_size(fac.scene.n_patches, len(self.luminaires), [])
        for lum in self.luminaires:                      # before any ray: an opening too large for its points
            check_area_points(lum.name, *lum.photometry.size[:2], spacing)
        self.fac = fac
        self.scene = fac.scene
        self.background = background
        self.spacing, self.near_ratio = float(spacing), float(near_ratio)
        self.timings: dict = {}
        t0 = time.perf_counter()
        self.caster = caster_for(self.scene)
        self.patch_direct = (patch_direct_illuminance(self.scene, self.luminaires, samples=samples,
                                                      caster=self.caster, spacing=spacing,
                                                      near_ratio=near_ratio, progress=progress)
                             if self.luminaires else np.zeros((self.scene.n_patches, 0)))
        self.timings["direct_patches_s"] = time.perf_counter() - t0
        self._solve(fac)

    def _solve(self, fac) -> None:
        t0 = time.perf_counter()
        rho = np.asarray(fac.reflectance, np.float64)
        L = len(self.luminaires)
        colours = np.array([lum.color for lum in self.luminaires]).reshape(L, 3)
        E = rho[:, :, None] * (self.patch_direct / LUMINOUS_EFFICACY)[:, None, :] * colours.T[None, :, :]
        E0 = np.asarray(self.scene.emission, np.float64) if self.background == "scene" else None
        if E0 is not None and E0.any():
            E = np.concatenate([E, E0[:, :, None]], axis=2)
        B = np.asarray(fac.solve(E), np.float64) if E.shape[2] else np.zeros_like(E)
        self.exitance_basis = E[:, :, :L]
        self.background_exitance = E[:, :, L] if E.shape[2] > L else np.zeros((self.scene.n_patches, 3))
        self.radiosity_basis = B[:, :, :L]
        self.background_radiosity = B[:, :, L] if B.shape[2] > L else np.zeros((self.scene.n_patches, 3))
        self.timings["solve_s"] = time.perf_counter() - t0
        self.timings["right_hand_sides"] = int(E.shape[2])

    def with_reflectance(self, reflectance) -> "LightingModel":
        """The same luminaires with new reflectances: the direct light is kept, the L columns re-solved.

        Uses ``fac.with_reflectance`` (no refactorization; reflectance <=
        the factorization's rho_max). Sensor responses must be taken again
        (:meth:`sensors`; their gather operators can be passed back in).
        """
        new = object.__new__(LightingModel)
        new.__dict__.update(self.__dict__)
        new.fac = self.fac.with_reflectance(reflectance)
        new.timings = dict(self.timings)
        new._solve(new.fac)
        return new

    @property
    def dimming(self) -> np.ndarray:
        """(L,) the layout's dimming of each luminaire."""
        return np.array([lum.dimming for lum in self.luminaires])

    def radiosity(self, dimming=None) -> np.ndarray:
        """(n, 3) W/m^2 of every patch for ``dimming`` (L,) (default: the layout's): O(n L)."""
        w = self.dimming if dimming is None else self._check(dimming)
        return self.radiosity_basis @ w + self.background_radiosity

    def radiosity_error(self, dimming=None):
        """The error figure of :meth:`radiosity` (a :class:`~hfrad.solve.samples.SolutionError`, per channel,
        relative to the reflected light): :meth:`HFactorization.solution_error` of the lighting's
        exitance (the luminaires' first bounce off the patches) and radiosity, O(n m) for m stored rows."""
        w = self.dimming if dimming is None else self._check(dimming)
        E = self.exitance_basis @ w + self.background_exitance
        return self.fac.solution_error(E, self.radiosity(w))

    def illuminance_error(self, response: "SensorResponse", error) -> np.ndarray:
        """(m,) lux: the figure of the interreflected light's error at each sensor.

        ``error`` is the lighting state's :meth:`radiosity_error` (computed once for all grids).
        The gathered irradiance is ``G B``; its error ``G e`` at sensor s is at most
        ``||g_s||_{1/A} ||e||_A`` per channel (Cauchy-Schwarz in the area norm the radiosity
        figure bounds), weighted to lux as the illuminance is. The direct light is computed
        by rays, not by the factorization, and has no part in it.
        """
        areas = np.asarray(self.scene.areas, np.float64)
        g = response.gather.matrix.astype(np.float64)
        spread = np.sqrt((g ** 2 / areas[None, :]).sum(axis=1))            # ||g_s||_{1/A}, (m,)
        per_channel = spread[:, None] * np.asarray(error.absolute, np.float64)[None, :]   # (m, 3) W/m^2
        return photometric(per_channel, "lux")

    def _check(self, dimming) -> np.ndarray:
        w = np.asarray(dimming, np.float64).reshape(-1)
        if w.shape != (len(self.luminaires),) or not np.isfinite(w).all() or (w < 0).any():
            raise InputError(f"dimming must be {len(self.luminaires)} finite numbers >= 0, got shape {w.shape}")
        return w

    def sensors(self, sensors: SensorSet, *, samples: int = 2, gather: GatherOperator | None = None,
                progress: ProgressCallback = None) -> SensorResponse:
        """The response of ``sensors`` to every luminaire (and the background): the stored gather.

        Cost: the direct light (one ray per sensor, luminaire and area-source
        point) and the gather operator (:func:`gather_operator`; skipped when
        ``gather`` is given), once; then ``R = D + 683 Y(G B_l)``.
        """
        check_lighting_size(self.scene.n_patches, len(self.luminaires), [len(sensors)])
        t0 = time.perf_counter()
        D = direct_illuminance(self.luminaires, sensors.points, sensors.normals, caster=self.caster,
                               spacing=self.spacing, near_ratio=self.near_ratio) \
            if self.luminaires else np.zeros((len(sensors), 0))
        t1 = time.perf_counter()
        if gather is None:
            gather = gather_operator(self.scene, sensors.points, sensors.normals, samples=samples,
                                     caster=self.caster, progress=progress)
        elif gather.shape != (len(sensors), self.scene.n_patches):
            raise InputError(f"gather operator has shape {gather.shape}, expected ({len(sensors)}, "
                             f"{self.scene.n_patches})")
        t2 = time.perf_counter()
        GB = gather.apply(self.radiosity_basis)                          # (m, 3, L) W/m^2
        indirect = photometric(np.moveaxis(GB, 1, 2), "lux")              # (m, L)
        offset = photometric(gather.apply(self.background_radiosity), "lux")
        report(progress, len(sensors), len(sensors))
        return SensorResponse(sensors, D + indirect, D, offset, gather,
                              {"direct_s": t1 - t0, "gather_s": t2 - t1,
                               "response_s": time.perf_counter() - t2})
