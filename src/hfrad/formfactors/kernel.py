"""Unoccluded patch-to-patch form factors: Lambert's contour integral, numba kernel.

For a differential area dA at x (unit normal n) and a planar polygon P whose
vertices are v_1..v_m, Lambert's closed form (the contour integral of the
differential-area-to-polygon view factor) is

    F_{dA->P} = (1 / 2 pi) |sum_e gamma_e  n . (r_e x r_{e+1}) / |r_e x r_{e+1}||   (1)

with r_e = v_e - x and gamma_e the angle between r_e and r_{e+1}. Eq. (1) is
exact for a polygon lying in the closed half-space in front of x, so P is first
clipped to that half-space (Sutherland-Hodgman; the cos(theta_x) >= 0 clamp),
and x must lie strictly in front of P's plane (the cos(theta_y) >= 0 clamp).

A patch is a set of triangles (CSR lists, one triangle per patch unless the
scene is clustered); A_i F_ij = sum over triangle pairs (t in i, u in j) of

    A_t F_tu = int_t F_{dx->u} dA_x                                            (2)

The polygon integral (1) is exact; only the outer integral over the point
triangle is a quadrature, chosen per triangle pair by its centroid distance d
and diameters (longest edges) D_t, D_u:

- *distant* pairs, d >= FAR * (D_t + D_u) (FAR = 6): point to point between the
  centroids, A_t A_u cos_t cos_u / (pi d^2 + (A_t + A_u) / 2), symmetric by
  construction. The area term in the denominator is the exact correction for a
  point facing a coaxial disk (F = A / (pi h^2 + A)); it removes most of the
  midpoint rule's O((D/d)^2) bias for facing patches (without it the 12-split
  C-11 plates at d = 3 are 1.4e-3 off; with it 8.2e-4, the centroid rule there
  gave 7.0e-4). Almost all of the O(n^2) pairs of a large scene are distant,
  and this rule needs no arc tangent and no clipping (the far rule's two
  evaluations of (1) need both; F changes by ~7e-5 in the Frobenius norm);
- *far* pairs, near * (D_t + D_u) <= d < FAR * (D_t + D_u): the symmetric centroid rule
  1/2 (A_t F_{c_t->u} + A_u F_{c_u->t}), two evaluations of (1), relative error
  O((D/d)^2) (median 0.2% at the switch for the default ``near`` = 3, and the
  far pairs carry a small share of any row's sum);
- far or distant pairs where one triangle *straddles* the other's plane (corners
  on both sides; along the lines where two planes of the scene meet) are seen
  only in part, and the straddler's centroid may lie behind the other triangle:
  one evaluation of (1) from the other triangle's centroid, which (1) clips
  exactly (the symmetric rule counted such pairs at half: -1.5e-3 on the row sums
  of left-wall patches of the 10K Cornell box); nearer pairs put their
  quadrature points on the triangle that does not straddle;
- *middle* pairs, adaptive * (D_t + D_u) <= d < near * (D_t + D_u): one
  6-point rule exact for polynomials of degree 4 (Dunavant) on the smaller
  triangle, error O((D/d)^6) (median 2e-6, 95th percentile 1e-3 at the inner
  end, on random triangle pairs);
- *near* pairs (closer, which includes every pair sharing an edge or a vertex:
  its centroids are less than ~0.7 (D_t + D_u) apart): the
  *adaptive* path integrates over the smaller triangle (the point side; ties go
  to the lower index) by recursive 4-splitting. On every sub-triangle S two
  embedded rules are evaluated (9 points): Dunavant's 6-point rule Q6, exact to
  degree 4, and the 3-point rule Q3, exact to degree 2. S is accepted with
  value Q6(S) when |Q6(S) - Q3(S)| <= budget x area(S) / A_t, otherwise split
  into its four midpoint children; budget = tolerance x max(|A_t F_tu|, FLOOR A_t)
  (estimated on the whole triangle; FLOOR = 1% spares pairs that cannot matter).
  |Q6 - Q3| is essentially Q3's error, so Q6's own error is far below it
  (at the default tolerance, typically ~1e-5 relative and a few tens of
  evaluations of (1) per pair). The estimate converges to the exact
  double-area integral as ``tolerance`` -> 0, including edge- and
  vertex-sharing pairs (the integrand F_{dx->u} is bounded there; only its
  derivative is singular, which is where the splitting concentrates).
  Quadrature points lie strictly inside t, so (1)
  stays finite (a zero cross product contributes 0).

Why the switches are where they are: there are O(n^2) far pairs, so they get
the cheapest rule whose error stays near the default tolerance; middle and
near pairs are O(n) (at 10K Cornell patches, 7% and 2% of all pairs), so a
few to a few hundred evaluations each cost little.

Reciprocity is exact by construction: the pair (i, j) is always evaluated in
canonical order (lower patch index outer, point side chosen by a rule symmetric
in t and u), so A_i F_ij and A_j F_ji are the same floating-point number.
Facing-away pairs, coplanar pairs and a patch with itself give exactly 0.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from ..errors import InputError

#: Bumped whenever the numbers produced by this module change (cache keys use it).
#: 11: clustered touching pairs (clustered.py, ``_touching_area_ff``): the 3-point and 6-point
#: rules by distance, a budget shared per patch pair, and families of sub-triangles settled at once.
#: 10: visibility's second round picks its segments by kernel weight (visibility.IMPORTANCE).
#: 9: clustered patches (clustered.py): triangles at least POINT_FAR diameters from a quadrature
#: point take the disk-corrected point rule in eq. (3) there.
#: 8: visibility's second round from max(F_ij, F_ji) = 1e-4 (was 3e-4): every Cornell row closes.
#: 7: far pairs where one triangle straddles the other's plane integrate from the other's centroid;
#: kernel-weighted rays, 16 for the flagged pairs and 64 / 256 in the second round (visibility.py).
#: 6: probe rays first (probing.py); 5: point-to-point rule beyond FAR; 4: visibility's second round.
KERNEL_VERSION = 11

#: Triangle pairs closer than NEAR * (D_t + D_u) (centroid distance) leave the centroid rule.
NEAR = 3.0

#: Triangle pairs at least FAR * (D_t + D_u) apart are two points with the disk-corrected
#: point-to-point rule (see module docstring): no contour integral, no arc tangent.
FAR = 6.0

#: Triangle pairs closer than ADAPTIVE * (D_t + D_u) take the adaptive path.
ADAPTIVE = 1.5

#: Default relative tolerance of the adaptive path (per near triangle pair).
TOLERANCE = 1e-3

#: Deepest 4-split of the adaptive path (4^8 = 65,536 sub-triangles at most).
MAX_DEPTH = 8

#: The adaptive path's error budget is tolerance x max(A_t F_tu, FLOOR x A_t): a pair
#: whose form factor is below 1% needs no more than its share of a row's error.
FLOOR = 1e-2


_INV_2PI = 1.0 / (2.0 * math.pi)


def settings(*, near: float = NEAR, adaptive: float = ADAPTIVE, tolerance: float = TOLERANCE) -> dict:
    """The kernel's version and parameters, as recorded with results (.hfr files, cache keys)."""
    return {"kernel_version": KERNEL_VERSION, "far": FAR, "near": float(near), "adaptive": float(adaptive),
            "tolerance": float(tolerance)}


def split_centroids(m: int) -> np.ndarray:
    """Barycentric weights (m*m, 3) of the centroids of an m x m triangle split.

    The m^2 sub-triangles have equal areas, so equal weights give the
    composite centroid rule. All points are strictly inside the triangle.
    """
    if m < 1:
        raise InputError(f"split count must be >= 1, got {m}")
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


def patch_csr(scene) -> tuple[np.ndarray, np.ndarray]:
    """(start (n + 1,), index (t,)): the triangles of patch p are ``index[start[p]:start[p + 1]]``.

    Read from ``scene.patch_triangles`` when the scene has it (clustered
    patches); otherwise every patch is its own triangle.
    """
    csr = getattr(scene, "patch_triangles", None)
    if csr is not None:
        start, index = csr
        return np.ascontiguousarray(start, np.int64), np.ascontiguousarray(index, np.int64)
    t = len(scene.triangles)
    return np.arange(t + 1, dtype=np.int64), np.arange(t, dtype=np.int64)


class PatchGeometry:
    """Arrays the kernels read, derived once from a Scene (all float64, C order).

    Positions are relative to ``centre``, the scene's bounding-box centre: the
    plane tests compare with eps = 1e-9 x scene size, which must stay above the
    rounding of the coordinates even for scenes far from the origin.

    Attributes
    ----------
    centre : (3,)
    triangles : (t, 3, 3) corners of every triangle (of every patch)
    normals : (t, 3) unit (zero for a degenerate triangle)
    areas : (t,)
    centroids : (t, 3)
    diameters : (t,) longest edge
    start, index : (n + 1,), (t,) int, the triangles of each patch (see :func:`patch_csr`)
    patch_areas : (n,) sum of the areas of a patch's triangles
    eps : float, length tolerance for "in the plane" (1e-9 x scene size)
    near, adaptive : float, distance thresholds of the rules (see module docstring)
    tolerance : float, relative tolerance of the adaptive path
    """

    def __init__(self, scene, *, near: float = NEAR, adaptive: float = ADAPTIVE,
                 tolerance: float = TOLERANCE) -> None:
        if not (0 <= adaptive <= near and math.isfinite(near)):
            raise InputError(f"need finite 0 <= adaptive <= near, got adaptive={adaptive}, near={near}")
        if not (0 < tolerance < 1):
            raise InputError(f"tolerance must be in (0, 1), got {tolerance}")
        n_tri = len(scene.triangles)
        self.centre = 0.5 * (scene.bounds[0] + scene.bounds[1]) if n_tri else np.zeros(3)
        tri = np.ascontiguousarray(np.asarray(scene.triangles, dtype=np.float64) - self.centre)
        self.triangles = tri
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(cross, axis=1)
        self.areas = np.ascontiguousarray(0.5 * length)
        self.normals = np.ascontiguousarray(np.divide(cross, length[:, None], out=np.zeros_like(cross),
                                                      where=length[:, None] > 0))
        self.centroids = np.ascontiguousarray(tri.mean(axis=1))
        edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)
        self.diameters = np.ascontiguousarray(np.linalg.norm(edges, axis=2).max(axis=1) if n_tri else np.zeros(0))
        self.start, self.index = patch_csr(scene)
        self.patch_areas = np.add.reduceat(self.areas[self.index], self.start[:-1]) if n_tri else np.zeros(0)
        #: patch p is triangle p (no clustering): the kernel skips the CSR loops
        self.one_triangle_per_patch = bool(len(self.start) == n_tri + 1
                                           and np.array_equal(self.index, np.arange(n_tri)))
        size = float(np.ptp(scene.bounds, axis=0).max()) if n_tri else 1.0
        self.scale = size if size > 0 else 1.0
        self.eps = 1e-9 * self.scale
        self.near = float(near)
        self.adaptive = float(adaptive)
        self.tolerance = float(tolerance)

    @property
    def n(self) -> int:
        """Number of patches."""
        return len(self.start) - 1


# ---------------------------------------------------------------------------
# numba kernels (trust their input; validation happens in blocks.py). The helpers called once
# per pair are inline="always": called as functions with a dozen array arguments, numba paid
# their reference counts on every pair (several times the pair's own arithmetic).


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


@njit(cache=True, fastmath=False, inline="always")
def _append(s, m, fx, fy, fz, px, py, pz, x, y, z, nx, ny, nz):
    """Add vertex (x, y, z) to a polygon being summed edge by edge: the edge from the previous
    vertex p (none for the first, which is kept as f to close the polygon)."""
    if m > 0:
        s += _edge_term(px, py, pz, x, y, z, nx, ny, nz)
    else:
        fx, fy, fz = x, y, z
    return s, m + 1, fx, fy, fz, x, y, z


@njit(cache=True, fastmath=False)
def _clipped_sum(ax, ay, az, bx, by, bz, cx, cy, cz, da, db, dc, nx, ny, nz):
    """Eq. (1) sum for the triangle (a, b, c) (relative to x) clipped to d >= 0 (d: the corners'
    heights over x's tangent plane). Scalars, no arrays: in touching clusters (perpendicular
    walls, folds) many points see a neighbour triangle across their plane, and three heap
    arrays a call cost more than the arc tangents. The edges are summed in the polygon's order,
    first to last, then the closing edge."""
    s = 0.0
    m = 0
    fx = fy = fz = px = py = pz = 0.0
    for k in range(3):
        if k == 0:
            x0, y0, z0, d0, x1, y1, z1, d1 = ax, ay, az, da, bx, by, bz, db
        elif k == 1:
            x0, y0, z0, d0, x1, y1, z1, d1 = bx, by, bz, db, cx, cy, cz, dc
        else:
            x0, y0, z0, d0, x1, y1, z1, d1 = cx, cy, cz, dc, ax, ay, az, da
        if d0 >= 0.0:
            s, m, fx, fy, fz, px, py, pz = _append(s, m, fx, fy, fz, px, py, pz, x0, y0, z0, nx, ny, nz)
        if (d0 >= 0.0) != (d1 >= 0.0):
            t = d0 / (d0 - d1)
            s, m, fx, fy, fz, px, py, pz = _append(s, m, fx, fy, fz, px, py, pz, x0 + t * (x1 - x0),
                                                   y0 + t * (y1 - y0), z0 + t * (z1 - z0), nx, ny, nz)
    if m > 0:
        s += _edge_term(px, py, pz, fx, fy, fz, nx, ny, nz)
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
    else:  # cos(theta_x) >= 0: keep the part in front of dA
        s = _clipped_sum(ax, ay, az, bx, by, bz, cx, cy, cz, da, db, dc, nx, ny, nz)
    return abs(s) * _INV_2PI


#: Dunavant's 6-point rule, exact for polynomials of degree 4 on a triangle
#: (barycentric (a, a, 1 - 2a) and permutations, weights summing to 1), then the
#: 3-point rule (1/6, 1/6, 2/3) exact to degree 2; all points strictly inside.
_RULE_A = (0.445948490915965, 0.108103018168070, 0.091576213509771, 0.816847572980459,
           1.0 / 6.0, 2.0 / 3.0)
_RULE_W = (0.223381589678011, 0.109951743655322)


@njit(cache=True, fastmath=False)
def _rules(x0, y0, z0, x1, y1, z1, x2, y2, z2, nx, ny, nz, T, N, u, eps, groups=3, first=0):
    """area(S) x quadratures of F_{dx->u} over the triangle S with corners (x_k, y_k, z_k).

    Returns (Q6, Q3): Dunavant's 6-point rule (exact to degree 4) and the
    3-point rule (2/3, 1/6, 1/6) (exact to degree 2). |Q6 - Q3| estimates the
    error of Q3 and bounds that of Q6 (much smaller for a smooth integrand).
    ``groups`` = 2: Q6 alone (the same number), Q3 returned as 0: the middle
    distance's one degree-4 rule, which used to evaluate and discard Q3's three
    points (a third of its work; clustered Sponza's touching pairs: ~38 such triangle pairs each).
    ``first`` = 2 (with ``groups`` = 3): Q3 alone, Q6 returned as 0 (the clustered touching
    rule's triangle pairs at least 1 (D_t + D_u) apart).
    Corners come as scalars: the adaptive path calls this once per sub-triangle,
    and small arrays there cost a heap allocation each.
    """
    e1x, e1y, e1z = x1 - x0, y1 - y0, z1 - z0
    e2x, e2y, e2z = x2 - x0, y2 - y0, z2 - z0
    cx = e1y * e2z - e1z * e2y
    cy = e1z * e2x - e1x * e2z
    cz = e1x * e2y - e1y * e2x
    area = 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)
    q6 = 0.0
    q3 = 0.0
    for g in range(first, groups):
        a = _RULE_A[2 * g]  # two corners get weight a, the third b = 1 - 2a
        b = _RULE_A[2 * g + 1]
        acc = 0.0
        for k in range(3):
            w0 = b if k == 0 else a
            w1 = b if k == 1 else a
            w2 = b if k == 2 else a
            x = w0 * x0 + w1 * x1 + w2 * x2
            y = w0 * y0 + w1 * y1 + w2 * y2
            z = w0 * z0 + w1 * z1 + w2 * z2
            acc += _point_to_patch(x, y, z, nx, ny, nz, T, N, u, eps)
        if g < 2:
            q6 += _RULE_W[g] * acc
        else:
            q3 = acc / 3.0
    return area * q6, area * q3


@njit(cache=True, fastmath=False)
def _adaptive_area_ff(p, u, T, N, A, eps, tol):
    """A_p F_pu: adaptive 4-split of triangle p against the exact polygon integral over u."""
    q6, q3 = _rules(T[p, 0, 0], T[p, 0, 1], T[p, 0, 2], T[p, 1, 0], T[p, 1, 1], T[p, 1, 2],
                    T[p, 2, 0], T[p, 2, 1], T[p, 2, 2], N[p, 0], N[p, 1], N[p, 2], T, N, u, eps)
    # tolerance x max(|A_p F_pu|, FLOOR A_p), from the first estimate
    # (an empty counter: counts nothing; cheaper than the stack the old loop allocated for every pair)
    return _refine(p, u, T, N, eps, q6, q3, tol * max(abs(q6), FLOOR * A[p]), np.empty(0, np.int64))


@njit(cache=True, fastmath=False)
def _refine(p, u, T, N, eps, q6, q3, budget, count, families=False):
    """A_p F_pu from the whole triangle p's two rules (q6, q3): q6 if they agree within ``budget``,
    else the sum over p's 4-split, each sub-triangle (area 4^-level of p's) accepted with its
    Q6 when its rules agree within its area's share of ``budget``, split again otherwise
    (MAX_DEPTH levels at most). ``count[0]`` (when given) gains the evaluations of eq. (1).

    ``families``: a sub-triangle that splits is also replaced by its four children's Q6 at once
    when their sum agrees with its own Q6 within its share of the budget. Q6's own error is far
    below |Q6 - Q3| (Q3's error), so the difference between a Q6 and the sum of its children's
    is the sharper estimate; without it, a child whose two rules differ splits again although
    the family as a whole is settled. (Off: the same numbers as the split alone.)
    """
    if abs(q6 - q3) <= budget or MAX_DEPTH <= 1:
        return q6
    nx, ny, nz = N[p, 0], N[p, 1], N[p, 2]
    size = 3 * MAX_DEPTH + 8  # depth-first stack of sub-triangles: 9 coordinates, Q6, Q3; their depths
    stack = np.empty((size, 11))
    depth = np.empty(size, np.int64)
    _put(stack[0], T[p, 0, 0], T[p, 0, 1], T[p, 0, 2], T[p, 1, 0], T[p, 1, 1], T[p, 1, 2],
         T[p, 2, 0], T[p, 2, 1], T[p, 2, 2])
    stack[0, 9] = q6
    stack[0, 10] = q3
    depth[0] = 0
    top = 1
    total = 0.0
    while top > 0:
        top -= 1
        lvl = depth[top]
        s = stack[top]
        x0, y0, z0, x1, y1, z1, x2, y2, z2 = s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7], s[8]
        q6 = s[9]
        share = budget * 0.25 ** lvl
        # accept when the two rules agree within this sub-triangle's share (area 4^-lvl) of the budget
        if lvl > 0 and (abs(q6 - s[10]) <= share or lvl + 1 >= MAX_DEPTH):
            total += q6
            continue
        _split(stack, depth, top, lvl, x0, y0, z0, x1, y1, z1, x2, y2, z2)
        children = 0.0
        for k in range(top, top + 4):
            c = stack[k]
            stack[k, 9], stack[k, 10] = _rules(c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8],
                                               nx, ny, nz, T, N, u, eps)
            children += stack[k, 9]
        if count.shape[0] > 0:
            count[0] += 36
        if families and abs(children - q6) <= share:
            total += children
            continue
        top += 4
    return total


@njit(cache=True, fastmath=False, inline="always")
def _split(stack, depth, top, lvl, x0, y0, z0, x1, y1, z1, x2, y2, z2):
    """Push the four midpoint children of a level-``lvl`` sub-triangle onto the stack at ``top``:
    (c0, m01, m20), (m01, c1, m12), (m20, m12, c2), (m12, m20, m01)."""
    ax, ay, az = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1)    # m01
    bx, by, bz = 0.5 * (x1 + x2), 0.5 * (y1 + y2), 0.5 * (z1 + z2)    # m12
    cx, cy, cz = 0.5 * (x2 + x0), 0.5 * (y2 + y0), 0.5 * (z2 + z0)    # m20
    _put(stack[top], x0, y0, z0, ax, ay, az, cx, cy, cz)
    _put(stack[top + 1], ax, ay, az, x1, y1, z1, bx, by, bz)
    _put(stack[top + 2], cx, cy, cz, bx, by, bz, x2, y2, z2)
    _put(stack[top + 3], bx, by, bz, cx, cy, cz, ax, ay, az)
    for k in range(4):
        depth[top + k] = lvl + 1


@njit(cache=True, fastmath=False, inline="always")
def _put(row, x0, y0, z0, x1, y1, z1, x2, y2, z2):
    """Write a sub-triangle's nine coordinates into a stack row."""
    row[0], row[1], row[2] = x0, y0, z0
    row[3], row[4], row[5] = x1, y1, z1
    row[6], row[7], row[8] = x2, y2, z2


@njit(cache=True, fastmath=False, inline="always")
def _behind(t, u, T, N, eps):
    """True if triangle t lies wholly on or behind the plane of u: then F_tu = F_ut = 0 exactly.

    (Every point of t fails the cos(theta_y) clamp of u; coplanar pairs, the
    most common near pairs, end here before any quadrature.)
    """
    for k in range(3):
        if (N[u, 0] * (T[t, k, 0] - T[u, 0, 0]) + N[u, 1] * (T[t, k, 1] - T[u, 0, 1])
                + N[u, 2] * (T[t, k, 2] - T[u, 0, 2])) > eps:
            return False
    return True


@njit(cache=True, fastmath=False, inline="always")
def _sides(t, u, T, N, eps):
    """(front, back): some corner of triangle t lies in front of u's plane (> eps), some behind (< -eps)."""
    front = False
    back = False
    for k in range(3):
        h = (N[u, 0] * (T[t, k, 0] - T[u, 0, 0]) + N[u, 1] * (T[t, k, 1] - T[u, 0, 1])
             + N[u, 2] * (T[t, k, 2] - T[u, 0, 2]))
        if h > eps:
            front = True
        elif h < -eps:
            back = True
    return front, back


@njit(cache=True, fastmath=False, inline="always")
def _triangle_pair_area_ff(t, u, T, N, A, C, D, near, adaptive, eps, tol):
    """A_t F_tu (unoccluded), eq. (2), by the rule for the pair's distance (symmetric in t, u).

    A triangle that straddles the other's plane (corners on both sides) is seen
    only in part, and its centroid may lie behind the other triangle: the
    centroid rules would count that side as 0 (half the symmetric rule, 100%
    of the point-to-point one). Such far pairs take one evaluation of (1) from
    the other triangle's centroid (that triangle is wholly in front, and (1)
    clips the straddler exactly); pairs where both straddle take the 6-point rule.
    Nearer pairs put their quadrature points on the triangle that does not straddle.
    """
    dx = C[t, 0] - C[u, 0]
    dy = C[t, 1] - C[u, 1]
    dz = C[t, 2] - C[u, 2]
    d2 = dx * dx + dy * dy + dz * dz
    s2 = (D[t] + D[u]) * (D[t] + D[u])
    if d2 >= FAR * FAR * s2 and d2 >= near * near * s2 and A[t] > 0.0 and A[u] > 0.0:
        # most of the O(n^2) pairs: distant, each centroid at least its own diameter in front of the
        # other's plane. Then no corner is behind (the corners average to the centroid) and neither
        # triangle straddles, so the tests below would reach the distant rule: take it at once
        # (the same expressions, so the same numbers to the last bit)
        cos_u = N[u, 0] * dx + N[u, 1] * dy + N[u, 2] * dz
        cos_t = -(N[t, 0] * dx + N[t, 1] * dy + N[t, 2] * dz)
        if cos_u >= D[t] and cos_t >= D[u] and cos_u > 4.0 * eps and cos_t > 4.0 * eps:
            return A[t] * A[u] * cos_t * cos_u / (d2 * (math.pi * d2 + 0.5 * (A[t] + A[u])))
        # a centroid a diameter behind the other's plane: every corner is behind it (a corner lies
        # within 2/3 of a median, less than a diameter, of the centroid), so _behind below says 0
        if cos_u <= -D[t] - 4.0 * eps or cos_t <= -D[u] - 4.0 * eps:
            return 0.0
    if A[t] <= 0.0 or A[u] <= 0.0 or _behind(t, u, T, N, eps) or _behind(u, t, T, N, eps):
        return 0.0
    straddle = False
    if d2 >= near * near * s2:
        # t can straddle u's plane only if its centroid is closer to that plane than D_t
        h_t = N[u, 0] * dx + N[u, 1] * dy + N[u, 2] * dz
        h_u = -(N[t, 0] * dx + N[t, 1] * dy + N[t, 2] * dz)
        back_t = abs(h_t) < D[t] and _sides(t, u, T, N, eps)[1]
        back_u = abs(h_u) < D[u] and _sides(u, t, T, N, eps)[1]
        straddle = back_t or back_u
        if straddle and not (back_t and back_u):
            if back_t:  # t straddles u's plane: integrate from u's centroid (u is wholly in front of t)
                return A[u] * _point_to_patch(C[u, 0], C[u, 1], C[u, 2], N[u, 0], N[u, 1], N[u, 2], T, N, t, eps)
            return A[t] * _point_to_patch(C[t, 0], C[t, 1], C[t, 2], N[t, 0], N[t, 1], N[t, 2], T, N, u, eps)
    if d2 >= FAR * FAR * s2 and d2 >= near * near * s2 and not straddle:
        # distant: centroid to centroid (both cosines at the centroids); near > FAR forces the rules below
        cos_t = -(N[t, 0] * dx + N[t, 1] * dy + N[t, 2] * dz)
        cos_u = N[u, 0] * dx + N[u, 1] * dy + N[u, 2] * dz
        if cos_t <= 0.0 or cos_u <= 0.0:
            return 0.0
        # cos_t cos_u here carry d^2 (unnormalized directions), hence the extra d2 below
        return A[t] * A[u] * cos_t * cos_u / (d2 * (math.pi * d2 + 0.5 * (A[t] + A[u])))
    if d2 >= near * near * s2 and not straddle:  # far: symmetric centroid rule
        g_tu = _point_to_patch(C[t, 0], C[t, 1], C[t, 2], N[t, 0], N[t, 1], N[t, 2], T, N, u, eps)
        g_ut = _point_to_patch(C[u, 0], C[u, 1], C[u, 2], N[u, 0], N[u, 1], N[u, 2], T, N, t, eps)
        return 0.5 * (A[t] * g_tu + A[u] * g_ut)
    p, q = _point_side(t, u, T, N, A, eps, straddle)
    if d2 >= adaptive * adaptive * s2:  # middle distance (or both straddle): one degree-4 rule
        return _rules(T[p, 0, 0], T[p, 0, 1], T[p, 0, 2], T[p, 1, 0], T[p, 1, 1], T[p, 1, 2],
                      T[p, 2, 0], T[p, 2, 1], T[p, 2, 2], N[p, 0], N[p, 1], N[p, 2], T, N, q, eps, 2)[0]
    return _adaptive_area_ff(p, q, T, N, A, eps, tol)


@njit(cache=True, fastmath=False, inline="always")
def _point_side(t, u, T, N, A, eps, straddle):
    """(p, q): the quadrature points go on p, eq. (1) integrates over q. The smaller triangle
    (ties: the lower index), but never one that straddles the other's plane when the other
    does not (its quadrature points could all fall behind and miss the part in front; not
    checked when ``straddle``, both do): a choice symmetric in (t, u)."""
    p, q = (t, u) if (A[t] < A[u] or (A[t] == A[u] and t < u)) else (u, t)
    if not straddle:
        back_t = _sides(t, u, T, N, eps)[1]
        back_u = _sides(u, t, T, N, eps)[1]
        if back_t != back_u:
            p, q = (u, t) if back_t else (t, u)
    return p, q


@njit(cache=True, fastmath=False, inline="always")
def _pair_area_ff(i, j, T, N, A, C, D, start, index, near, adaptive, eps, tol):
    """A_i F_ij (unoccluded): sum over the triangle pairs of patches i and j, in canonical order."""
    if i == j:
        return 0.0
    a = min(i, j)  # same summation order for (i, j) and (j, i): reciprocity to the last bit
    b = max(i, j)
    total = 0.0
    for s in range(start[a], start[a + 1]):
        t = index[s]
        for r in range(start[b], start[b + 1]):
            total += _triangle_pair_area_ff(t, index[r], T, N, A, C, D, near, adaptive, eps, tol)
    return total


@njit(parallel=True, cache=True, fastmath=False, nogil=True)
def _unoccluded_block(T, N, A, C, D, start, index, PA, rows, cols, near, adaptive, eps, tol, out, chunks):
    """out[r, c] = F[rows[r], cols[c]] without visibility (parallel over rows, dealt out in turn
    to ``chunks`` parts: see :func:`row_chunks`)."""
    for part in prange(chunks):
        for r in range(part, rows.shape[0], chunks):
            i = rows[r]
            for c in range(cols.shape[0]):
                j = cols[c]
                af = _pair_area_ff(i, j, T, N, A, C, D, start, index, near, adaptive, eps, tol)
                out[r, c] = af / PA[i] if af > 0.0 else 0.0


@njit(parallel=True, cache=True, fastmath=False, nogil=True, error_model="numpy")
def _unoccluded_block_triangles(T, N, A, C, D, rows, cols, near, adaptive, eps, tol, out, chunks):
    """:func:`_unoccluded_block` for scenes whose patches are single triangles (patch p is
    triangle p): no CSR loops per pair, the same numbers to the last bit (the sum of one term).

    Each row takes the distant pairs' shortcut of :func:`_triangle_pair_area_ff` first over all
    its columns at once (:func:`_distant_row`, branch-free: SIMD), then the pairs it leaves one
    by one. Rows are dealt out in turn to ``chunks`` parts (:func:`row_chunks`).
    """
    nc = cols.shape[0]
    # the columns' centroids, normals, areas and diameters, column index last
    col = np.empty((8, nc))
    for c in range(nc):
        j = cols[c]
        col[0, c], col[1, c], col[2, c] = C[j, 0], C[j, 1], C[j, 2]
        col[3, c], col[4, c], col[5, c] = N[j, 0], N[j, 1], N[j, 2]
        col[6, c], col[7, c] = A[j], D[j]
    nr = rows.shape[0]
    for part in prange(chunks):
        left = np.empty(nc, np.bool_)    # the pairs the shortcut does not decide
        for r in range(part, nr, chunks):
            i = rows[r]
            _distant_row(i, C[i, 0], C[i, 1], C[i, 2], N[i, 0], N[i, 1], N[i, 2], A[i], D[i], cols, col,
                         near, eps, out[r], left)
            for c in range(nc):
                if left[c]:
                    j = cols[c]
                    af = _triangle_pair_area_ff(min(i, j), max(i, j), T, N, A, C, D, near, adaptive, eps, tol)
                    out[r, c] = af / A[i] if af > 0.0 else 0.0


@njit(cache=True, fastmath=False, nogil=True, error_model="numpy")
def _distant_row(i, cx, cy, cz, nx, ny, nz, a, dm, cols, col, near, eps, out, left):
    """The distant shortcut of :func:`_triangle_pair_area_ff` for row patch i against every
    column, and the pairs its ``_behind`` test surely sets to 0: ``out[c]`` where one applies
    (the pair in canonical order, lower index first, by selects: the same expressions on the
    same numbers), ``left[c]`` where neither does.
    ``col`` (8, nc): the columns' centroids, normals, areas and diameters. Branch-free so that
    the loop runs in SIMD lanes (``error_model="numpy"``: no check for division by zero, whose
    lanes are discarded)."""
    for c in range(cols.shape[0]):
        lower = i < cols[c]            # i is the pair's first triangle t
        tx, ty, tz = (cx, cy, cz) if lower else (col[0, c], col[1, c], col[2, c])
        ux, uy, uz = (col[0, c], col[1, c], col[2, c]) if lower else (cx, cy, cz)
        tnx, tny, tnz = (nx, ny, nz) if lower else (col[3, c], col[4, c], col[5, c])
        unx, uny, unz = (col[3, c], col[4, c], col[5, c]) if lower else (nx, ny, nz)
        at, au = (a, col[6, c]) if lower else (col[6, c], a)
        dt, du = (dm, col[7, c]) if lower else (col[7, c], dm)
        dx = tx - ux
        dy = ty - uy
        dz = tz - uz
        d2 = dx * dx + dy * dy + dz * dz
        s2 = (dt + du) * (dt + du)
        far = d2 >= FAR * FAR * s2 and d2 >= near * near * s2 and at > 0.0 and au > 0.0
        cos_u = unx * dx + uny * dy + unz * dz
        cos_t = -(tnx * dx + tny * dy + tnz * dz)
        front = cos_u >= dt and cos_t >= du and cos_u > 4.0 * eps and cos_t > 4.0 * eps
        behind = cos_u <= -dt - 4.0 * eps or cos_t <= -du - 4.0 * eps
        af = at * au * cos_t * cos_u / (d2 * (math.pi * d2 + 0.5 * (at + au)))
        # _behind for sure (then 0 whatever the distance): a corner's height over the other plane
        # exceeds the centroid's by at most |n_t - n_u| D (a corner is within D of its centroid,
        # and level with it along its own normal), so a bound under eps / 2 leaves the rounding
        # of the heights (~1e-16 of the scene) far from eps: coplanar pairs, the commonest near ones
        dn = math.sqrt((nx - col[3, c]) ** 2 + (ny - col[4, c]) ** 2 + (nz - col[5, c]) ** 2)
        zero = cos_u + dn * dt <= 0.5 * eps or cos_t + dn * du <= 0.5 * eps or at <= 0.0 or au <= 0.0
        out[c] = af / a if far and front and af > 0.0 else 0.0
        left[c] = not (far and (front or behind) or zero) and i != cols[c]   # a patch and itself: 0


def row_chunks(rows: int) -> int:
    """Parts a block's rows go in for a numba loop: eight per thread, at most one per row, at least one.

    Row r goes to part r % chunks, so each part holds rows from the whole block: in the internal
    (Z-)order the costly near pairs of a column block are the rows next to its columns, and numba
    hands each thread a contiguous run of the parts, so contiguous runs of rows left one thread
    with nearly all of a block's work (clustered Sponza, 3,129 patches: 99% in one half).
    """
    return max(1, min(rows, 8 * numba.get_num_threads()))


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
    if out.size and geom.one_triangle_per_patch:
        _unoccluded_block_triangles(geom.triangles, geom.normals, geom.areas, geom.centroids, geom.diameters,
                                    rows, cols, geom.near, geom.adaptive, geom.eps, geom.tolerance, out,
                                    row_chunks(len(rows)))
    elif out.size:
        _unoccluded_block(geom.triangles, geom.normals, geom.areas, geom.centroids, geom.diameters,
                          geom.start, geom.index, geom.patch_areas, rows, cols, geom.near, geom.adaptive,
                          geom.eps, geom.tolerance, out, row_chunks(len(rows)))
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
