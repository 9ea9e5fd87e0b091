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

import numpy as np

from ..formfactors.raycast import RayCaster

__all__ = ["GlazingTracer", "angular_factor", "MAX_PANES"]

#: panes a ray may cross before it is counted as blocked (double glazing modelled as two faces is 2)
MAX_PANES = 6
_N_GLASS = 1.52


def _pane(cos_i: np.ndarray, absorb: float) -> np.ndarray:
    """Transmittance of one pane at incidence cosine ``cos_i``, absorption ``exp(-absorb / cos_t)``."""
    cos_i = np.clip(cos_i, 1e-9, 1.0)
    sin_t = np.sqrt(1 - cos_i ** 2) / _N_GLASS
    cos_t = np.sqrt(1 - sin_t ** 2)
    rs = ((cos_i - _N_GLASS * cos_t) / (cos_i + _N_GLASS * cos_t)) ** 2
    rp = ((_N_GLASS * cos_i - cos_t) / (_N_GLASS * cos_i + cos_t)) ** 2
    a = np.exp(-absorb / cos_t)
    return 0.5 * sum((1 - r) ** 2 * a / (1 - (r * a) ** 2) for r in (rs, rp))


def angular_factor(cos_incidence: np.ndarray, tau_normal: float = 0.88) -> np.ndarray:
    """``tau(theta) / tau(0)`` of a clear pane whose normal-incidence transmittance is ``tau_normal``.

    Parameters
    ----------
    cos_incidence : (...) float, |cosine| of the angle between the ray and the pane's normal
    tau_normal : float in (0, 0.92]: the pane at normal incidence (above the clear pane's 0.92 no absorption is left)
    """
    lo, hi = 0.0, 5.0
    target = min(float(tau_normal), float(_pane(np.ones(1), 0.0)[0]))
    for _ in range(60):                 # bisection on the absorption that gives tau_normal at normal incidence
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _pane(np.ones(1), mid)[0] > target else (lo, mid)
    absorb = 0.5 * (lo + hi)
    return _pane(np.abs(np.asarray(cos_incidence, float)), absorb) / _pane(np.ones(1), absorb)[0]


class GlazingTracer:
    """Transmittance along rays through a scene's glazing.

    Parameters
    ----------
    scene : Scene
    angular : bool
        Apply :func:`angular_factor` (default); False: each pane's normal-incidence transmittance at every angle.
    """

    def __init__(self, scene, *, angular: bool = True, threads: int | None = None) -> None:
        tri = np.asarray(scene.triangles, np.float64)
        self.caster = RayCaster(scene.vertices, scene.faces, threads=threads)
        mat = np.asarray(scene.material)[np.asarray(scene.patch_of_triangle)]
        tau = np.array([m.transmittance for m in scene.materials], np.float64).reshape(-1, 3)
        self.tau = tau[mat]                                                  # (t, 3)
        self.glazing = self.tau.max(axis=1) > 0
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        self.angular = angular
        self._factor = {}
        for i, m in enumerate(scene.materials):
            if max(m.transmittance) > 0:
                self._factor[i] = max(m.transmittance)
        self.material = mat
        size = float(np.ptp(scene.bounds, axis=0).max()) if len(tri) else 1.0
        self.eps = 1e-5 * max(size, 1e-3)

    @property
    def has_glazing(self) -> bool:
        return bool(self.glazing.any())

    def transmittance(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(r, 3) float: the light of each ray's sky direction that reaches its origin (0: blocked).

        Parameters
        ----------
        origins : (r, 3) float, on or off a surface (offset along the ray here)
        directions : (r, 3) float, unit vectors toward the sky
        """
        o = np.asarray(origins, np.float64) + self.eps * directions
        d = np.ascontiguousarray(directions, np.float64)
        T = np.ones((len(o), 3))
        live = np.arange(len(o))
        for _ in range(MAX_PANES + 1):
            if not len(live):
                break
            face, dist, _ = self.caster.intersect(o[live], d[live])
            escaped = face < 0
            hit = ~escaped
            glass = np.zeros(len(live), bool)
            glass[hit] = self.glazing[face[hit]]
            T[live[hit & ~glass]] = 0.0
            g = live[glass]
            f = face[glass]
            t = self.tau[f]
            if self.angular:
                cos_i = np.abs(np.einsum("rd,rd->r", self.normals[f], d[g]))
                for mi, tn in self._factor.items():
                    sel = self.material[f] == mi
                    if sel.any():
                        t[sel] *= angular_factor(cos_i[sel], tn)[:, None]
            T[g] *= t
            o[g] = o[g] + (dist[glass] + self.eps)[:, None] * d[g]
            live = g
        T[live] = 0.0          # still inside glazing after MAX_PANES panes: counted as blocked
        return T
