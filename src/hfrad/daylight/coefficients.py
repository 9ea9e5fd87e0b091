"""Daylight coefficients: the light of every sky patch at every patch and sensor, interreflections included.

For sky patch p (radiance ``L_p``, W/(sr m^2), uniform over its solid angle
``Omega_p``), the first-hit irradiance of a point x with normal n is

    H_p(x) = L_p  integral over Omega_p of  max(0, n . w) T(x, w) dw          (W/m^2)

``T`` the transmittance of the glazing the ray from x toward w crosses (0 if
an opaque face blocks it; :class:`GlazingTracer`). The integral is a sum over
``k x k`` strata of equal solid angle (:meth:`SkyPatches.samples`), one ray
each. Patches take the mean over their ``s x s`` visibility sample points.

The first reflection of all sky patches, ``E = rho H`` (n, 3, P), is solved
in ONE batched ``fac.solve`` (eq. 4): ``B_p = (I - R F)^{-1} E_p``; at the
sensors the interreflected part is the stored gather ``G B_p``
(:mod:`hfrad.lighting.gather`). So the daylight coefficients of m sensors are

    DC = D + G B      (m, 3, P)   irradiance per unit patch radiance (sr)

and a sky vector ``L`` (P, 3) gives the sensors' illuminance
``sum_c Y_c sum_p DC[:, c, p] L[p, c]`` (lux, Y = :data:`RADIANCE_LUMINANCE`).
"""

from __future__ import annotations

import numpy as np

from ..formfactors.visibility import sample_points
from ..progress import ProgressCallback, report
from .glazing import GlazingTracer
from .sky import SkyPatches, direction

__all__ = ["first_hit"]


def first_hit(tracer: GlazingTracer, patches: SkyPatches, points: np.ndarray, normals: np.ndarray, *,
              k: int = 3, north: float = 0.0, progress: ProgressCallback = None, batch: int = 1 << 20) -> np.ndarray:
    """(q, 3, P) float, sr: first-hit irradiance at ``points`` per unit radiance of each sky patch.

    Parameters
    ----------
    tracer : GlazingTracer
    patches : SkyPatches (P patches, the ground first)
    points, normals : (q, 3) float; normals of unit length
    k : int
        ``k x k`` ray directions per sky patch.
    north : float, degrees (see :func:`direction`)
    progress : callable (done, total), optional
        Sky patches done.
    batch : int
        Rays per call to the tracer: directions of several patches go together, so that
        Embree's batches are large enough for all its threads.

    Notes
    -----
    Cost: up to q P k^2 rays (those below a point's horizon are not cast),
    each followed through at most :data:`MAX_PANES` panes.
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    N = np.asarray(normals, np.float64).reshape(-1, 3)
    q, n_patch = len(P), len(patches)
    dirs, owner, weight = [], [], []
    for p, (alt, azi) in enumerate(patches.samples(k)):
        dirs.append(direction(alt, azi, north))
        owner.append(np.full(len(alt), p))
        weight.append(np.full(len(alt), patches.solid_angle[p] / len(alt)))
    dirs, owner, weight = np.vstack(dirs), np.concatenate(owner), np.concatenate(weight)
    out = np.zeros((q, 3, n_patch))
    step = max(1, batch // max(q, 1))
    for start in range(0, len(dirs), step):
        d = dirs[start:start + step]
        cos = N @ d.T                                                # (q, b)
        qi, di = np.nonzero(cos > 0)
        if len(qi):
            T = tracer.transmittance(P[qi], d[di])                   # (r, 3)
            w = cos[qi, di] * weight[start + di]
            cell = qi * n_patch + owner[start + di]
            for c in range(3):
                out[:, c, :] += np.bincount(cell, weights=w * T[:, c], minlength=q * n_patch).reshape(q, n_patch)
        report(progress, int(owner[min(len(dirs), start + step) - 1]) + 1, n_patch)
    return out


def patch_first_hit(scene, tracer: GlazingTracer, patches: SkyPatches, *, samples: int = 2, k: int = 3,
                    north: float = 0.0, progress: ProgressCallback = None) -> np.ndarray:
    """(n, 3, P) float, sr: each scene patch's mean first-hit irradiance per unit radiance of each sky patch."""
    pts, nrm = sample_points(scene, samples)
    n, s = pts.shape[:2]
    H = first_hit(tracer, patches, pts.reshape(-1, 3), nrm.reshape(-1, 3), k=k, north=north, progress=progress)
    return H.reshape(n, s, 3, -1).mean(axis=1)
