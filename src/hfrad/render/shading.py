"""Smooth radiosity over patches: per-corner values and barycentric interpolation.

Radiosity is constant per patch. For pictures it is interpolated: each patch
corner gets the value at its vertex of the area-weighted least-squares linear
fit through the centroids of the patches around that vertex that belong to the
same smooth surface,

    B_c = a,   (a, g) = argmin sum_{q in S(c)} A_q (B_q - a - g . (c_q - x_c))^2,

clipped to the range of those patches' values (see :func:`corner_weights`;
a linear radiosity comes back exactly on any mesh, where the area-weighted mean
left smudges on lopsided vertex fans), where S(c) holds the patches touching the corner's vertex whose material is the
corner's patch's material and whose normal is within ``crease_angle`` of its
normal (the patch itself always belongs). So colours do not bleed across the
corner between the red wall and the floor, nor from a light onto the ceiling.

Vertices are welded by position first, so triangle soups (every face with its
own three vertices) are smoothed as well as meshes that share vertices.

Everything works on the detail triangles (``scene.faces``). When patches are
clusters of many triangles, per-corner averaging alone would only blend one
triangle wide at patch borders and the patches would look blocky. There each
corner c instead gets a partition-of-unity blend of the patches near it,

    B_c = sum_q w_q B_q / sum_q w_q,   w_q = max(0, 1 - |x_c - c_q| / (RHO r_q))^2,

over the patches q touching c's vertex in its smoothing set and their
neighbours on the same smooth surface (c_q the patch centroid, r_q its
radius: the farthest corner from c_q); the patches touching the vertex also get
a small floor weight so every corner has one. At a patch centroid the patch's
own value dominates, half-way to a neighbour the two blend evenly; corners
that share a vertex and a smoothing set get equal values, so the picture is
continuous.

Units: radiosity B is an exitance in W/m^2. A Lambertian surface of radiosity B
has radiance L = B / pi in W/(m^2 sr) in every direction; that is what a pixel
of a rendered image measures (see :func:`hfrad.render.render_radiance`).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..scene.weld import weld

#: Default largest angle between patch normals that are still smoothed together, degrees.
CREASE_ANGLE = 30.0

#: Reach of a clustered patch's value, in units of its radius (see the module docstring).
RHO = 1.5

#: Floor weight of the patches touching a corner's vertex (so every corner has one).
_OWN_FLOOR = 1e-3


def _corner_pairs(scene, crease_angle: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (a, b) of corners at one welded vertex, b in the smoothing set of a.

    Corners are numbered 3 f + k (corner k of patch f). Returns ``a`` sorted
    (each corner's partners are contiguous), ``b``, and the (3n + 1,) start of
    each corner's block in them. Cost O(sum over vertices of degree^2).
    """
    n = scene.n_triangles
    vid = weld(scene.vertices, scene.faces).reshape(-1)
    order = np.argsort(vid, kind="stable")
    sv = vid[order]
    new = np.r_[True, sv[1:] != sv[:-1]]
    group_start = np.flatnonzero(new)
    degree = np.diff(np.r_[group_start, len(sv)])
    g = np.cumsum(new) - 1                       # group of each sorted position
    d = degree[g]                                # partners of each sorted corner (incl. itself)
    a = np.repeat(order, d)
    block = np.repeat(np.cumsum(d) - d, d)
    k = np.arange(len(a)) - block
    b = order[np.repeat(group_start[g], d) + k]
    fa, fb = a // 3, b // 3
    cos_min = math.cos(math.radians(crease_angle))
    normals = scene.triangle_normals
    material = scene.material[scene.patch_of_triangle]
    keep = (material[fa] == material[fb]) & (
        np.einsum("ij,ij->i", normals[fa], normals[fb]) >= cos_min)
    keep |= a == b
    a, b = a[keep], b[keep]
    # a is grouped by sorted position; reorder so corners are in 0..3n-1 order
    perm = np.argsort(a, kind="stable")
    a, b = a[perm], b[perm]
    start = np.searchsorted(a, np.arange(3 * n + 1))
    return a, b, start


def corner_weights(scene, *, crease_angle: float = CREASE_ANGLE):
    """(3t, t) sparse matrix W: corner values are ``W @ v`` for per-triangle values v.

    Row ``3 f + k`` (corner k of triangle f at position x_c) holds the weights of
    the triangles q in that corner's smoothing set S(c) (see the module
    docstring): the value at x_c of the area-weighted least-squares linear fit
    ``v_q ~ a + g . (c_q - x_c)`` through their centroids c_q,

        W_cq = w_q (1 - (d_q - dbar)^T M^+ dbar),   d_q = P (c_q - x_c),
        w_q = A_q / sum A,   dbar = sum w_q d_q,   M = sum w_q (d_q - dbar)(d_q - dbar)^T,

    (P projects on the plane of the set's area-weighted mean normal: 2-vectors,
    2 x 2 M), so
    each row sums to 1 and a radiosity linear over the surface (whose patch
    means are its values at the centroids) comes back exactly at every corner,
    however irregular the mesh. The plain area-weighted mean (``W_cq = w_q``)
    is off by ``g . dbar`` wherever the triangles around a vertex are lopsided,
    which drew the faint saw-tooth smudges under the Cornell box's ceiling,
    where the direct light falls steeply toward the corner. A set whose
    centroids do not span a plane (one or two triangles) is fitted along what
    they span. A corner whose set has zero total area takes its own
    triangle's value.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (3t, t)

    Notes
    -----
    The fit extrapolates at a surface's border; :func:`corner_smoother` clips
    each corner to the range of its set's values so no new extremes appear.
    """
    from scipy import sparse

    t = scene.n_triangles
    if t == 0:
        return sparse.csr_matrix((0, 0))
    a, b, _ = _corner_pairs(scene, crease_angle)
    fb = b // 3
    area = scene.triangle_areas[fb]
    total = np.bincount(a, weights=area, minlength=3 * t)
    ok = total[a] > 0
    a, fb = a[ok], fb[ok]
    w = area[ok] / total[a]
    corner_pos = scene.vertices[scene.faces].reshape(-1, 3)
    d3 = scene.vertices[scene.faces].mean(axis=1)[fb] - corner_pos[a]        # (pairs, 3), metres
    # fit in the plane of the set's area-weighted mean normal: the same for every corner that shares
    # the vertex and the set, so those corners get one value (the picture stays continuous)
    normal = np.stack([np.bincount(a, weights=w * scene.triangle_normals[fb, i], minlength=3 * t)
                       for i in range(3)], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    e1, e2 = _tangent_basis(normal)
    d = np.stack([np.einsum("ij,ij->i", d3, e1[a]), np.einsum("ij,ij->i", d3, e2[a])], axis=1)
    dbar = np.stack([np.bincount(a, weights=w * d[:, i], minlength=3 * t) for i in range(2)], axis=1)
    e = d - dbar[a]
    Mxx, Mxy, Myy = (np.bincount(a, weights=w * e[:, i] * e[:, j], minlength=3 * t) for i, j in ((0, 0), (0, 1), (1, 1)))
    fit = _pinv2_times(Mxx, Mxy, Myy, dbar)                                      # (3t, 2): M^+ dbar
    vals = w * (1.0 - np.einsum("ij,ij->i", e, fit[a]))
    lonely = np.flatnonzero(total <= 0)  # fallback: the triangle's own value
    rows = np.concatenate([a, lonely])
    cols = np.concatenate([fb, lonely // 3])
    vals = np.concatenate([vals, np.ones(len(lonely))])
    return sparse.csr_matrix((vals, (rows, cols)), shape=(3 * t, t))


def _tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (t, 3) unit vectors spanning the plane of each unit normal."""
    helper = np.zeros_like(normals)
    helper[np.arange(len(normals)), np.argmin(np.abs(normals), axis=1)] = 1.0   # the axis least along n
    e1 = np.cross(normals, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    return e1, np.cross(normals, e1)


def _pinv2_times(a: np.ndarray, b: np.ndarray, c: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(m, 2): the pseudo-inverse of each symmetric PSD [[a, b], [b, c]] times the rows of v (m, 2).

    Full rank: the adjugate over the determinant. Where the smaller eigenvalue is below 1e-6 of the
    larger (centroids on a line, or one), the matrix is ``lam u u^T`` with ``lam`` its trace, whose
    pseudo-inverse is ``M / lam^2``; its rounding noise across the line is not inverted.
    """
    trace = a + c
    det = a * c - b * b
    half_gap = np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    small, large = 0.5 * trace - half_gap, 0.5 * trace + half_gap
    full = small > 1e-6 * large
    x, y = v[:, 0], v[:, 1]
    inv_det = np.where(full, 1.0 / np.where(full, det, 1.0), 0.0)
    inv_lam2 = np.where(~full & (trace > 0), 1.0 / np.where(trace > 0, trace, 1.0) ** 2, 0.0)
    out_full = np.stack([c * x - b * y, -b * x + a * y], axis=1) * inv_det[:, None]
    out_line = np.stack([a * x + b * y, b * x + c * y], axis=1) * inv_lam2[:, None]
    return np.where(full[:, None], out_full, out_line)


def _clip_to_set(W, values: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Corner values clipped to the range of the values their row of W draws on (a slope limiter)."""
    v = values[W.indices]
    starts = W.indptr[:-1]
    return np.clip(corners, np.minimum.reduceat(v, starts), np.maximum.reduceat(v, starts))


def patch_field_weights(scene, *, crease_angle: float = CREASE_ANGLE):
    """(3t, n) sparse matrix P: corner values are ``P @ B`` for per-patch radiosity B.

    The partition-of-unity blend of a clustered scene's patches (see the
    module docstring); each row sums to 1.
    """
    from scipy import sparse

    t, n = scene.n_triangles, scene.n_patches
    a, b, _ = _corner_pairs(scene, crease_angle)
    patch = scene.patch_of_triangle
    # S(c): patches touching corner c's vertex in its smoothing set
    touch = np.unique(a * n + patch[b // 3])
    ca, cp = touch // n, touch % n
    # neighbours of each patch on the same smooth surface (itself included)
    link = np.unique(patch[ca // 3] * n + cp)
    lp, lq = link // n, link % n
    first = np.searchsorted(lp, np.arange(n + 1))
    # candidates of corner c: the neighbours of every patch in S(c)
    deg = first[cp + 1] - first[cp]
    rep = np.repeat(np.arange(len(ca)), deg)
    offset = np.arange(len(rep)) - np.repeat(np.cumsum(deg) - deg, deg)
    cand = np.unique(ca[rep] * n + lq[first[cp[rep]] + offset])
    rows, cols = cand // n, cand % n
    own = np.isin(cand, touch, assume_unique=True)
    corner_pos = scene.vertices[scene.faces].reshape(-1, 3)
    centroids = scene.centroids
    radius = np.zeros(n)
    np.maximum.at(radius, np.repeat(patch, 3), np.linalg.norm(corner_pos - centroids[np.repeat(patch, 3)], axis=1))
    dist = np.linalg.norm(corner_pos[rows] - centroids[cols], axis=1)
    w = np.clip(1.0 - dist / np.maximum(RHO * radius[cols], 1e-300), 0.0, None) ** 2 + _OWN_FLOOR * own
    total = np.bincount(rows, weights=w, minlength=3 * t)
    return sparse.csr_matrix((w / total[rows], (rows, cols)), shape=(3 * t, n))


def corner_smoother(scene, *, crease_angle: float = CREASE_ANGLE) -> Callable[[np.ndarray], np.ndarray]:
    """``smooth(radiosity) -> (t, 3, 3)``: :func:`smooth_corners` with its sparse weights built once.

    For smoothing many radiosities of one scene (the viewer does, per slider
    move): each call costs one sparse product, O(20 t).
    """
    t = scene.n_triangles
    if scene.is_clustered:
        P = patch_field_weights(scene, crease_angle=crease_angle)

        def smooth_clustered(radiosity: np.ndarray) -> np.ndarray:
            B = np.asarray(radiosity, dtype=np.float64).reshape(scene.n_patches, 3)
            return np.asarray(P @ B).reshape(t, 3, 3)

        return smooth_clustered
    W = corner_weights(scene, crease_angle=crease_angle)

    def smooth(radiosity: np.ndarray) -> np.ndarray:
        values = np.asarray(radiosity, dtype=np.float64).reshape(scene.n_patches, 3)
        if t == 0:
            return np.zeros((0, 3, 3))
        return _clip_to_set(W, values, np.asarray(W @ values)).reshape(t, 3, 3)

    return smooth


def smooth_corners(scene, radiosity: np.ndarray, *, crease_angle: float = CREASE_ANGLE) -> np.ndarray:
    """(t, 3, 3) float: radiosity at each detail triangle's corners (triangle, corner, channel).

    Parameters
    ----------
    scene : Scene
    radiosity : (n, 3) float, W/m^2
        Per patch.
    crease_angle : float, degrees
        Triangles whose normals differ by more than this are not averaged.

    Notes
    -----
    Cost O(sum of vertex degree^2), about 20 t for subdivided meshes.
    A corner whose smoothing set has zero total area keeps its triangle's value.
    To smooth many radiosities of one scene, build :func:`corner_smoother` once.

    Examples
    --------
    >>> from hfrad.scene.builtin import furnace
    >>> from hfrad.scene.patches import subdivide
    >>> s = subdivide(furnace(), patches=200)
    >>> c = smooth_corners(s, np.full((s.n_patches, 3), 2.0))
    >>> bool(np.allclose(c, 2.0))
    True
    """
    return corner_smoother(scene, crease_angle=crease_angle)(radiosity)


def corner_vertices(scene, *, crease_angle: float = CREASE_ANGLE) -> tuple[np.ndarray, np.ndarray]:
    """Split the patch mesh along creases and material borders.

    Two corners at one welded vertex share an output vertex when their
    smoothing sets (see the module docstring) are the same set of patches, so
    :func:`smooth_corners` gives them the same value; corners across a crease
    or a material border get separate vertices.

    Returns
    -------
    vertices : (v, 3) float, metres
    faces : (t, 3) int
        Same triangle order as ``scene.faces``.
    """
    n = scene.n_triangles
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    a, b, start = _corner_pairs(scene, crease_angle)
    # Order-independent hash of each corner's smoothing set: the sum (mod 2^64)
    # of a fixed random 64-bit key per patch. Equal sets give equal sums;
    # different sets collide with probability ~2^-64.
    keys = np.random.default_rng(0x5EED).integers(0, 2**63, size=n, dtype=np.int64).view(np.uint64)
    set_hash = np.add.reduceat(keys[b // 3], start[:-1])  # every corner has >= 1 partner (itself)
    vid = weld(scene.vertices, scene.faces).reshape(-1)
    pair = np.stack([vid.astype(np.uint64), set_hash], axis=1)
    _, first, inverse = np.unique(pair, axis=0, return_index=True, return_inverse=True)
    corner_pos = scene.vertices[scene.faces].reshape(-1, 3)
    return corner_pos[first], inverse.reshape(n, 3)


def interpolate(corners: np.ndarray, face: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(r, 3) float: barycentric interpolation of per-corner values at ray hits.

    Parameters
    ----------
    corners : (t, 3, 3) float
        Values at the corners of each triangle.
    face : (r,) int, triangle hit (>= 0)
    uv : (r, 2) float
        Barycentric weights of corners 1 and 2 (corner 0 gets 1 - u - v).
    """
    c = corners[face]
    u, v = uv[:, :1], uv[:, 1:2]
    return (1.0 - u - v) * c[:, 0] + u * c[:, 1] + v * c[:, 2]
