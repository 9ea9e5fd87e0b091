"""A daylit scene over a year: precompute the daylight coefficients once, then the year is small products.

For m sensors and h hours::

    E(m, h) = sum_c Y_c [ (D + G B)_c @ sky_c  +  (G B)_c @ sun_c ]  +  S(m, h)      (lux)

``sky`` and ``sun`` the matrices of :func:`sky_matrices` (P, 3, h), ``D`` the
sensors' first-hit coefficients, ``G B`` the interreflected ones
(:mod:`.coefficients`), and ``S`` the direct sun: per hour, the direct-normal
illuminance ``sum_p Y . sun_p Omega_p`` along the sun's own direction
(pvlib), one ray per sensor through the glazing. The sun's interreflected
light goes through the patches it was spread over (the sky-patch
coefficients, as Radiance's two-phase method does for all of it); its direct
light never does, so ASE (direct sun only, ``S``) is exact to the ray.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..lighting import SensorSet, gather_operator
from ..progress import ProgressCallback, report
from .coefficients import first_hit, patch_first_hit
from .glazing import GlazingTracer
from .sky import RADIANCE_LUMINANCE, SkyPatches, direction, sky_matrices
from .weather import Weather

__all__ = ["DaylightModel", "DaylightCoefficients", "AnnualResult"]


@dataclass
class DaylightCoefficients:
    """The response of a sensor set to each sky patch.

    Attributes
    ----------
    sensors : SensorSet
    direct : (m, 3, P) float, sr: first-hit irradiance per unit patch radiance
    indirect : (m, 3, P) float, sr: interreflected irradiance per unit patch radiance
    gather : GatherOperator (kept for a change of reflectance)
    """

    sensors: SensorSet
    direct: np.ndarray
    indirect: np.ndarray
    gather: object = field(repr=False)

    def relit(self, model: "DaylightModel") -> "DaylightCoefficients":
        """The same sensors in ``model`` (e.g. ``model.with_reflectance(...)``): first hits and gather kept,
        the interreflected part taken again, ``G B`` (O(m n P), no ray)."""
        return DaylightCoefficients(self.sensors, self.direct, self.gather.apply(model.radiosity_basis), self.gather)

    def illuminance(self, sky: np.ndarray, sun: np.ndarray | None = None) -> np.ndarray:
        """(m, h) lux of sky matrix ``sky`` (P, 3, h) (and the sun's interreflected light from ``sun``).

        One (m, 6P) x (6P, h) product in float32 (the three colours and both matrices side by side).
        """
        Y = RADIANCE_LUMINANCE[None, :, None]
        left = [((self.direct + self.indirect) * Y).reshape(len(self.direct), -1)]
        right = [np.asarray(sky, np.float32).transpose(1, 0, 2).reshape(-1, sky.shape[2])]
        if sun is not None:
            left.append((self.indirect * Y).reshape(len(self.direct), -1))
            right.append(np.asarray(sun, np.float32).transpose(1, 0, 2).reshape(-1, sun.shape[2]))
        return np.hstack(left).astype(np.float32) @ np.vstack(right)


@dataclass
class AnnualResult:
    """A year at a sensor set.

    Attributes
    ----------
    sensors : SensorSet
    weather : Weather
    illuminance : (m, h) float32, lux: total (sky, sun, interreflections)
    direct_sun : (m, h) float32, lux: the sun's direct light only (for ASE)
    timings : dict, seconds
    """

    sensors: SensorSet
    weather: Weather
    illuminance: np.ndarray
    direct_sun: np.ndarray
    timings: dict = field(default_factory=dict)


class DaylightModel:
    """Sky patches in a factorized scene with windows (module docstring).

    Parameters
    ----------
    fac : HFactorization, with its scene
    mf : {1, 2, 4}
        Reinhart subdivision.
    north : float, degrees
        North is ``-z`` turned this much toward ``+x`` (:func:`direction`).
    angular : bool
        Angle dependence of plain glass (:func:`angular_factor`).
    samples : int
        Sample points per patch edge for the patches' first hit.
    rays : int
        ``rays x rays`` directions per sky patch from each patch sample point.
    sensor_rays : int
        ``sensor_rays^2`` directions per sky patch from each sensor, and ``(sensor_rays refine)^2``
        where a window's edge crosses the patch (:func:`first_hit`: a sensor sees a window's edge
        sharply, a patch's light is averaged again by the gather). ``rays`` and ``sensor_rays`` are
        per MF:1 patch: at MF:2 and 4 they are divided by MF (rounded up).
    refine : int
        See ``sensor_rays``; 1: no refinement. The default 4 x 4 refined 4 times keeps a work-plane
        sensor's annual first-hit light within 1% of 64 x 64 rays (benchmarks/README.md).
    progress : callable (done, total), optional
        Sky patches done (first hits of the scene's patches).
    """

    def __init__(self, fac, *, mf: int = 1, north: float = 0.0, angular: bool = True, samples: int = 2,
                 rays: int = 3, sensor_rays: int = 4, refine: int = 4, progress: ProgressCallback = None) -> None:
        if fac.scene is None:
            raise InputError("the factorization carries no scene; load it from an .hfr file or build it "
                             "with hfrad.factorize(scene)")
        for name, v in (("samples", samples), ("rays", rays), ("sensor_rays", sensor_rays), ("refine", refine)):
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name} must be an integer >= 1, got {v!r}")
        if not np.isfinite(north):
            raise InputError(f"north must be a finite angle in degrees, got {north!r}")
        self.fac, self.scene = fac, fac.scene
        self.patches = SkyPatches(mf)
        # a finer sky (MF:2, 4) splits each patch m x m: fewer rays per patch keep the rays per steradian
        self.north, self.samples, self.refine = float(north), int(samples), int(refine)
        self.rays, self.sensor_rays = (max(1, -(-int(r) // mf)) for r in (rays, sensor_rays))
        self.timings: dict = {}
        t0 = time.perf_counter()
        self.tracer = GlazingTracer(self.scene, angular=angular)
        self.patch_first_hit = patch_first_hit(self.scene, self.tracer, self.patches, samples=samples, k=self.rays,
                                               north=north, progress=progress)
        self.timings["first_hit_patches_s"] = time.perf_counter() - t0
        self._solve()

    def _solve(self) -> None:
        t0 = time.perf_counter()
        rho = np.asarray(self.fac.reflectance, np.float64)
        E = rho[:, :, None] * self.patch_first_hit                      # (n, 3, P): first reflection
        self.radiosity_basis = np.asarray(self.fac.solve(E), np.float64)
        self.timings["solve_s"] = time.perf_counter() - t0

    def with_reflectance(self, reflectance) -> "DaylightModel":
        """The same sky with new reflectances: first hits kept, the P columns solved again (no new form factors).

        ``fac.with_reflectance`` (reflectance <= the factorization's rho_max). Take the sensors'
        coefficients again with :meth:`sensors`, passing their gather operator back in.
        """
        new = object.__new__(DaylightModel)
        new.__dict__.update(self.__dict__)
        new.fac = self.fac.with_reflectance(reflectance)
        new.timings = dict(self.timings)
        new._solve()
        return new

    def with_transmittance(self, material: str, transmittance, *, progress: ProgressCallback = None) -> "DaylightModel":
        """The same scene with glazing ``material``'s transmittance changed: new rays, no new form factors.

        The patches' first hits are traced again through the new glazing and the P columns solved
        with the same factorization; take the sensors' coefficients again with :meth:`sensors`
        (passing their gather operator back in) and the direct sun with :meth:`direct_sun`.

        Raises
        ------
        InputError
            No such material, or a transmittance outside [0, 1 - reflectance].
        """
        from dataclasses import replace as _replace

        if material not in self.scene.material_names:
            raise InputError(f"material {material!r} is not in the scene; its materials are: "
                             + ", ".join(self.scene.material_names))
        tau = np.broadcast_to(np.asarray(transmittance, np.float64), (3,))
        i = self.scene.material_names.index(material)
        mats = list(self.scene.materials)
        mats[i] = _replace(mats[i], transmittance=tuple(float(t) for t in tau))
        scene = self.scene.replace(materials=tuple(mats))       # checks 0 <= tau, rho + tau <= 1
        new = object.__new__(DaylightModel)
        new.__dict__.update(self.__dict__)
        new.scene, new.timings = scene, dict(self.timings)
        t0 = time.perf_counter()
        new.tracer = GlazingTracer(scene, angular=self.tracer.angular)
        new.patch_first_hit = patch_first_hit(scene, new.tracer, self.patches, samples=self.samples, k=self.rays,
                                              north=self.north, progress=progress)
        new.timings["first_hit_patches_s"] = time.perf_counter() - t0
        new._solve()
        return new

    def sensors(self, sensors: SensorSet, *, gather=None, progress: ProgressCallback = None) -> DaylightCoefficients:
        """Daylight coefficients of ``sensors``: first hits by rays, interreflections by the stored gather."""
        D = first_hit(self.tracer, self.patches, sensors.points, sensors.normals, k=self.sensor_rays,
                      refine=self.refine, north=self.north)
        if gather is None:
            gather = gather_operator(self.scene, sensors.points, sensors.normals, caster=self.tracer.caster,
                                     progress=progress)
        elif gather.shape != (len(sensors), self.scene.n_patches):
            raise InputError(f"gather operator has shape {gather.shape}, expected ({len(sensors)}, "
                             f"{self.scene.n_patches})")
        return DaylightCoefficients(sensors, D, gather.apply(self.radiosity_basis), gather)

    def direct_sun(self, sensors: SensorSet, weather: Weather, sun: np.ndarray,
                   progress: ProgressCallback = None) -> np.ndarray:
        """(m, h) float32, lux: the sun's direct light at each sensor and hour, one ray each through the glazing.

        ``sun`` is the sun-only matrix (P, 3, h); its per-hour sum ``sum_p sun_p Omega_p`` is
        the direct-normal irradiance (RGB), sent along the sun's direction from pvlib.
        """
        normal = np.einsum("pch,p->hc", sun, self.patches.solid_angle)           # (h, 3) W/m^2 visible
        alt, azi = weather.sun()
        hours = np.flatnonzero((alt > 0) & (normal.max(axis=1) > 0))
        dirs = direction(np.radians(alt[hours]), np.radians(azi[hours]), self.north)   # (s, 3)
        out = np.zeros((len(sensors), len(weather)), np.float32)
        Pt, N = sensors.points, sensors.normals
        step = max(1, (1 << 20) // max(1, len(Pt)))
        for start in range(0, len(hours), step):
            h = hours[start:start + step]
            d = dirs[start:start + step]
            cos = N @ d.T                                                         # (m, b)
            si, hi = np.nonzero(cos > 0)
            if len(si):
                T = self.tracer.transmittance(Pt[si], d[hi])
                out[si, h[hi]] = cos[si, hi] * ((T * normal[h[hi]]) @ RADIANCE_LUMINANCE)
            report(progress, min(len(hours), start + step), len(hours))
        return out

    def year(self, sensors: SensorSet, weather: Weather, *, ground: float = 0.2, coefficients=None,
             matrices=None, direct_sun=None, progress: ProgressCallback = None) -> AnnualResult:
        """The year at ``sensors``: :func:`sky_matrices`, the coefficients, the products, the direct sun.

        ``coefficients``, ``matrices`` (sky, sun) and ``direct_sun`` (m, h) are computed when not given;
        none depends on the reflectances except the coefficients' interreflected part, so a design loop
        passes the last result's ``direct_sun`` and ``coefficients.relit(new_model)``.
        """
        t0 = time.perf_counter()
        sky, sun = matrices if matrices is not None else sky_matrices(weather, self.patches.mf, ground=ground)
        t1 = time.perf_counter()
        dc = coefficients if coefficients is not None else self.sensors(sensors)
        t2 = time.perf_counter()
        S = direct_sun if direct_sun is not None else self.direct_sun(sensors, weather, sun, progress=progress)
        t3 = time.perf_counter()
        E = dc.illuminance(sky, sun).astype(np.float32) + S
        t4 = time.perf_counter()
        return AnnualResult(sensors, weather, E, S, {"sky_matrices_s": t1 - t0, "coefficients_s": t2 - t1,
                                                     "direct_sun_s": t3 - t2, "products_s": t4 - t3})
