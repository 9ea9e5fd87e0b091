"""Rays to the sky through windows: glazing transmits, every other surface blocks.

A ray from a point toward a sky direction reaches the sky when every face it
crosses is glazing (a material with a transmittance, docs/buildings.md); its
light is then multiplied by each pane's transmittance at the ray's angle of
incidence. Opaque surfaces stay Lambertian and block. Panes are plain clear
glass: the angular factor ``tau(theta) / tau(0)`` of a single uncoated pane of
refractive index 1.52 (Fresnel reflection at both faces, multiple reflections
and absorption along the refracted path, the absorption chosen so that the
normal-incidence value is the material's own), which is 1 at normal
incidence and falls to 0 at grazing.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..formfactors.raycast import RayCaster

__all__ = ["GlazingTracer", "angular_factor", "MAX_PANES"]

#: panes a ray may cross before it is counted as blocked (double glazing modelled as two faces is 2)
MAX_PANES = 6
_N_GLASS = 1.52
_COS_TABLE = np.linspace(0.0, 1.0, 4097)


def _pane(cos_i: np.ndarray, absorb: float) -> np.ndarray:
    """Transmittance of one pane at incidence cosine ``cos_i``, absorption ``exp(-absorb / cos_t)``."""
    cos_i = np.clip(cos_i, 1e-9, 1.0)
    sin_t = np.sqrt(1 - cos_i ** 2) / _N_GLASS
    cos_t = np.sqrt(1 - sin_t ** 2)
    rs = ((cos_i - _N_GLASS * cos_t) / (cos_i + _N_GLASS * cos_t)) ** 2
    rp = ((_N_GLASS * cos_i - cos_t) / (_N_GLASS * cos_i + cos_t)) ** 2
    a = np.exp(-absorb / cos_t)
    return 0.5 * sum((1 - r) ** 2 * a / (1 - (r * a) ** 2) for r in (rs, rp))


@lru_cache(maxsize=64)
def _absorption(tau_normal: float) -> float:
    """The absorption ``a`` (``exp(-a / cos_t)`` along the refracted path) whose pane transmits ``tau_normal``
    at normal incidence (bisection; above the clear pane's 0.92 no absorption is left)."""
    lo, hi = 0.0, 5.0
    target = min(float(tau_normal), float(_pane(np.ones(1), 0.0)[0]))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _pane(np.ones(1), mid)[0] > target else (lo, mid)
    return 0.5 * (lo + hi)


def angular_factor(cos_incidence: np.ndarray, tau_normal: float = 0.88) -> np.ndarray:
    """``tau(theta) / tau(0)`` of a clear pane whose normal-incidence transmittance is ``tau_normal``.

    Parameters
    ----------
    cos_incidence : (...) float, |cosine| of the angle between the ray and the pane's normal
    tau_normal : float in (0, 0.92]: the pane at normal incidence (above the clear pane's 0.92 no absorption is left)
    """
    absorb = _absorption(float(tau_normal))
    return _pane(np.abs(np.asarray(cos_incidence, float)), absorb) / _pane(np.ones(1), absorb)[0]


class GlazingTracer:
    """Transmittance along rays through a scene's glazing.

    Two Embree scenes answer it: the opaque faces (one occlusion query per ray, in
    packets: is anything opaque in the way?) and the panes alone (first hits, followed
    from pane to pane only for the rays nothing opaque blocks). ``caster`` is the
    whole scene, for callers that need every face (the gather operator).

    Parameters
    ----------
    scene : Scene
    angular : bool
        Apply :func:`angular_factor` (default); False: each pane's normal-incidence transmittance at every angle.
    threads : int, optional
        Embree threads per batch (default: the cores this process may use).
    """

    def __init__(self, scene, *, angular: bool = True, threads: int | None = None) -> None:
        tri = np.asarray(scene.triangles, np.float64)
        faces = np.asarray(scene.faces)
        self.caster = RayCaster(scene.vertices, faces, threads=threads)
        mat = np.asarray(scene.material)[np.asarray(scene.patch_of_triangle)]
        tau = np.array([m.transmittance for m in scene.materials], np.float64).reshape(-1, 3)
        self.tau = tau[mat]                                                  # (t, 3)
        self.glazing = self.tau.max(axis=1) > 0
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        self.angular = angular
        # per glazing material: angular_factor tabulated once over |cos| (smooth: linear interpolation
        # on 4,097 points is within 1e-6 of it)
        self._table = {i: angular_factor(_COS_TABLE, max(m.transmittance)) for i, m in enumerate(scene.materials)
                       if max(m.transmittance) > 0}
        self.material = mat
        size = float(np.ptp(scene.bounds, axis=0).max()) if len(tri) else 1.0
        self.eps = 1e-5 * max(size, 1e-3)
        opaque = ~self.glazing
        self._opaque = RayCaster(scene.vertices, faces[opaque], threads=threads) if opaque.any() else None
        self._pane_face = np.flatnonzero(self.glazing)                      # pane caster's face -> scene triangle
        self._panes = RayCaster(scene.vertices, faces[self.glazing], threads=threads) if self.glazing.any() else None

    @property
    def has_glazing(self) -> bool:
        return bool(self.glazing.any())

    def _pane_transmittance(self, f: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(r, 3): triangles ``f``'s transmittance for rays of directions ``d`` (r, 3)."""
        t = self.tau[f]
        if self.angular:
            cos_i = np.clip(np.abs(np.einsum("rd,rd->r", self.normals[f], d)), 0.0, 1.0)
            mat = self.material[f]
            for mi, table in self._table.items():
                sel = mat == mi
                if sel.any():
                    t[sel] *= np.interp(cos_i[sel], _COS_TABLE, table)[:, None]
        return t

    def transmittance(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(r, 3) float: the light of each ray's sky direction that reaches its origin (0: blocked).

        A ray reaches the sky when no opaque face lies along it; it then carries the
        product of the transmittances of the panes it crosses (0 past :data:`MAX_PANES`).

        Parameters
        ----------
        origins : (r, 3) float, on or off a surface (offset along the ray here)
        directions : (r, 3) float, unit vectors toward the sky
        """
        d = np.ascontiguousarray(directions, np.float64)
        o = np.asarray(origins, np.float64) + self.eps * d
        T = np.zeros((len(o), 3))
        if self._opaque is None:
            live = np.arange(len(o))
        else:
            live = np.flatnonzero(~self._opaque.occluded(o, d, np.full(len(o), np.inf)))
        T[live] = 1.0
        if self._panes is None:
            return T
        o, d = o[live], d[live]
        for _ in range(MAX_PANES + 1):
            if not len(live):
                break
            face, dist, _ = self._panes.intersect(o, d)
            hit = face >= 0
            live, o, d, dist = live[hit], o[hit], d[hit], dist[hit]
            T[live] *= self._pane_transmittance(self._pane_face[face[hit]], d)
            o = o + (dist + self.eps)[:, None] * d
        T[live] = 0.0          # still crossing panes after MAX_PANES: counted as blocked
        return T
