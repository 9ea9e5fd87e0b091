"""Direct illuminance from luminaires, at points and on patches, with Embree visibility.

For a luminaire at ``s`` with intensity ``I`` (cd) towards a receiver at ``p``
with unit normal ``n``::

    E(p) = I(u) max(0, -u . n) / d^2 * V(s, p),    u = (p - s) / d,  d = |p - s|

(the inverse-square cosine law, lux), ``V`` 1 when nothing blocks the segment
(one Embree occlusion ray). A luminaire whose luminous opening is large next to
the distance (``d < near_ratio x size``, the "five-times rule" by default) is
an area source: ``k`` points spread over its opening (about ``spacing`` apart),
each with ``I / k`` and its own shadow ray; farther receivers see it as a point.

A patch's direct irradiance ``H_direct,l`` is the mean of ``E`` over its
visibility sample points (``m x m`` per patch, :func:`hfrad.formfactors.visibility.sample_points`).
"""

from __future__ import annotations

import numpy as np

from ..formfactors.raycast import RayCaster
from ..formfactors.visibility import sample_points
from ..progress import ProgressCallback, report

__all__ = ["direct_illuminance", "patch_direct_illuminance", "caster_for", "SPACING", "NEAR_RATIO"]

#: metres between the points that stand for a large luminous opening
SPACING = 0.1
#: a receiver nearer than this many opening sizes sees the opening as an area source
NEAR_RATIO = 5.0
#: rays per Embree batch
_BATCH = 1 << 20


def caster_for(scene, threads: int | None = None) -> RayCaster:
    """An Embree caster over the scene's occluder mesh (its un-subdivided faces)."""
    return RayCaster(scene.occluder_vertices, scene.occluder_faces, threads=threads)


def _offset(scene_size: float) -> float:
    return 1e-5 * max(scene_size, 1e-3)


def direct_illuminance(luminaires, points: np.ndarray, normals: np.ndarray, *, caster: RayCaster | None = None,
                       spacing: float = SPACING, near_ratio: float = NEAR_RATIO,
                       progress: ProgressCallback = None) -> np.ndarray:
    """(p, L) float, lux: direct illuminance at ``points`` from each luminaire at dimming 1.

    Parameters
    ----------
    luminaires : sequence of Luminaire (L)
    points : (p, 3) float, metres
    normals : (p, 3) float, unit normals of the receiving surfaces
    caster : RayCaster, optional
        Occluders (:func:`caster_for`); None: nothing blocks (free space).
    spacing, near_ratio : float
        Area-source sampling (module docstring).
    progress : callable (done, total), optional
        Luminaires done.

    Notes
    -----
    Cost: one occlusion ray per (point, luminaire) with a positive
    contribution, k per near pair of a large luminaire.
    """
    P = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    N = np.ascontiguousarray(np.asarray(normals, np.float64).reshape(-1, 3))
    out = np.zeros((len(P), len(luminaires)))
    if not len(P):
        return out
    span = float(np.ptp(np.vstack([P] + [lum.position[None] for lum in luminaires]), axis=0).max())
    eps = _offset(span)
    for j, lum in enumerate(luminaires):
        d_centre = np.linalg.norm(P - lum.position, axis=1)
        size = lum.size
        near = (d_centre < near_ratio * size) if size > 0 else np.zeros(len(P), bool)
        if (~near).any():
            far = np.flatnonzero(~near)
            out[far, j] = _from_sources(lum, lum.position[None], np.ones(1), P[far], N[far], caster, eps)
        if near.any():
            idx = np.flatnonzero(near)
            out[idx, j] = _from_sources(lum, *lum.emission_points(spacing), P[idx], N[idx], caster, eps)
        report(progress, j + 1, len(luminaires))
    return out


def _from_sources(lum, sources: np.ndarray, weights: np.ndarray, P: np.ndarray, N: np.ndarray, caster,
                  eps: float) -> np.ndarray:
    """(p,) lux at P from ``sources`` (k, 3), each with ``weights`` (k,) of the luminaire's intensity."""
    k = len(sources)
    total = np.zeros(len(P))
    frame = lum.frame
    rows = max(1, _BATCH // k)
    for start in range(0, len(P), rows):
        p = P[start:start + rows]
        n = N[start:start + rows]
        v = p[:, None, :] - sources[None, :, :]                         # (b, k, 3) source -> receiver
        d2 = np.einsum("bkd,bkd->bk", v, v)
        d = np.sqrt(d2)
        ok = d > eps
        u = np.divide(v, d[..., None], out=np.zeros_like(v), where=ok[..., None])
        cos_r = -np.einsum("bkd,bd->bk", u, n)
        live = ok & (cos_r > 0)
        E = np.zeros(d.shape)
        if live.any():
            I = lum.photometry.intensity(u[live] @ frame)
            E[live] = I * cos_r[live] / d2[live] * np.broadcast_to(weights, E.shape)[live]
            live &= E > 0
            if caster is not None and live.any():
                bi, ki = np.nonzero(live)
                dirs = -u[bi, ki]                                        # receiver -> source
                origin = p[bi] + eps * dirs
                blocked = caster.occluded(origin, dirs, d[bi, ki] - 2 * eps)
                E[bi[blocked], ki[blocked]] = 0.0
        total[start:start + rows] = E.sum(axis=1)
    return total


def patch_direct_illuminance(scene, luminaires, *, samples: int = 3, caster: RayCaster | None = None,
                             spacing: float = SPACING, near_ratio: float = NEAR_RATIO,
                             progress: ProgressCallback = None) -> np.ndarray:
    """(n, L) float, lux: each patch's direct illuminance from each luminaire (dimming 1).

    The mean over ``samples x samples`` points of every patch (points of
    :func:`hfrad.formfactors.visibility.sample_points`, each with its
    triangle's normal). Multiply by the reflectance and divide by 683 lm/W to
    get the first-bounce exitance of :class:`hfrad.lighting.LightingModel`.
    """
    pts, nrm = sample_points(scene, samples)
    n, s = pts.shape[:2]
    if caster is None:
        caster = caster_for(scene)
    E = direct_illuminance(luminaires, pts.reshape(-1, 3), nrm.reshape(-1, 3), caster=caster,
                           spacing=spacing, near_ratio=near_ratio, progress=progress)
    return E.reshape(n, s, len(luminaires)).mean(axis=1)
