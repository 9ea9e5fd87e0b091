"""Direct illuminance from luminaires, at points and on patches, with Embree visibility.

For a luminaire at ``s`` with intensity ``I`` (cd) towards a receiver at ``p``
with unit normal ``n``::

    E(p) = I(u) max(0, -u . n) / d^2 * V(s, p),    u = (p - s) / d,  d = |p - s|

(the inverse-square cosine law, lux), ``V`` 1 when nothing blocks the segment.
A luminaire whose luminous opening is large next to the distance (``d <
near_ratio x size``, the "five-times rule" by default) is an area source:
``k`` points spread over its opening (about ``spacing`` apart), each with
``I / k`` and its own shadow ray; farther receivers see it as a point.

A patch receives the flux ``Phi = integral of I(w) V(w) dw`` over the solid
angle its triangles subtend at the source (lumens), and its direct
irradiance is ``Phi / area``. Each triangle's solid angle is exact (Van
Oosterom & Strackee 1983); a triangle that subtends more than
``samples^2 x`` :data:`SOLID_ANGLE_PER_SAMPLE` is split in four until none
does, so a patch 1 cm from a luminaire is sampled as finely, in direction,
as one 10 m away; within a piece the ``samples x samples`` points weight
``I V`` by their share of the solid angle (``cos / d^2``). For a closed room
the patches' solid angles tile the sphere, so the flux the patches receive
is the luminaire's flux up to the quadrature of ``I`` with samples of about
:data:`SOLID_ANGLE_PER_SAMPLE` each (tests/test_lighting_flux.py: within 0.1% for a
smooth distribution, 2% for a hard-edged 10-degree spot, from 1 mm to metres).

Shadow rays: Embree (float32) tests the segment from ``eps`` off the
receiver to ``reach`` from the source; the first ``reach`` next to the
source is tested exactly in float64 against the scene's faces near the
source, so no offset carries light through a wall, however thin, that the
luminaire sits behind (a luminaire flush with a surface lights the side the
surface faces, never the side behind it).
"""

from __future__ import annotations

import numpy as np

from ..formfactors.kernel import points_on_triangles, split_centroids
from ..formfactors.raycast import RayCaster
from ..progress import ProgressCallback, report

__all__ = ["direct_illuminance", "patch_direct_illuminance", "caster_for", "SPACING", "NEAR_RATIO",
           "SOLID_ANGLE_PER_SAMPLE"]

#: metres between the points that stand for a large luminous opening
SPACING = 0.1
#: a receiver nearer than this many opening sizes sees the opening as an area source
NEAR_RATIO = 5.0
#: steradians per sample point on the patches (about 2.6 degrees square), about the step of photometric tables
SOLID_ANGLE_PER_SAMPLE = 2e-3
#: rays per Embree batch
_BATCH = 1 << 20
#: (source point, triangle) pairs handled at once (their corner vectors: 150 MB)
_PAIRS = 1 << 21
#: splits of one triangle at most (a piece 2^-40 of the triangle's size: float64's limit)
_MAX_DEPTH = 40


def caster_for(scene, threads: int | None = None) -> RayCaster:
    """An Embree caster over the scene's occluder mesh (its un-subdivided faces)."""
    return RayCaster(scene.occluder_vertices, scene.occluder_faces, threads=threads)


def _offsets(scene_size: float) -> tuple[float, float]:
    """(eps, reach), metres: a shadow ray's offset off its receiver, and its source end tested exactly."""
    size = max(scene_size, 1e-3)
    return 1e-5 * size, 1e-3 * size


# -- shadow rays ----------------------------------------------------------------------------------------

def _faces_near(caster: RayCaster | None, point: np.ndarray, reach: float) -> np.ndarray:
    """(f, 3, 3) float64 faces of ``caster`` whose bounding box, grown by ``reach``, holds ``point``."""
    tri = getattr(caster, "world_triangles", None)
    if tri is None or not len(tri):
        return np.zeros((0, 3, 3))
    inside = ((tri.min(axis=1) - reach <= point) & (point <= tri.max(axis=1) + reach)).all(axis=1)
    return tri[inside]


def _blocked_near_source(faces: np.ndarray, source: np.ndarray, dirs: np.ndarray, length: np.ndarray,
                         tol: float) -> np.ndarray:
    """(r,) bool: whether the segments ``source + t dirs``, ``0 <= t <= length``, pass through a face.

    Exact in float64. A source on a face's plane (within ``tol``) is blocked
    only towards the face's back: a luminaire flush with a ceiling lights the
    room, not the space above it.
    """
    out = np.zeros(len(dirs), bool)
    for a, b, c in faces:
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm == 0:
            continue
        n /= norm
        sd0 = float((source - a) @ n)
        dn = dirs @ n
        if abs(sd0) <= tol:
            cross, t = dn < 0, np.zeros(len(dirs))                        # leaves through the back
        else:
            t = np.divide(-sd0, dn, out=np.full(len(dirs), np.inf), where=dn != 0)
            cross = (t > 0) & (t <= length)
        if not cross.any():
            continue
        x = source + t[cross, None] * dirs[cross]
        out[np.flatnonzero(cross)[_inside(x, a, b, c, n)]] = True
    return out


def _inside(x: np.ndarray, a, b, c, n) -> np.ndarray:
    """(r,) bool: points ``x`` on the plane of triangle abc (normal n) inside it or on its edges."""
    tol = -1e-9
    return ((np.cross(b - a, x - a) @ n >= tol * np.linalg.norm(b - a) ** 2)
            & (np.cross(c - b, x - b) @ n >= tol * np.linalg.norm(c - b) ** 2)
            & (np.cross(a - c, x - c) @ n >= tol * np.linalg.norm(a - c) ** 2))


def _shadowed(caster: RayCaster | None, source: np.ndarray, P: np.ndarray, eps: float, reach: float,
              near: "list[np.ndarray] | np.ndarray", which: np.ndarray | None = None) -> np.ndarray:
    """(r,) bool: whether something blocks the segment from ``source`` to each receiver ``P`` (r, 3).

    ``source``: (3,), or (k, 3) with ``which`` (r,) the source of each ray;
    ``near``: the faces near the source (:func:`_faces_near`), or a list of
    them per source.
    """
    S = source[which] if which is not None else source
    v = P - S
    d = np.sqrt(np.einsum("rd,rd->r", v, v))
    dirs = v / d[:, None]                                                # source -> receiver
    a = np.minimum(reach, 0.5 * d)                                       # exact part at the source's end
    blocked = np.zeros(len(P), bool)
    for i, faces in enumerate([near] if which is None else near):
        if len(faces):
            rays = slice(None) if which is None else np.flatnonzero(which == i)
            src = source if which is None else source[i]
            blocked[rays] = _blocked_near_source(faces, src, dirs[rays], a[rays], 1e-9 * eps)
    e_r = np.minimum(eps, 0.5 * d)
    length = d - a - e_r
    todo = np.flatnonzero(~blocked & (length > 0))
    if caster is not None and len(todo):
        blocked[todo] = caster.occluded(P[todo] - e_r[todo, None] * dirs[todo], -dirs[todo], length[todo])
    return blocked


# -- points -----------------------------------------------------------------------------------------------

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
    eps, reach = _offsets(span)
    for j, lum in enumerate(luminaires):
        d_centre = np.linalg.norm(P - lum.position, axis=1)
        size = lum.size
        near = (d_centre < near_ratio * size) if size > 0 else np.zeros(len(P), bool)
        if (~near).any():
            far = np.flatnonzero(~near)
            out[far, j] = _from_sources(lum, lum.position[None], np.ones(1), P[far], N[far], caster, eps, reach)
        if near.any():
            idx = np.flatnonzero(near)
            out[idx, j] = _from_sources(lum, *lum.emission_points(spacing), P[idx], N[idx], caster, eps, reach)
        report(progress, j + 1, len(luminaires))
    return out


def _from_sources(lum, sources: np.ndarray, weights: np.ndarray, P: np.ndarray, N: np.ndarray, caster,
                  eps: float, reach: float) -> np.ndarray:
    """(p,) lux at P from ``sources`` (k, 3), each with ``weights`` (k,) of the luminaire's intensity."""
    total = np.zeros(len(P))
    frame = lum.frame
    for src, w in zip(sources, weights):
        near = _faces_near(caster, src, reach)
        for start in range(0, len(P), _BATCH):
            p, n = P[start:start + _BATCH], N[start:start + _BATCH]
            v = p - src
            d2 = np.einsum("bd,bd->b", v, v)
            d = np.sqrt(d2)
            u = np.divide(v, d[:, None], out=np.zeros_like(v), where=d[:, None] > eps)
            cos_r = -np.einsum("bd,bd->b", u, n)
            live = np.flatnonzero((d > eps) & (cos_r > 0))
            if not len(live):
                continue
            E = lum.photometry.intensity(u[live] @ frame) * cos_r[live] / d2[live] * w
            lit = E > 0
            if caster is not None and lit.any():
                lit[lit] = ~_shadowed(caster, src, p[live[lit]], eps, reach, near)
            total[start + live[lit]] += E[lit]
    return total


# -- patches --------------------------------------------------------------------------------------------

def _solid_angles(T: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(t,) steradians that triangles ``T`` (t, 3, 3) subtend at ``s`` (Van Oosterom & Strackee 1983)."""
    a, b, c = (T[:, i] - s for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.abs(np.einsum("td,td->t", a, np.cross(b, c)))
    den = (la * lb * lc + np.einsum("td,td->t", a, b) * lc + np.einsum("td,td->t", a, c) * lb
           + np.einsum("td,td->t", b, c) * la)
    return 2.0 * np.arctan2(num, den)


def _split4(T: np.ndarray) -> np.ndarray:
    """(4t, 3, 3): each triangle cut at its edge midpoints into four, with the same orientation."""
    a, b, c = T[:, 0], T[:, 1], T[:, 2]
    ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
    return np.concatenate([np.stack(x, axis=1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def _pieces(T: np.ndarray, S: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles ``T`` (t, 3, 3) split until each piece subtends at most ``limit`` sr at its point ``S`` (t, 3).

    Returns pieces (q, 3, 3), their row in ``T`` (q,) and solid angle (q,).
    """
    out_T, out_i, out_w = [], [], []
    owner = np.arange(len(T))
    for depth in range(_MAX_DEPTH + 1):
        w = _solid_angles(T, S[owner])
        big = (w > limit) if depth < _MAX_DEPTH else np.zeros(len(T), bool)
        out_T.append(T[~big]), out_i.append(owner[~big]), out_w.append(w[~big])
        if not big.any():
            break
        T, owner = _split4(T[big]), np.tile(owner[big], 4)
    return np.concatenate(out_T), np.concatenate(out_i), np.concatenate(out_w)


def _dark_side(photometry) -> int:
    """+1 if a type C distribution sends nothing at gamma >= 90 (a downlight), -1 nothing at gamma <= 90, else 0.

    Read off the table's nodes: the bilinear interpolant is zero over a
    hemisphere when every node there is zero and a node lies on the horizon
    (or the table stops short of it: zero beyond its angles).
    """
    if photometry.kind != "C":
        return 0
    v, cd = photometry.vertical, photometry.candela
    horizon = bool(np.isclose(v, 90.0, rtol=0, atol=1e-9).any())
    if not cd[:, v >= 90 - 1e-9].any() and (horizon or v.max() < 90):
        return 1
    if not cd[:, v <= 90 + 1e-9].any() and (horizon or v.min() > 90):
        return -1
    return 0


def _triangle_flux(lum, sources: np.ndarray, weights: np.ndarray, T: np.ndarray, normals: np.ndarray, caster,
                   eps: float, reach: float, samples: int) -> np.ndarray:
    """(t,) lumens that triangles ``T`` (t, 3, 3) with unit ``normals`` receive from ``sources`` (k, 3).

    Source i carries ``weights[i]`` of the luminaire's intensity; all
    (source, triangle) pairs are sampled together, in batches.
    """
    per = max(1, _PAIRS // max(1, len(T)))
    if len(sources) > per:                                                # (k, t, 3, 3) below: bounded memory
        return sum(_triangle_flux(lum, sources[i:i + per], weights[i:i + per], T, normals, caster, eps, reach,
                                  samples) for i in range(0, len(sources), per))
    out = np.zeros(len(T))
    rel = T[None, :, :, :] - sources[:, None, None, :]                   # (k, t, 3, 3) source -> corners
    lit = np.einsum("ktd,td->kt", rel[:, :, 0], normals) < 0              # the triangle faces the source
    dark = _dark_side(lum.photometry)
    if dark:                       # wholly in the dark hemisphere: no need to sample (a ceiling above a downlight)
        lit &= (dark * np.einsum("ktcd,d->ktc", rel, lum.aim) > 0).any(axis=2)
    si, ti = np.nonzero(lit)
    if not len(si):
        return out
    near = [_faces_near(caster, src, reach) for src in sources]
    bary = split_centroids(samples)
    limit = samples * samples * SOLID_ANGLE_PER_SAMPLE
    frame = lum.frame
    rows = max(1, _BATCH // len(bary))
    for first in range(0, len(si), rows):                                 # pairs, then their pieces, in batches
        pi, pt = si[first:first + rows], ti[first:first + rows]
        pieces, owner, omega = _pieces(T[pt], sources[pi], limit)
        for start in range(0, len(pieces), rows):
            sl = slice(start, start + rows)
            o = owner[sl]
            src = sources[pi[o]]
            p = points_on_triangles(pieces[sl], bary)                        # (b, s, 3)
            v = p - src[:, None, :]
            d2 = np.einsum("bsd,bsd->bs", v, v)
            u = v / np.sqrt(d2)[..., None]
            share = np.maximum(-np.einsum("bsd,bd->bs", u, normals[pt[o]]), 0.0) / d2   # solid angle per area
            tot = share.sum(axis=1, keepdims=True)
            share = np.divide(share, tot, out=np.zeros_like(share), where=tot > 0) * omega[sl, None]
            I = lum.photometry.intensity(u.reshape(-1, 3) @ frame).reshape(share.shape)
            flux = I * share * weights[pi[o]][:, None]
            live = flux > 0
            if caster is not None and live.any():
                bi, ki = np.nonzero(live)
                hit = _shadowed(caster, sources, p[bi, ki], eps, reach, near, which=pi[o[bi]])
                flux[bi[hit], ki[hit]] = 0.0
            out += np.bincount(pt[o], weights=flux.sum(axis=1), minlength=len(T))
    return out


def patch_direct_illuminance(scene, luminaires, *, samples: int = 3, caster: RayCaster | None = None,
                             spacing: float = SPACING, near_ratio: float = NEAR_RATIO,
                             progress: ProgressCallback = None) -> np.ndarray:
    """(n, L) float, lux: each patch's direct illuminance from each luminaire (dimming 1).

    The flux each patch receives over its area (module docstring): a
    triangle's solid angle at the source, split until no piece subtends more
    than ``samples^2 x`` :data:`SOLID_ANGLE_PER_SAMPLE`, each piece sampled
    at ``samples x samples`` points with one shadow ray each. Multiply by the
    reflectance and divide by 683 lm/W to get the first-bounce exitance of
    :class:`hfrad.lighting.LightingModel`.

    Notes
    -----
    Cost: ``samples^2`` shadow rays per triangle and luminaire, plus about
    ``4 pi / SOLID_ANGLE_PER_SAMPLE`` (6.3e3) per source point for the pieces of triangles
    close to a luminaire; ``k`` times that for the triangles near a large
    luminaire (its ``k`` area-source points).
    """
    T = np.asarray(scene.triangles, np.float64)
    normals = np.asarray(scene.triangle_normals, np.float64)
    owner = np.asarray(scene.patch_of_triangle)
    if caster is None:
        caster = caster_for(scene)
    n = scene.n_patches
    out = np.zeros((n, len(luminaires)))
    if not len(T):
        return out
    centroids = T.mean(axis=1)
    radius = np.linalg.norm(T - centroids[:, None], axis=2).max(axis=1)
    span = float(np.ptp(np.vstack([T.reshape(-1, 3)] + [lum.position[None] for lum in luminaires]),
                        axis=0).max())
    eps, reach = _offsets(span)
    areas = np.asarray(scene.areas, np.float64)
    for j, lum in enumerate(luminaires):
        flux = np.zeros(len(T))
        gap = np.linalg.norm(centroids - lum.position, axis=1) - radius
        near = (gap < near_ratio * lum.size) if lum.size > 0 else np.zeros(len(T), bool)
        far = np.flatnonzero(~near)
        flux[far] = _triangle_flux(lum, lum.position[None], np.ones(1), T[far], normals[far], caster, eps, reach,
                                   samples)
        idx = np.flatnonzero(near)
        if len(idx):
            flux[idx] = _triangle_flux(lum, *lum.emission_points(spacing), T[idx], normals[idx], caster, eps,
                                       reach, samples)
        per_patch = np.bincount(owner, weights=flux, minlength=n)
        out[:, j] = np.divide(per_patch, areas, out=np.zeros(n), where=areas > 0)
        report(progress, j + 1, len(luminaires))
    return out
