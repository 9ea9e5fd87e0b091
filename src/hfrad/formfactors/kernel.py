"""Unoccluded patch-to-patch form factors: Lambert's contour integral, numba kernel.

For a differential area dA at x (unit normal n) and a planar polygon P whose
vertices are v_1..v_m, Lambert's closed form (the contour integral of the
differential-area-to-polygon view factor) is

    F_{dA->P} = (1 / 2 pi) |sum_e gamma_e  n . (r_e x r_{e+1}) / |r_e x r_{e+1}||   (1)

with r_e = v_e - x and gamma_e the angle between r_e and r_{e+1}. Eq. (1) is
exact for a polygon lying in the closed half-space in front of x, so P is first
clipped to that half-space (Sutherland-Hodgman; the cos(theta_x) >= 0 clamp),
and x must lie strictly in front of P's plane (the cos(theta_y) >= 0 clamp).

The patch-to-patch quantity A_i F_ij = int_i int_j cos cos / (pi r^2) is the
same integral seen from either side, so it is estimated symmetrically:

    A_i F_ij := 1/2 (A_i mean_{x in i} F_{dx->j} + A_j mean_{y in j} F_{dy->i})  (2)

which makes reciprocity A_i F_ij = A_j F_ji hold to rounding by construction.
The integration over the polygon is exact; only the outer mean over points of
the other patch is a quadrature:

- far pairs: the centroid (1 point, error O((h/d)^2));
- the *near-field path*: pairs whose centroid distance is below
  ``near * (diam_i + diam_j)`` use the centroids of an s x s split of each
  triangle (s^2 equal-area points, default 4 x 4 = 16). Adjacent patches
  (sharing an edge or a vertex, e.g. at room corners) take this path; their
  quadrature points lie strictly inside the triangles, so they never touch the
  other polygon and eq. (1) stays finite (a zero cross product contributes 0).

Facing-away pairs, coplanar pairs and a patch with itself give exactly 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Bumped whenever the numbers produced by this module change (cache keys use it).
KERNEL_VERSION = 2

#: Pairs closer than NEAR * (diam_i + diam_j) take the near-field path.
NEAR = 1.0

#: Near-field rule: centroids of an NEAR_SPLITS x NEAR_SPLITS split (16 points).
NEAR_SPLITS = 4

#: Near-field side weights ~ (other patch's area)^power (see _near_field_area_ff).
NEAR_WEIGHT_POWER = 4.0

_INV_2PI = 1.0 / (2.0 * math.pi)


def split_centroids(m: int) -> np.ndarray:
    """Barycentric weights (m*m, 3) of the centroids of an m x m triangle split.

    The m^2 sub-triangles have equal areas, so equal weights give the
    composite centroid rule. All points are strictly inside the triangle.
    """
    if m < 1:
        raise ValueError(f"split count must be >= 1, got {m}")
    out = []
    for j in range(m):
        for i in range(m - j):
            # upright sub-triangle with lattice corners (i,j), (i+1,j), (i,j+1)
            out.append(((3 * i + 1) / (3 * m), (3 * j + 1) / (3 * m)))
            if i + j + 2 <= m:  # inverted one: (i+1,j), (i+1,j+1), (i,j+1)
                out.append(((3 * i + 2) / (3 * m), (3 * j + 2) / (3 * m)))
    w = np.array(out)
    return np.column_stack([1.0 - w[:, 0] - w[:, 1], w[:, 0], w[:, 1]])


def points_on_triangles(triangles: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n, q, 3) points with barycentric ``weights`` (q, 3) on each of (n, 3, 3) triangles."""
    return np.einsum("qk,nkd->nqd", weights, triangles)


class PatchGeometry:
    """Arrays the kernels read, derived once from a Scene (all float64, C order).

    Attributes
    ----------
    centre : (3,) the scene's bounding-box centre; positions below are relative to it
    triangles : (n, 3, 3)
    normals : (n, 3) unit (zero for a degenerate patch)
    areas : (n,)
    centroids : (n, 3)
    diameters : (n,) longest edge
    near_points : (n, q, 3) near-field quadrature points
    eps : float, length tolerance for "in the plane" (1e-9 x scene size)
    near : float, near-field threshold (see module docstring)
    """

    def __init__(self, scene, *, near: float = NEAR, near_splits: int = NEAR_SPLITS) -> None:
        # Coordinates relative to the scene's centre: the plane tests compare with
        # eps = 1e-9 x scene size, which must stay above the rounding of the coordinates.
        self.centre = 0.5 * (scene.bounds[0] + scene.bounds[1]) if scene.n_patches else np.zeros(3)
        tri = np.ascontiguousarray(np.asarray(scene.triangles, dtype=np.float64) - self.centre)
        self.triangles = tri
        self.normals = np.ascontiguousarray(scene.normals, dtype=np.float64)
        self.areas = np.ascontiguousarray(scene.areas, dtype=np.float64)
        self.centroids = np.ascontiguousarray(tri.mean(axis=1))
        edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)
        self.diameters = np.ascontiguousarray(np.linalg.norm(edges, axis=2).max(axis=1) if len(tri) else np.zeros(0))
        self.near_points = np.ascontiguousarray(points_on_triangles(tri, split_centroids(near_splits)))
        size = float(np.ptp(scene.bounds, axis=0).max()) if len(tri) else 1.0
        self.scale = size if size > 0 else 1.0
        self.eps = 1e-9 * self.scale
        self.near = float(near)
        self.near_splits = int(near_splits)

    @property
    def n(self) -> int:
        return len(self.areas)


# ---------------------------------------------------------------------------
# numba kernels (trust their input; validation happens in blocks.py)


@njit(cache=True, fastmath=False)
def _edge_term(ax, ay, az, bx, by, bz, nx, ny, nz):
    """gamma * n . unit(a x b) for one polygon edge seen from the origin."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    s = math.sqrt(cx * cx + cy * cy + cz * cz)
    if s == 0.0:  # x on the edge's line (or a zero-length edge): contributes 0
        return 0.0
    gamma = math.atan2(s, ax * bx + ay * by + az * bz)
    return gamma * (nx * cx + ny * cy + nz * cz) / s


@njit(cache=True, fastmath=False)
def _clipped_sum(r, d, nx, ny, nz):
    """Eq. (1) sum for triangle r (3, 3) (relative to x) clipped to d >= 0."""
    poly = np.empty((4, 3))
    m = 0
    for k in range(3):
        k1 = (k + 1) % 3
        if d[k] >= 0.0:
            poly[m, 0] = r[k, 0]
            poly[m, 1] = r[k, 1]
            poly[m, 2] = r[k, 2]
            m += 1
        if (d[k] >= 0.0) != (d[k1] >= 0.0):
            t = d[k] / (d[k] - d[k1])
            poly[m, 0] = r[k, 0] + t * (r[k1, 0] - r[k, 0])
            poly[m, 1] = r[k, 1] + t * (r[k1, 1] - r[k, 1])
            poly[m, 2] = r[k, 2] + t * (r[k1, 2] - r[k, 2])
            m += 1
    s = 0.0
    for k in range(m):
        k1 = (k + 1) % m
        s += _edge_term(poly[k, 0], poly[k, 1], poly[k, 2], poly[k1, 0], poly[k1, 1], poly[k1, 2], nx, ny, nz)
    return s


@njit(cache=True, fastmath=False)
def _point_to_patch(x, y, z, nx, ny, nz, T, N, j, eps):
    """F_{dA -> patch j} for dA at (x, y, z) with normal n: eq. (1) with both clamps."""
    # cos(theta_y) >= 0: the point must be strictly in front of patch j's plane
    if N[j, 0] * (x - T[j, 0, 0]) + N[j, 1] * (y - T[j, 0, 1]) + N[j, 2] * (z - T[j, 0, 2]) <= eps:
        return 0.0
    ax = T[j, 0, 0] - x
    ay = T[j, 0, 1] - y
    az = T[j, 0, 2] - z
    bx = T[j, 1, 0] - x
    by = T[j, 1, 1] - y
    bz = T[j, 1, 2] - z
    cx = T[j, 2, 0] - x
    cy = T[j, 2, 1] - y
    cz = T[j, 2, 2] - z
    da = nx * ax + ny * ay + nz * az
    db = nx * bx + ny * by + nz * bz
    dc = nx * cx + ny * cy + nz * cz
    if da <= eps and db <= eps and dc <= eps:  # behind, or in, the tangent plane of dA
        return 0.0
    if da >= -eps and db >= -eps and dc >= -eps:  # wholly in front: no clipping
        s = (_edge_term(ax, ay, az, bx, by, bz, nx, ny, nz)
             + _edge_term(bx, by, bz, cx, cy, cz, nx, ny, nz)
             + _edge_term(cx, cy, cz, ax, ay, az, nx, ny, nz))
    else:  # cos(theta_x) >= 0: keep the part in front of dA (rare)
        r = np.empty((3, 3))
        r[0, 0], r[0, 1], r[0, 2] = ax, ay, az
        r[1, 0], r[1, 1], r[1, 2] = bx, by, bz
        r[2, 0], r[2, 1], r[2, 2] = cx, cy, cz
        d = np.empty(3)
        d[0], d[1], d[2] = da, db, dc
        s = _clipped_sum(r, d, nx, ny, nz)
    return abs(s) * _INV_2PI


@njit(cache=True, fastmath=False)
def _pair_area_ff(i, j, T, N, A, C, D, Q, near, eps):
    """A_i F_ij (unoccluded) by the symmetric estimate, eq. (2)."""
    if i == j or A[i] <= 0.0 or A[j] <= 0.0:
        return 0.0
    dx = C[i, 0] - C[j, 0]
    dy = C[i, 1] - C[j, 1]
    dz = C[i, 2] - C[j, 2]
    lim = near * (D[i] + D[j])
    if dx * dx + dy * dy + dz * dz < lim * lim:
        return _near_field_area_ff(i, j, T, N, A, Q, eps)
    g_ij = _point_to_patch(C[i, 0], C[i, 1], C[i, 2], N[i, 0], N[i, 1], N[i, 2], T, N, j, eps)
    g_ji = _point_to_patch(C[j, 0], C[j, 1], C[j, 2], N[j, 0], N[j, 1], N[j, 2], T, N, i, eps)
    return 0.5 * (A[i] * g_ij + A[j] * g_ji)


@njit(cache=True, fastmath=False)
def _near_field_area_ff(i, j, T, N, A, Q, eps):
    """Near-field path of eq. (2): composite centroid rule on both patches."""
    q = Q.shape[1]
    g_ij = 0.0
    g_ji = 0.0
    for k in range(q):
        g_ij += _point_to_patch(Q[i, k, 0], Q[i, k, 1], Q[i, k, 2], N[i, 0], N[i, 1], N[i, 2], T, N, j, eps)
        g_ji += _point_to_patch(Q[j, k, 0], Q[j, k, 1], Q[j, k, 2], N[j, 0], N[j, 1], N[j, 2], T, N, i, eps)
    # Weight each side by the other's area^p: the points of the smaller patch
    # resolve the interaction, the polygon integral over the larger one is exact.
    # Symmetric in (i, j) bit for bit (x + y == y + x), so reciprocity is kept.
    a_i = A[i] ** NEAR_WEIGHT_POWER
    a_j = A[j] ** NEAR_WEIGHT_POWER
    w_i = a_j / (a_i + a_j)
    w_j = a_i / (a_i + a_j)
    return (w_i * A[i] * g_ij + w_j * A[j] * g_ji) / q


@njit(parallel=True, cache=True, fastmath=False, nogil=True)
def _unoccluded_block(T, N, A, C, D, Q, rows, cols, near, eps, out):
    """out[r, c] = F[rows[r], cols[c]] without visibility (parallel over rows)."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        for c in range(cols.shape[0]):
            j = cols[c]
            af = _pair_area_ff(i, j, T, N, A, C, D, Q, near, eps)
            out[r, c] = af / A[i] if af > 0.0 else 0.0


def unoccluded_block(geom: PatchGeometry, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(len(rows), len(cols)) float64: F[rows][:, cols] without visibility.

    Parameters
    ----------
    geom : PatchGeometry
    rows, cols : (r,), (c,) int
        Patch indices (the scene's order).
    """
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    out = np.empty((len(rows), len(cols)))
    if out.size:
        _unoccluded_block(geom.triangles, geom.normals, geom.areas, geom.centroids, geom.diameters,
                          geom.near_points, rows, cols, geom.near, geom.eps, out)
    return out


@njit(cache=True, fastmath=False)
def _point_to_patch_many(P, n, T, N, j, eps, out):
    for k in range(P.shape[0]):
        out[k] = _point_to_patch(P[k, 0], P[k, 1], P[k, 2], n[0], n[1], n[2], T, N, j, eps)


def point_to_patch(points: np.ndarray, normal: np.ndarray, triangle: np.ndarray) -> np.ndarray:
    """(p,) exact unoccluded F from differential areas at ``points`` to one triangle.

    Parameters
    ----------
    points : (p, 3) float
    normal : (3,) float, unit normal of the differential areas
    triangle : (3, 3) float, counter-clockwise seen from its front
    """
    T = np.ascontiguousarray(np.asarray(triangle, np.float64).reshape(1, 3, 3))
    cr = np.cross(T[0, 1] - T[0, 0], T[0, 2] - T[0, 0])
    N = (cr / np.linalg.norm(cr)).reshape(1, 3)
    P = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    out = np.empty(len(P))
    _point_to_patch_many(P, np.asarray(normal, np.float64), T, N, 0, 1e-12, out)
    return out
