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


def _directions(patches: SkyPatches, k: int, north: float):
    """All patches' sample directions stacked: (K, 3) unit vectors, (K,) owning patch, (K,) solid angle each (sr)."""
    dirs, owner, weight = [], [], []
    for p, (alt, azi) in enumerate(patches.samples(k)):
        dirs.append(direction(alt, azi, north))
        owner.append(np.full(len(alt), p))
        weight.append(np.full(len(alt), patches.solid_angle[p] / len(alt)))
    return np.vstack(dirs), np.concatenate(owner), np.concatenate(weight)


def _accumulate(out, counts, tracer, P, N, dirs, owner, weight, batch, progress=None):
    """Add the rays from points ``P`` along ``dirs`` into ``out`` (q, 3, P); with ``counts`` (2, q, P),
    count the rays that got through (``counts[0]``) and those blocked (``counts[1]``)."""
    n_patch = out.shape[2]
    step = max(1, batch // max(len(P), 1))
    for start in range(0, len(dirs), step):
        d = dirs[start:start + step]
        cos = N @ d.T                                                # (q, b)
        qi, di = np.nonzero(cos > 0)
        if len(qi):
            T = tracer.transmittance(P[qi], d[di])                   # (r, 3)
            w = cos[qi, di] * weight[start + di]
            cell = qi * n_patch + owner[start + di]
            size = out.shape[0] * n_patch
            for c in range(3):
                out[:, c, :] += np.bincount(cell, weights=w * T[:, c], minlength=size).reshape(-1, n_patch)
            if counts is not None:
                through = T.max(axis=1) > 0
                counts[0] += np.bincount(cell[through], minlength=size).reshape(-1, n_patch)
                counts[1] += np.bincount(cell[~through], minlength=size).reshape(-1, n_patch)
        report(progress, int(owner[min(len(dirs), start + step) - 1]) + 1, n_patch)


def first_hit(tracer: GlazingTracer, patches: SkyPatches, points: np.ndarray, normals: np.ndarray, *,
              k: int = 3, refine: int = 1, north: float = 0.0, progress: ProgressCallback = None,
              batch: int = 1 << 20) -> np.ndarray:
    """(q, 3, P) float, sr: first-hit irradiance at ``points`` per unit radiance of each sky patch.

    Parameters
    ----------
    tracer : GlazingTracer
    patches : SkyPatches (P patches, the ground first)
    points, normals : (q, 3) float; normals of unit length
    k : int
        ``k x k`` ray directions per sky patch.
    refine : int
        Where a patch is seen in part from a point (some of its ``k^2`` rays blocked, some not: a
        window's edge crosses it), or a neighbouring patch is seen otherwise than it is (hidden,
        in part, whole: an edge near the border can fall between all of its rays), its rays are cast
        again, ``(k refine)^2`` of them. Most of the sky is wholly seen or wholly hidden, so
        refining only the edges costs little: at ``k`` 4, ``refine`` 4 a work-plane sensor's annual
        first-hit light is within 1% of 64^2 rays in every patch; 8^2 rays everywhere are 3-4% off.
    north : float, degrees (see :func:`direction`)
    progress : callable (done, total), optional
        Sky patches done in the first pass; with ``refine`` the total is twice the patch count and the
        second half follows the refinement's rays (so that a bar keeps moving while edges are refined).
    batch : int
        Rays per call to the tracer: directions of several patches go together, so that
        Embree's batches are large enough for all its threads.

    Notes
    -----
    Cost: up to q P k^2 rays (those below a point's horizon are not cast) plus
    (k refine)^2 per refined (point, patch) pair, each followed through at most
    :data:`MAX_PANES` panes. A window seen through a gap narrower than a coarse
    ray spacing (12 / k degrees at MF:1) in a patch can be missed.
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    N = np.asarray(normals, np.float64).reshape(-1, 3)
    q, n_patch = len(P), len(patches)
    out = np.zeros((q, 3, n_patch))
    counts = np.zeros((2, q, n_patch), np.int64) if refine > 1 else None
    total = 2 * n_patch if refine > 1 else n_patch
    first = (lambda done, _: progress(done, total)) if progress is not None else None
    _accumulate(out, counts, tracer, P, N, *_directions(patches, k, north), batch, first)
    if refine > 1:
        # refined: patches seen in part, and patches next to one seen otherwise (hidden, in part, whole):
        # a window's edge near a patch's border can pass between all of its coarse rays
        through, blocked = counts[0] > 0, counts[1] > 0
        state = np.stack([blocked & ~through, through & blocked, through & ~blocked], axis=2)   # (q, P, 3)
        near = np.einsum("qpv,pr->qrv", state.astype(np.float32), patches.neighbours().astype(np.float32)) > 0
        partial = (through | blocked) & (state[:, :, 1] | (near & ~state).any(axis=2))
        fine = [(direction(alt, azi, north), patches.solid_angle[p] / len(alt))
                for p, (alt, azi) in enumerate(patches.samples(k * refine))]
        groups, rays = [[]], [0]
        for p in np.flatnonzero(partial.any(axis=0)):
            groups[-1].append((p, np.flatnonzero(partial[:, p])))
            rays[-1] += len(groups[-1][-1][1]) * len(fine[p][0])
            if rays[-1] >= batch:
                groups.append([])
                rays.append(0)
        done, all_rays = 0, max(sum(rays), 1)
        for group, r in zip(groups, rays):
            _refine(out, tracer, P, N, group, fine)
            done += r
            report(progress, n_patch + (n_patch * done) // all_rays, total)
        report(progress, total, total)
    return out


def _refine(out, tracer, P, N, group, fine) -> None:
    """Replace ``out[q, :, p]`` for each (p, q) of ``group`` by its fine rays ``fine[p]`` (directions, sr each),
    all of the group's rays in one call to the tracer."""
    if not group:
        return
    O = np.concatenate([np.repeat(P[q], len(fine[p][0]), axis=0) for p, q in group])
    Nr = np.concatenate([np.repeat(N[q], len(fine[p][0]), axis=0) for p, q in group])
    D = np.concatenate([np.tile(fine[p][0], (len(q), 1)) for p, q in group])
    W = np.concatenate([np.full(len(q) * len(fine[p][0]), fine[p][1]) for p, q in group])
    cos = np.einsum("rd,rd->r", Nr, D)
    up = np.flatnonzero(cos > 0)
    L = np.zeros((len(O), 3))
    L[up] = tracer.transmittance(O[up], D[up]) * (cos[up] * W[up])[:, None]
    start = 0
    for p, q in group:
        stop = start + len(q) * len(fine[p][0])
        out[q, :, p] = L[start:stop].reshape(len(q), -1, 3).sum(axis=1)
        start = stop


def patch_first_hit(scene, tracer: GlazingTracer, patches: SkyPatches, *, samples: int = 2, k: int = 3,
                    north: float = 0.0, progress: ProgressCallback = None) -> np.ndarray:
    """(n, 3, P) float, sr: each scene patch's mean first-hit irradiance per unit radiance of each sky patch."""
    pts, nrm = sample_points(scene, samples)
    n, s = pts.shape[:2]
    H = first_hit(tracer, patches, pts.reshape(-1, 3), nrm.reshape(-1, 3), k=k, north=north, progress=progress)
    return H.reshape(n, s, 3, -1).mean(axis=1)
