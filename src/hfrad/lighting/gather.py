"""The stored gather operator: illuminance at sensors from patch radiosity.

A sensor at ``p`` facing ``n`` receives from patch j (radiosity ``B_j``, W/m^2)

    H(p) = sum_j F_{p -> j} V_{p j} B_j

with ``F_{p -> j}`` the exact point-to-polygon form factor (Lambert's contour
integral, eq. (1) of docs/method.md, the form-factor kernel's own
``_point_to_patch``, clipped to the sensor's hemisphere) and ``V_{p j}`` the
fraction of the patch's ``s x s`` visibility sample points that the sensor
sees (one Embree occlusion ray each). The (m, n) matrix ``G = F V`` is built
once; after that the sensors' indirect light for any radiosity costs one
product, O(m n), and for L precomputed luminaire radiosities ``G @ B_l`` is
taken once too, so a relighting is O(m L) (:class:`hfrad.lighting.LightingModel`).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ..formfactors.kernel import _point_to_patch
from ..formfactors.raycast import RayCaster
from ..formfactors.visibility import sample_points
from ..progress import ProgressCallback, report
from .direct import caster_for

__all__ = ["GatherOperator", "gather_operator"]


@njit(parallel=True, cache=True)
def _unoccluded(P, Nrm, T, TN, tri_patch, eps, out):
    for i in prange(P.shape[0]):
        for t in range(T.shape[0]):
            f = _point_to_patch(P[i, 0], P[i, 1], P[i, 2], Nrm[i, 0], Nrm[i, 1], Nrm[i, 2], T, TN, t, eps)
            if f > 0.0:
                out[i, tri_patch[t]] += f


class GatherOperator:
    """``G`` (m, n): irradiance at m sensors per unit radiosity of each of n patches.

    Attributes
    ----------
    matrix : (m, n) float32
    rays : int
        Occlusion rays cast to build it.
    """

    def __init__(self, matrix: np.ndarray, rays: int = 0) -> None:
        self.matrix = np.ascontiguousarray(matrix, dtype=np.float32)
        self.rays = int(rays)

    @property
    def shape(self) -> tuple[int, int]:
        return self.matrix.shape

    def apply(self, radiosity: np.ndarray) -> np.ndarray:
        """Irradiance (m, ...) W/m^2 at the sensors for ``radiosity`` (n, ...) W/m^2 (any trailing shape)."""
        B = np.asarray(radiosity)
        flat = B.reshape(B.shape[0], -1).astype(np.float32)
        return (self.matrix @ flat).astype(np.float64).reshape((self.matrix.shape[0],) + B.shape[1:])


def gather_operator(scene, points: np.ndarray, normals: np.ndarray, *, samples: int = 2,
                    caster: RayCaster | None = None, progress: ProgressCallback = None,
                    rows_per_batch: int = 64) -> GatherOperator:
    """Build the gather operator of sensors at ``points`` facing ``normals`` in ``scene``.

    Parameters
    ----------
    scene : Scene
        The factorization's scene (``fac.scene``), user patch order.
    points, normals : (m, 3) float
    samples : int
        Visibility sample points per patch edge (``samples^2`` rays per
        (sensor, patch) pair with a positive form factor).
    caster : RayCaster, optional
        Default: one over the scene's occluder mesh.
    progress : callable (done, total), optional
        Sensors done.

    Returns
    -------
    GatherOperator

    Notes
    -----
    Cost: O(m t) form factors (t triangles) and up to m n s^2 rays, once.
    """
    P = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    Nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    Nrm = np.ascontiguousarray(Nrm / np.linalg.norm(Nrm, axis=1)[:, None])
    n = scene.n_patches
    T = np.ascontiguousarray(np.asarray(scene.triangles, np.float64))
    cr = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    ln = np.linalg.norm(cr, axis=1)
    TN = np.ascontiguousarray(np.divide(cr, ln[:, None], out=np.zeros_like(cr), where=ln[:, None] > 0))
    tri_patch = np.ascontiguousarray(scene.patch_of_triangle, dtype=np.int64)
    size = float(np.ptp(scene.bounds, axis=0).max()) if len(T) else 1.0
    eps = 1e-9 * size
    ray_eps = 1e-5 * size
    spts, _ = sample_points(scene, samples)                     # (n, s, 3)
    s = spts.shape[1]
    if caster is None:
        caster = caster_for(scene)
    G = np.zeros((len(P), n), np.float32)
    rays = 0
    for start in range(0, len(P), rows_per_batch):
        stop = min(len(P), start + rows_per_batch)
        F = np.zeros((stop - start, n))
        _unoccluded(P[start:stop], Nrm[start:stop], T, TN, tri_patch, eps, F)
        ri, pj = np.nonzero(F > 0)
        if len(ri):
            origin = np.repeat(P[start + ri], s, axis=0)
            target = spts[pj].reshape(-1, 3)
            v = target - origin
            d = np.linalg.norm(v, axis=1)
            u = v / np.maximum(d, 1e-300)[:, None]
            blocked = caster.occluded(origin + ray_eps * u, u, np.maximum(d * (1 - 1e-6) - 2 * ray_eps, 0.0))
            rays += len(origin)
            seen = 1.0 - blocked.reshape(-1, s).mean(axis=1)
            F[ri, pj] *= seen
        G[start:stop] = F
        report(progress, stop, len(P))
    return GatherOperator(G, rays)
