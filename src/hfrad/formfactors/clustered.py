"""Form factors between patches that are clusters of triangles.

A clustered patch P (see :mod:`hfrad.scene.cluster`) is a set of triangles t
with areas A_t and unit normals n_t; its area is A_P = sum A_t, its area
vector S_P = sum A_t n_t, its centroid c_P the area-weighted mean and its
diameter D_P twice the largest distance of a corner from c_P. The
differential-area-to-patch form factor is the sum of Lambert's contour
integrals over its triangles, each with its own clamps (kernel.py, eq. 1):

    F_{dx->P} = sum_{t in P} F_{dx->t}                                      (3)

and A_P F_PQ is estimated symmetrically, as for single triangles (kernel.py,
eq. 2), with a rule chosen by the centroid distance d:

- *far*, d >= FAR (D_P + D_Q), when P or Q has more than one triangle:
  both patches as points with their area vectors,
  A_P F_PQ = max(0, S_P . r) max(0, -S_Q . r) / (pi d^4), r = c_Q - c_P;
  one evaluation whatever the triangle counts, relative error O((D/d)^2);
- *quadrants*, FAR / 2 <= d / (D_P + D_Q) < FAR, a cluster involved: the same
  with each patch split into (up to) 4 groups of triangles by the quadrant of
  their centroid around the patch centroid (in its mean plane): 16 point
  pairs, a quarter of the error;
- *middle*, NEAR (D_P + D_Q) <= d: 1/2 (A_P F_{P->Q} + A_Q F_{Q->P}), where
  F_{P->Q} is the area-weighted mean of eq. (3) over the quadrant groups'
  centroids (with their mean normals; a one-triangle patch: its centroid
  alone), at most 4 (|P| + |Q|) contour integrals;
- *touching*, d < EXACT_NEAR (D_P + D_Q) and |P| |Q| <= EXACT_PAIRS:
  eq. (2) of kernel.py summed over every triangle pair (:func:`_touching_area_ff`):
  kernel.py's centroid rules beyond its NEAR, otherwise by the pair's centroid
  distance one point (from 2 (D_t + D_u)), the 3-point rule (from 1), Dunavant's 6-point rule (pairs
  surely apart), or, for pairs in contact, both and kernel.py's 4-split
  refinement to CLUSTER_TOLERANCE, with a tenth of the patch pair's tolerance
  shared among those pairs and a split settled as a family when its children's
  sum agrees with the parent. Touching clusters are where the 32-point rule
  below errs most (its points miss the integrand's peak along the shared
  edge); the sum costs |P| |Q| triangle pairs, hence the EXACT_PAIRS cap.
  Against the adaptive rule at 1e-5 on every triangle pair (3K patches; conference
  room, Sponza, Sibenik) it errs by 0.16%, 0.07%, 0.13% of the touching pairs'
  total with 0.44, 0.46, 0.40 times the contour integrals of kernel.py's rules per
  triangle pair (0.10%, 0.05%, 0.12%; benchmarks/README.md, "The touching rule");
- *near*, otherwise: up to 32 weighted quadrature points spread over each patch's
  triangles (a triangle gets the centroids of an m x m split, m ~ sqrt(16
  A_t / A_P), or, for patches of more than 16 triangles, 16 triangles are
  picked at equal steps of cumulative area) against eq. (3), each point
  with its own triangle's normal, weighted by the other patch's area^4 as
  the single-triangle near field does.

In eq. (3) a triangle u at least POINT_FAR = 4 of its diameters D_u from the point
x, and wholly in front of x's tangent plane, takes the disk-corrected point rule
F_{dx->u} ~ A_u cos_x cos_u / (pi r^2 + A_u) (exact for a coaxial disk; 0.2-0.4%
off for a triangle at 4 diameters) instead of eq. (1)'s three arc tangents; the
others eq. (1). A quadrature point of the middle and near rules sees most of the
other patch's triangles from that far (Sponza, 3,129 patches: the middle and near rules
about 3x cheaper, F moved by 6e-4 in the Frobenius norm, against
the rules' own 4.8% from an all-triangle-pairs reference).

A patch of more than KERNEL_TRIANGLES triangles (micro-triangle crumbs such
as screws that clustering joined to it) is integrated, as the target of eq.
(3), over its KERNEL_TRIANGLES largest triangles, the sum scaled by A_P / (their
area): the cost of a pair stays bounded; ``ClusterGeometry.dropped`` is the
area fraction left out per patch (for a check of the approximation's reach).

All three rules are symmetric in (P, Q), so A_P F_PQ = A_Q F_QP to rounding; the middle, near
and touching rules to the bit (their two halves are added in either order, the touching sum runs
in canonical order). Those rules are ~95% of the kernel's time on a real scene (Sponza, 3,129
patches: 24% of the pairs) and a pass over F's column blocks asks for nearly every pair twice, as
(P, Q) and as (Q, P) (the reciprocity copy takes only blocks 8 or more apart, and the diagonal
tiles hold both orders): :class:`ClusterGeometry` keeps each such pair's A_P F_PQ once computed
(the *memo*: one float64 a pair closer than FAR / 2 (D_P + D_Q), in a table fixed when the
geometry is built), and the second order reads it. F is the same to the bit, whatever the order
in which blocks and threads meet the pair.
A patch of one triangle gets the same points as in kernel.py (its centroid
far away, the 16 centroids of a 4 x 4 split near).
"""

from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit, prange

from ..scene.cluster import patch_diameters
from .kernel import (ADAPTIVE, FLOOR, NEAR as KERNEL_NEAR, PatchGeometry, _behind, _point_side, _point_to_patch,
                     _refine, _rules, _triangle_pair_area_ff, row_chunks, split_centroids, unoccluded_block)

#: Clustered pairs farther than FAR * (D_P + D_Q) are treated as two points.
FAR = 3.0

#: Pairs closer than NEAR * (D_P + D_Q) take the near-field quadrature.
NEAR = 1.0


#: Near pairs with at most this many triangle pairs take kernel.py's rules per triangle pair
#: (adaptive near rule, tolerance TOLERANCE), as unclustered patches do.
EXACT_PAIRS = 1024

#: ... and centroids closer than this times (D_P + D_Q) (touching pairs, where the 32-point rule errs most).
EXACT_NEAR = 0.7

#: Relative tolerance of kernel.py's adaptive rule on those pairs: looser than kernel.py's 1e-3,
#: which costs several times the kernel time there for a gain below the other rules' error.
CLUSTER_TOLERANCE = 3e-2

#: The touching rule's (c1_from, q3_from, gap, slack, families) (see :func:`_touching_area_ff`): the
#: centroid of the point side for triangle pairs from 2 (D_t + D_u) apart, the 3-point rule from 1,
#: the 6-point rule for those surely apart (gap 0), a tenth of the patch pair's tolerance shared
#: among its contact triangle pairs, and splits settled as families (1: on). Chosen on the
#: conference room, Sponza and Sibenik (benchmarks/README.md, "The touching rule").
TOUCHING_RULES = (2.0, 1.0, 0.0, 0.1, 1.0)

#: Most triangles of a patch that eq. (3) sums over (the largest; see the module docstring).
KERNEL_TRIANGLES = 256

#: In eq. (3), a triangle at least this many of its diameters from the point takes the
#: disk-corrected point rule instead of eq. (1) (see :func:`_point_to_cluster`).
POINT_FAR = 4.0

#: Quadrature points per patch in the near field (at most 2 x this with padding).
NEAR_POINTS = 16

#: Most pairs the memo keeps (12 bytes each: column and value, 200 MB at most); a scene with more
#: keeps none. Sponza: 1.19M pairs at 3,129 patches (14 MB, ~380 a patch), 3.56M at 20,102 (43 MB,
#: ~180 a patch); listing them is O(n^2) distance tests (~4 s at 20K patches on the loaded 2 cores).
MEMO_PAIRS = 1 << 24

_WEIGHT_POWER = 4.0
_INV_PI = 1.0 / math.pi


class ClusterGeometry:
    """Arrays the clustered kernel reads, derived once from a clustered Scene.

    Positions are relative to the scene's bounding-box centre (the plane tests
    use eps = 1e-9 x scene size). Triangles are stored patch by patch:
    patch p owns rows ``start[p]:start[p + 1]`` of ``triangles``.

    ``memo`` (default True): keep A_P F_PQ of the pairs closer than FAR / 2 (D_P + D_Q) once
    computed (``memo_start``, ``memo_cols``, ``memo_values``, :func:`memo_table`; see the
    module docstring); False computes every pair each time it is asked for (the same numbers).
    ``touching_rules``: the touching rule's (c1_from, q3_from, gap, slack, families), default
    :data:`TOUCHING_RULES` (for measurements of other choices, as in benchmarks/bench_touching.py).
    """

    clustered = True

    def __init__(self, scene, *, far: float = FAR, near: float = NEAR, tolerance: float = CLUSTER_TOLERANCE,
                 exact_pairs: int = EXACT_PAIRS, exact_near: float = EXACT_NEAR,
                 point_far: float = POINT_FAR, memo: bool = True, touching_rules=None) -> None:
        start, index = scene.patch_triangles
        self.centre = 0.5 * (scene.bounds[0] + scene.bounds[1]) if scene.n_triangles else np.zeros(3)
        tri = np.ascontiguousarray(scene.triangles[index] - self.centre)
        self.start = np.ascontiguousarray(start, np.int64)
        self.triangles = tri
        self.tri_normals = np.ascontiguousarray(scene.triangle_normals[index], np.float64)
        self.tri_areas = np.ascontiguousarray(scene.triangle_areas[index], np.float64)
        self.areas = np.ascontiguousarray(scene.areas, np.float64)
        self.area_vectors = np.ascontiguousarray(scene.area_vectors, np.float64)
        self.normals = np.ascontiguousarray(scene.normals, np.float64)
        self.centroids = np.ascontiguousarray(scene.centroids - self.centre)
        self.diameters = np.ascontiguousarray(patch_diameters(scene), np.float64)
        self.mid_points, self.mid_normals, self.mid_vectors, self.mid_weights = quadrant_points(
            self.triangles, self.tri_normals, self.tri_areas, self.start, self.centroids, self.normals)
        self.points, self.point_normals, self.weights = near_points(self.triangles, self.tri_normals,
                                                                   self.tri_areas, self.start)
        # eq. (3)'s targets: at most KERNEL_TRIANGLES per patch, the largest, scaled to the patch area
        keep = _kernel_triangles(self.tri_areas, self.start, KERNEL_TRIANGLES)
        counts = np.add.reduceat(keep.astype(np.int64), self.start[:-1]) if len(tri) else np.zeros(0, np.int64)
        kept_area = np.add.reduceat(np.where(keep, self.tri_areas, 0.0), self.start[:-1]) if len(tri) else np.zeros(0)
        self.dropped = 1.0 - np.divide(kept_area, self.areas, out=np.ones_like(kept_area), where=self.areas > 0)
        self.scale_kept = np.divide(self.areas, kept_area, out=np.ones_like(kept_area), where=kept_area > 0)
        self.triangles = np.ascontiguousarray(tri[keep])
        self.tri_normals = np.ascontiguousarray(self.tri_normals[keep])
        self.tri_areas = np.ascontiguousarray(self.tri_areas[keep])
        self.start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        # per-triangle arrays of kernel.py's rules (near pairs of few triangles)
        self.tri_centroids = np.ascontiguousarray(self.triangles.mean(axis=1))
        edges = self.triangles - np.roll(self.triangles, 1, axis=1)
        self.tri_diameters = np.ascontiguousarray(np.linalg.norm(edges, axis=2).max(axis=1) if len(edges)
                                                  else np.zeros(0))
        self.touching_rules = np.array(TOUCHING_RULES if touching_rules is None else touching_rules, np.float64)
        self.tolerance = float(tolerance)
        self.exact_pairs = int(exact_pairs)
        self.exact_near = float(exact_near)
        size = float(np.ptp(scene.bounds, axis=0).max()) if len(tri) else 1.0
        self.scale = size if size > 0 else 1.0
        self.eps = 1e-9 * self.scale
        self.far = float(far)
        self.near = float(near)
        self.point_far = float(point_far)
        self.memo_start, self.memo_cols, self.memo_values = memo_table(self.centroids, self.diameters,
                                                                       0.5 * self.far, MEMO_PAIRS if memo else 0)

    @property
    def n(self) -> int:
        return len(self.areas)


def _kernel_triangles(TA: np.ndarray, start: np.ndarray, most: int) -> np.ndarray:
    """(t,) bool: each patch's ``most`` largest triangles (all of them in a smaller patch)."""
    keep = np.ones(len(TA), bool)
    counts = np.diff(start)
    for p in np.flatnonzero(counts > most):
        s = start[p]
        order = np.argsort(TA[s:s + counts[p]], kind="stable")[::-1]
        keep[s + order[most:]] = False
    return keep


def memo_table(C: np.ndarray, D: np.ndarray, reach: float, most: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The memo's slots: every pair (i, j), i < j, with centroids closer than ``reach`` (D_i + D_j).

    Parameters
    ----------
    C : (n, 3) float, patch centroids
    D : (n,) float, patch diameters
    reach : float, the memo's distance in units of D_i + D_j (the quadrant rule's inner edge)
    most : int, most slots; more pairs than this: no slots at all

    Returns
    -------
    start : (n + 1,) int64, patch i's slots are ``start[i]:start[i + 1]``
    cols : (slots,) int32, j of each slot, increasing within a patch
    values : (slots,) float64, NaN (not computed yet)
    """
    n = len(D)
    counts = np.zeros(n, np.int64)
    _memo_pairs(C, D, reach, counts, np.zeros(0, np.int32), np.zeros(n + 1, np.int64))
    start = np.zeros(n + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    if start[-1] > most:
        return np.zeros(n + 1, np.int64), np.zeros(0, np.int32), np.zeros(0)
    cols = np.empty(start[-1], np.int32)
    _memo_pairs(C, D, reach, counts, cols, start)
    return start, cols, np.full(len(cols), np.nan)


@njit(parallel=True, cache=True, nogil=True)
def _memo_pairs(C, D, reach, counts, cols, start):
    """Count (``cols`` empty) or list the memo pairs (i, j > i) of each patch i (see :func:`memo_table`).

    d2 and the bound are the same expressions as in :func:`_cluster_pair_area_ff` (which reads them
    with i and j swapped for j < i: the squares of negated differences, the same numbers).
    """
    n = D.shape[0]
    fill = cols.shape[0] > 0
    for i in prange(n):
        k = start[i]
        m = 0
        for j in range(i + 1, n):
            rx = C[j, 0] - C[i, 0]
            ry = C[j, 1] - C[i, 1]
            rz = C[j, 2] - C[i, 2]
            if rx * rx + ry * ry + rz * rz < (reach * (D[i] + D[j])) ** 2:
                if fill:
                    cols[k + m] = j
                m += 1
        counts[i] = m


@njit(cache=True, fastmath=False, inline="always")
def _memo_slot(i, j, MA, MC):
    """Index of the pair (i, j) in the memo (``MA`` starts, ``MC`` columns), -1 if it has none."""
    a = min(i, j)
    b = max(i, j)
    lo = MA[a]
    hi = MA[a + 1]
    while lo < hi:            # the first slot of a whose column is >= b
        mid = (lo + hi) >> 1
        if MC[mid] < b:
            lo = mid + 1
        else:
            hi = mid
    if lo < MA[a + 1] and MC[lo] == b:
        return lo
    return -1


def quadrant_points(T: np.ndarray, TN: np.ndarray, TA: np.ndarray, start: np.ndarray, C: np.ndarray,
                    PN: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Middle-field points: a patch's triangles in 4 groups by the quadrant of their centroid
    (axes in the patch's mean plane, origin at its centroid); each group gives its
    area-weighted centroid, mean normal and area fraction (a one-triangle patch: its
    centroid, weight 1).

    Returns points (n, 4, 3), unit normals (n, 4, 3), area vectors (n, 4, 3), weights (n, 4).
    """
    n = len(start) - 1
    patch = np.repeat(np.arange(n), np.diff(start))
    # tangent axes of each patch plane: e1 = normal x (an axis far from the normal), e2 = normal x e1
    helper = np.eye(3)[np.argmin(np.abs(PN), axis=1)]
    e1 = np.cross(PN, helper)
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-300)
    e2 = np.cross(PN, e1)
    rel = T.mean(axis=1) - C[patch]
    quadrant = 2 * (np.einsum("td,td->t", rel, e1[patch]) > 0) + (np.einsum("td,td->t", rel, e2[patch]) > 0)
    group = 4 * patch + quadrant
    area = np.bincount(group, weights=TA, minlength=4 * n)
    pts = np.stack([np.bincount(group, weights=TA * T.mean(axis=1)[:, k], minlength=4 * n) for k in range(3)], 1)
    nrm = np.stack([np.bincount(group, weights=TA * TN[:, k], minlength=4 * n) for k in range(3)], 1)
    pts = np.divide(pts, area[:, None], out=np.zeros_like(pts), where=area[:, None] > 0)
    vectors = nrm.copy()
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
    total = np.add.reduceat(TA, start[:-1]) if len(TA) else np.zeros(0)
    w = area.reshape(n, 4) / np.maximum(total, 1e-300)[:, None]
    return (np.ascontiguousarray(pts.reshape(n, 4, 3)), np.ascontiguousarray(nrm.reshape(n, 4, 3)),
            np.ascontiguousarray(vectors.reshape(n, 4, 3)), np.ascontiguousarray(w))


def near_points(T: np.ndarray, TN: np.ndarray, TA: np.ndarray, start: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted near-field quadrature points of each patch (see the module docstring).

    Returns points (n, q, 3), their normals (n, q, 3) and weights (n, q)
    summing to 1 per patch (zero weight = padding), q = 2 NEAR_POINTS.
    """
    n = len(start) - 1
    q = 2 * NEAR_POINTS
    P = np.zeros((n, q, 3))
    PN = np.zeros((n, q, 3))
    W = np.zeros((n, q))
    bary = {m: split_centroids(m) for m in range(1, 5)}
    counts = np.diff(start)
    area = np.add.reduceat(TA, start[:-1]) if len(TA) else np.zeros(0)
    for p in range(n):
        s, k = start[p], counts[p]
        if k > NEAR_POINTS:  # 16 triangles at equal steps of cumulative area, weight 1/16 each
            cum = np.cumsum(TA[s:s + k])
            pick = s + np.minimum(np.searchsorted(cum, (np.arange(NEAR_POINTS) + 0.5) / NEAR_POINTS * cum[-1]), k - 1)
            P[p, :NEAR_POINTS] = T[pick].mean(axis=1)
            PN[p, :NEAR_POINTS] = TN[pick]
            W[p, :NEAR_POINTS] = 1.0 / NEAR_POINTS
            continue
        row = 0
        for t in range(s, s + k):
            m = int(min(4, max(1, math.floor(math.sqrt(NEAR_POINTS * TA[t] / area[p]) + 1e-9))))
            w = bary[m]
            P[p, row:row + len(w)] = w @ T[t]
            PN[p, row:row + len(w)] = TN[t]
            W[p, row:row + len(w)] = TA[t] / area[p] / len(w)
            row += len(w)
    return P, PN, W


@njit(cache=True, fastmath=False, inline="always")
def _point_to_cluster(x, y, z, nx, ny, nz, T, N, TA, TC, TD, s0, s1, eps, far2):
    """Eq. (3): F from dA at (x, y, z) with normal n to triangles s0..s1-1.

    A triangle u at least sqrt(far2) of its diameters D_u from x and wholly in front of
    dA's tangent plane (its centroid at least D_u in front: every corner lies within D_u
    of it) takes the disk-corrected point rule A_u cos_x cos_u / (pi r^2 + A_u), exact for
    a coaxial disk, relative error O((D_u / r)^2) otherwise; the others eq. (1).
    """
    g = 0.0
    for u in range(s0, s1):
        rx = TC[u, 0] - x
        ry = TC[u, 1] - y
        rz = TC[u, 2] - z
        r2 = rx * rx + ry * ry + rz * rz
        if r2 >= far2 * TD[u] * TD[u]:
            hx = -(N[u, 0] * rx + N[u, 1] * ry + N[u, 2] * rz)  # x's height over u's plane (times 1)
            if hx <= eps:   # x on or behind u's plane: the cos(theta_y) clamp of eq. (1) gives 0
                continue
            hu = nx * rx + ny * ry + nz * rz                   # u's centroid over dA's tangent plane
            if hu >= TD[u]:
                g += TA[u] * hu * hx / (r2 * (math.pi * r2 + TA[u]))
                continue
            if hu <= -TD[u]:
                continue
        g += _point_to_patch(x, y, z, nx, ny, nz, T, N, u, eps)
    return g


@njit(cache=True, fastmath=False, inline="always")
def _points_to_cluster(P, PN, W, i, T, N, TA, TC, TD, s0, s1, eps, far2):
    """sum_k W[i, k] F_{dA(P[i, k], PN[i, k]) -> triangles s0..s1-1}: patch i's weighted points, eq. (3)."""
    g = 0.0
    for k in range(P.shape[1]):
        if W[i, k] > 0.0:
            g += W[i, k] * _point_to_cluster(P[i, k, 0], P[i, k, 1], P[i, k, 2], PN[i, k, 0], PN[i, k, 1],
                                             PN[i, k, 2], T, N, TA, TC, TD, s0, s1, eps, far2)
    return g


@njit(cache=True, fastmath=False, inline="always")
def _points_area_ff(xi, yi, zi, Si, xj, yj, zj, Sj):
    """A_i F_ij of two small patches as points with area vectors S (projected areas)."""
    rx = xj - xi
    ry = yj - yi
    rz = zj - zi
    d2 = rx * rx + ry * ry + rz * rz
    ci = Si[0] * rx + Si[1] * ry + Si[2] * rz
    cj = -(Sj[0] * rx + Sj[1] * ry + Sj[2] * rz)
    if ci <= 0.0 or cj <= 0.0 or d2 <= 0.0:
        return 0.0
    return ci * cj * _INV_PI / (d2 * d2)


@njit(cache=True, fastmath=False)
def _touching_area_ff(i, j, T, N, A, C, D, start, eps, tol, rules, count):
    """A_i F_ij of touching clusters: eq. (2) of kernel.py over every triangle pair, in canonical order.

    ``rules`` = (c1_from, q3_from, gap, slack, families) (:data:`TOUCHING_RULES`). Triangle pairs
    at least kernel.py's NEAR (D_t + D_u) apart take its centroid rules; back-to-back pairs give 0;
    the others put their points on p (kernel.py's choice) and take, by their centroid distance d:

    - d >= c1_from (D_t + D_u): p's centroid, A_p F_{c_p -> q} (one evaluation of eq. (1));
    - d >= q3_from (D_t + D_u): the 3-point rule (degree 2);
    - apart, d - 2/3 (D_t + D_u) > gap (D_t + D_u) (every point of a triangle is within 2/3 of its
      diameter from its centroid, so the two are at least that far apart and eq. (1) is smooth
      over p): Dunavant's 6-point rule (degree 4);
    - else (sharing an edge or a corner, or close to): both rules, then kernel.py's 4-split
      refinement where they differ by more than max(tol max(|Q6|, FLOOR A_p), slack S / k), S
      the patch pair's estimate from these first rules and k the number of such triangle pairs:
      a triangle pair holding a small part of A_i F_ij shares the pair's budget instead of
      refining to its own tolerance; with ``families`` non-zero, a split is settled at once when
      its four children's Q6 sum agrees with its own Q6 (kernel.py's ``_refine``).

    ``count[0]`` (when ``count`` is not empty) gains the evaluations of eq. (1) (those of the
    centroid rules beyond NEAR, at most 2 a triangle pair, not counted).
    """
    c1_from = rules[0]
    q3_from = rules[1]
    gap_min = rules[2]
    slack = rules[3]
    families = rules[4] != 0.0
    a = min(i, j)  # canonical order: the same sum for (i, j) and (j, i), reciprocity to the bit
    b = max(i, j)
    m = (start[a + 1] - start[a]) * (start[b + 1] - start[b])
    P = np.empty(m, np.int64)     # the contact pairs: points on P, eq. (1) over Q, their first rules
    Q = np.empty(m, np.int64)
    q6s = np.empty(m)
    q3s = np.empty(m)
    counting = count.shape[0] > 0
    total = 0.0
    k = 0
    for t in range(start[a], start[a + 1]):
        for u in range(start[b], start[b + 1]):
            dx = C[t, 0] - C[u, 0]
            dy = C[t, 1] - C[u, 1]
            dz = C[t, 2] - C[u, 2]
            d2 = dx * dx + dy * dy + dz * dz
            s = D[t] + D[u]
            if d2 >= KERNEL_NEAR * KERNEL_NEAR * s * s:
                total += _triangle_pair_area_ff(t, u, T, N, A, C, D, KERNEL_NEAR, ADAPTIVE, eps, tol)
                continue
            if A[t] <= 0.0 or A[u] <= 0.0 or _behind(t, u, T, N, eps) or _behind(u, t, T, N, eps):
                continue
            p, q = _point_side(t, u, T, N, A, eps, False)
            x0, y0, z0 = T[p, 0, 0], T[p, 0, 1], T[p, 0, 2]
            x1, y1, z1 = T[p, 1, 0], T[p, 1, 1], T[p, 1, 2]
            x2, y2, z2 = T[p, 2, 0], T[p, 2, 1], T[p, 2, 2]
            if d2 >= c1_from * c1_from * s * s:
                total += A[p] * _point_to_patch(C[p, 0], C[p, 1], C[p, 2], N[p, 0], N[p, 1], N[p, 2], T, N, q, eps)
                if counting:
                    count[0] += 1
                continue
            if d2 >= q3_from * q3_from * s * s:
                total += _rules(x0, y0, z0, x1, y1, z1, x2, y2, z2, N[p, 0], N[p, 1], N[p, 2], T, N, q, eps,
                                3, 2)[1]
                if counting:
                    count[0] += 3
                continue
            if math.sqrt(d2) - (2.0 / 3.0) * s > gap_min * s:
                total += _rules(x0, y0, z0, x1, y1, z1, x2, y2, z2, N[p, 0], N[p, 1], N[p, 2], T, N, q, eps,
                                2)[0]
                if counting:
                    count[0] += 6
                continue
            q6, q3 = _rules(x0, y0, z0, x1, y1, z1, x2, y2, z2, N[p, 0], N[p, 1], N[p, 2], T, N, q, eps)
            if counting:
                count[0] += 9
            P[k] = p
            Q[k] = q
            q6s[k] = q6
            q3s[k] = q3
            k += 1
            total += q6
    share = slack * total / max(k, 1)
    for r in range(k):
        budget = max(tol * max(abs(q6s[r]), FLOOR * A[P[r]]), share)
        if abs(q6s[r] - q3s[r]) > budget:   # refine: the 4-split's sum replaces the first Q6
            total += _refine(P[r], Q[r], T, N, eps, q6s[r], q3s[r], budget, count, families) - q6s[r]
    return total


@njit(parallel=True, cache=True, nogil=True)
def _touching_pairs(I, J, T, N, A, C, D, start, eps, tol, rules, out, counts):
    """out[k] (and counts[k], when ``counts`` is not empty) of :func:`_touching_area_ff` for (I[k], J[k])."""
    for k in prange(I.shape[0]):
        c = np.zeros(1 if counts.shape[0] else 0, np.int64)
        out[k] = _touching_area_ff(I[k], J[k], T, N, A, C, D, start, eps, tol, rules, c)
        if counts.shape[0]:
            counts[k] = c[0]


def touching_pairs(geom: "ClusterGeometry", i: np.ndarray, j: np.ndarray, *, rules=None,
                   count: bool = False):
    """The touching rule's sum over every triangle pair of patches (i[k], j[k]), whatever their distance.

    Parameters
    ----------
    geom : ClusterGeometry
    i, j : (m,) int, patch pairs
    rules : (5,) float, optional
        (c1_from, q3_from, gap, slack, families) of :func:`_touching_area_ff`; default
        ``geom.touching_rules``.
    count : bool
        Also return the evaluations of eq. (1) of each pair.

    Returns
    -------
    (m,) float64, A_i F_ij in m^2 without visibility and without the KERNEL_TRIANGLES scaling;
    with ``count``, also (m,) int64.
    """
    i = np.ascontiguousarray(i, np.int64)
    j = np.ascontiguousarray(j, np.int64)
    rules = geom.touching_rules if rules is None else np.ascontiguousarray(rules, np.float64)
    out = np.empty(len(i))
    counts = np.zeros(len(i) if count else 0, np.int64)
    _touching_pairs(i, j, geom.triangles, geom.tri_normals, geom.tri_areas, geom.tri_centroids,
                    geom.tri_diameters, geom.start, geom.eps, geom.tolerance, rules, out, counts)
    return (out, counts) if count else out


@njit(cache=True, fastmath=False, inline="always")
def _cluster_pair_area_ff(i, j, T, N, start, K, A, S, C, D, M, MN, MS, MW, Q, QN, W, far, near, eps,
                          TA, TC, TD, TR, tol, exact, exact_near, far2):
    """A_i F_ij (unoccluded) between two patches, symmetric in (i, j)."""
    if i == j or A[i] <= 0.0 or A[j] <= 0.0:
        return 0.0
    rx = C[j, 0] - C[i, 0]
    ry = C[j, 1] - C[i, 1]
    rz = C[j, 2] - C[i, 2]
    d2 = rx * rx + ry * ry + rz * rz
    reach = D[i] + D[j]
    single = start[i + 1] - start[i] == 1 and start[j + 1] - start[j] == 1
    if not single and d2 >= (far * reach) ** 2:
        return _points_area_ff(C[i, 0], C[i, 1], C[i, 2], S[i], C[j, 0], C[j, 1], C[j, 2], S[j])
    if not single and d2 >= (0.5 * far * reach) ** 2:
        # each patch as its (up to) 4 quadrant groups: halves the size, quarters the error
        total = 0.0
        for k in range(4):
            if MW[i, k] <= 0.0:
                continue
            for m in range(4):
                if MW[j, m] > 0.0:
                    total += _points_area_ff(M[i, k, 0], M[i, k, 1], M[i, k, 2], MS[i, k],
                                             M[j, m, 0], M[j, m, 1], M[j, m, 2], MS[j, m])
        return total
    if d2 >= (near * reach) ** 2:
        g_ij = K[j] * _points_to_cluster(M, MN, MW, i, T, N, TA, TC, TD, start[j], start[j + 1], eps, far2)
        g_ji = K[i] * _points_to_cluster(M, MN, MW, j, T, N, TA, TC, TD, start[i], start[i + 1], eps, far2)
        return 0.5 * (A[i] * g_ij + A[j] * g_ji)
    if (start[i + 1] - start[i]) * (start[j + 1] - start[j]) <= exact and d2 < (exact_near * reach) ** 2:
        # few triangle pairs: kernel.py's per-pair rules, canonical order (reciprocity to the bit)
        return K[i] * K[j] * _touching_area_ff(i, j, T, N, TA, TC, TD, start, eps, tol, TR,
                                               np.empty(0, np.int64))
    g_ij = K[j] * _points_to_cluster(Q, QN, W, i, T, N, TA, TC, TD, start[j], start[j + 1], eps, far2)
    g_ji = K[i] * _points_to_cluster(Q, QN, W, j, T, N, TA, TC, TD, start[i], start[i + 1], eps, far2)
    # the points of the smaller patch resolve the interaction (as in kernel.py)
    a_i = A[i] ** _WEIGHT_POWER
    a_j = A[j] ** _WEIGHT_POWER
    return (a_j * A[i] * g_ij + a_i * A[j] * g_ji) / (a_i + a_j)


@njit(parallel=True, cache=True, fastmath=False, nogil=True)
def _clustered_block(T, N, start, K, A, S, C, D, M, MN, MS, MW, Q, QN, W, rows, cols, far, near, eps, TA, TC, TD,
                     TR, tol, exact, exact_near, far2, MA, MC, MV, out, chunks):
    # rows dealt out in turn (row r to part r % chunks), not in contiguous runs: the costly near
    # pairs of a block sit in the rows next to its columns (Z-order), which a split into
    # contiguous runs gave to one thread (Sponza, 3,129 patches: 99% of a block's time on one core)
    memo = MC.shape[0] > 0
    half = 0.5 * far
    for part in prange(chunks):
        for r in range(part, rows.shape[0], chunks):
            i = rows[r]
            for c in range(cols.shape[0]):
                j = cols[c]
                slot = -1
                if memo:
                    rx = C[j, 0] - C[i, 0]
                    ry = C[j, 1] - C[i, 1]
                    rz = C[j, 2] - C[i, 2]
                    if rx * rx + ry * ry + rz * rz < (half * (D[i] + D[j])) ** 2:
                        slot = _memo_slot(i, j, MA, MC)
                if slot >= 0 and MV[slot] == MV[slot]:     # computed before (NaN: not yet)
                    af = MV[slot]
                else:
                    af = _cluster_pair_area_ff(i, j, T, N, start, K, A, S, C, D, M, MN, MS, MW, Q, QN, W, far,
                                               near, eps, TA, TC, TD, TR, tol, exact, exact_near, far2)
                    if slot >= 0:
                        # two threads meeting (i, j) and (j, i) at once both store the same bits:
                        # an aligned 8-byte store, no torn value
                        MV[slot] = af
                out[r, c] = af / A[i] if af > 0.0 else 0.0


def clustered_block(geom: ClusterGeometry, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(len(rows), len(cols)) float64: F[rows][:, cols] without visibility, clustered patches."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    out = np.empty((len(rows), len(cols)))
    if out.size:
        _clustered_block(geom.triangles, geom.tri_normals, geom.start, geom.scale_kept, geom.areas, geom.area_vectors,
                         geom.centroids, geom.diameters, geom.mid_points, geom.mid_normals, geom.mid_vectors, geom.mid_weights,
                         geom.points, geom.point_normals, geom.weights, rows, cols, geom.far, geom.near,
                         geom.eps, geom.tri_areas, geom.tri_centroids, geom.tri_diameters, geom.touching_rules,
                         geom.tolerance, geom.exact_pairs, geom.exact_near, geom.point_far ** 2,
                         geom.memo_start, geom.memo_cols, geom.memo_values, out, row_chunks(len(rows)))
    return out


#: The ClusterGeometry of each live clustered Scene (Scenes are frozen and hash by identity).
_GEOMETRIES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def kernel_for(scene, **options):
    """(geometry, block function) of the unoccluded kernel that fits ``scene``.

    :class:`ClusterGeometry` and :func:`clustered_block` when its patches are
    clusters of triangles, else kernel.py's :class:`PatchGeometry` (built with
    ``options``) and :func:`unoccluded_block`. ``block(geometry, rows, cols)``
    gives F[rows][:, cols] without visibility either way.
    """
    if scene.is_clustered:  # its own tolerance (CLUSTER_TOLERANCE): ``options`` are kernel.py's
        # one per scene, kept while the scene lives: the ray budget, the time estimate and the engine of
        # a precompute each ask for it (Sponza, 3,129 patches: 0.7-2 s a build, mostly near_points)
        geometry = _GEOMETRIES.get(scene)
        if geometry is None:
            geometry = _GEOMETRIES[scene] = ClusterGeometry(scene)
        return geometry, clustered_block
    return PatchGeometry(scene, **options), unoccluded_block


def block_function(geometry):
    """The block function that reads ``geometry`` (see :func:`kernel_for`)."""
    return clustered_block if isinstance(geometry, ClusterGeometry) else unoccluded_block
