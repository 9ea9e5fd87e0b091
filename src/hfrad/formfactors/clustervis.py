"""Visibility decided once per pair of patch clusters, where it is all or nothing.

Patches are grouped into *clusters*: runs of at most ``CLUSTER_SIZE``
consecutive patches in the Z-order of their centroids that lie in one octree
cell (of the finest level with at most n / ``CLUSTER_SIZE`` occupied cells), so
a cluster is compact; computed here, from the scene alone, so every block,
process and machine groups alike. Every segment between a
point of cluster A and a point of cluster B lies in the convex hull H of the two
clusters' bounding boxes (each padded by the end points' offset off their
surfaces). For each cluster pair the occluder triangles are tested against H,
exactly and conservatively (no rays):

* a triangle *cannot cut* the pair if the 16 box corners lie all in front of its
  plane or all behind it (within the offset tolerance, the per-pair culling rule
  of visibility.py applied to both boxes), or if an axis separates it from H
  (separating-axis test on the box axes, the triangle's edges crossed with the
  box axes and with the axis between the box centres, and that axis crossed
  with the box axes; a test with fewer axes than a complete one can only miss
  a separation, never invent one);
* a triangle *covers* the pair if box A lies wholly on one side of its plane,
  box B wholly on the other, and the 64 points where the segments between the
  corners of A and those of B cross the plane all lie inside the triangle (by a
  margin). Central projection maps convex sets to convex sets, so every
  segment between the boxes then crosses the triangle.

The pair is VISIBLE when no triangle can cut it; otherwise the first triangle
found that may cut it (in a fixed order: along the segment from the lower
cluster's box to the other's) decides: BLOCKED if it covers the pair, MIXED if
not (the search stops there, so a pair is BLOCKED only when that triangle covers it). For a VISIBLE pair every ray that
visibility.py would cast between its patches is free, for a BLOCKED one every
ray is blocked, so their visibility is 1 or 0 without rays and F equals the
per-patch-ray F (to Embree's float32 rounding near edges); only MIXED pairs
go on to probes and per-patch rays. The decisions are also what the probes of
these pairs would have said, so they stand in for them as neighbour states
(:func:`full_ray_pairs_clustered`) and the probing rule decides the other
pairs as before. Each test is symmetric and done once for the canonical pair
(lower cluster first), so V_ij == V_ji still holds.

Where the cluster pair is MIXED, visibility.py can run the same test on single
patch pairs (each patch's box as its cluster), for the pairs that would get
every ray whatever their probe says (close or large pairs, probing.py): one
test there replaces tens to hundreds of rays, while for the others it would
cost more than their one probe ray (:func:`costly_pairs`).

Cluster-pair states are kept in a (K, K) int8 table, K >= n / ``CLUSTER_SIZE``
(n^2 / 1024 bytes); patch-pair states are not kept.

Candidate triangles come from a uniform grid over the occluders (about
``TRIANGLES_PER_CELL`` a cell): the cells within ``r + h`` of points spaced
``h`` along the segment between the box centres (r: the larger box's half
diagonal), which cover H.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..scene.zorder import BITS_PER_AXIS, morton_codes
from .probing import _BLOCKED, _PENDING, _VISIBLE, full_ray_pairs

__all__ = ["ClusterVisibility", "costly_pairs", "CLUSTER_SIZE", "MIXED", "VISIBLE", "BLOCKED", "full_ray_pairs_clustered"]

#: Patches per cluster (consecutive in Z-order); 0 turns cluster visibility off.
CLUSTER_SIZE = 32

#: Occluder triangles per grid cell, on average (the grid has about M / this cells).
TRIANGLES_PER_CELL = 4

#: Up to this many occluders every triangle is tested (no grid walk).
_BRUTE_FORCE = 256

#: Cluster-pair states.
MIXED, VISIBLE, BLOCKED = 0, 1, 2
_UNKNOWN = -1


class ClusterVisibility:
    """Cluster-pair visibility states of one scene, computed on demand and kept.

    Parameters
    ----------
    centroids : (n, 3) float
        Patch centroids (any frame; only their Z-order is used).
    lo, hi : (n, 3) float
        Each patch's bounding box in the visibility frame, padded by the end
        points' offset.
    occluders : (m, 3, 3) float
        Occluder triangles in the same frame.
    tol : float
        Plane tolerance (frame units): a box within ``tol`` of a triangle's
        plane counts as on both sides; also the gap a separating axis must show.
    size : int
        Patches per cluster.

    Attributes
    ----------
    cluster : (n,) int64
        Cluster of each patch.
    pairs_visible, pairs_blocked : int
        Patch pairs that needed rays and were decided by their cluster pair instead.
    """

    def __init__(self, centroids: np.ndarray, lo: np.ndarray, hi: np.ndarray, occluders: np.ndarray,
                 tol: float, size: int = CLUSTER_SIZE) -> None:
        n = len(centroids)
        size = max(1, int(size))
        order, starts = _octree_runs(np.asarray(centroids, np.float64), size)
        k = len(starts)
        self.cluster = np.empty(n, np.int64)
        self.cluster[order] = np.repeat(np.arange(k), np.diff(np.r_[starts, n]))
        self.lo = np.ascontiguousarray(np.minimum.reduceat(np.asarray(lo, np.float64)[order], starts, axis=0))
        self.hi = np.ascontiguousarray(np.maximum.reduceat(np.asarray(hi, np.float64)[order], starts, axis=0))
        self.table = np.full((k, k), _UNKNOWN, np.int8)
        self.patch_lo = np.ascontiguousarray(lo, np.float64)
        self.patch_hi = np.ascontiguousarray(hi, np.float64)
        self.tol = float(tol)
        self.margin = float(tol)
        self.pairs_visible = 0
        self.pairs_blocked = 0
        occ = np.asarray(occluders, np.float64).reshape(-1, 3, 3)
        cr = np.cross(occ[:, 1] - occ[:, 0], occ[:, 2] - occ[:, 0])
        length = np.linalg.norm(cr, axis=1)
        live = length > 1e-14
        occ = occ[live]  # zero-area triangles block nothing
        self.tri = np.ascontiguousarray(occ)
        self.normal = np.ascontiguousarray(cr[live] / length[live, None])
        self.d0 = np.ascontiguousarray(np.einsum("td,td->t", self.normal, occ[:, 0]))
        self.tlo = np.ascontiguousarray(occ.min(axis=1))
        self.thi = np.ascontiguousarray(occ.max(axis=1))
        self._grid()

    def _grid(self) -> None:
        m = len(self.tri)
        if m == 0:
            self.glo, self.cell, self.g = np.zeros(3), np.ones(3), 1
            self.cstart, self.clist = np.zeros(2, np.int64), np.zeros(0, np.int64)
            return
        glo = self.tlo.min(axis=0)
        ghi = self.thi.max(axis=0)
        g = int(np.clip(round((m / TRIANGLES_PER_CELL) ** (1 / 3)), 1, 128))
        span = np.maximum(ghi - glo, 1e-9)
        self.glo, self.cell, self.g = glo, span / g, g
        self.cstart, self.clist = _bin_triangles(self.tlo, self.thi, self.glo, self.cell, g)

    def pair_states(self, rows: np.ndarray, cols: np.ndarray, which: np.ndarray) -> np.ndarray:
        """States of single patch pairs: the same test with each patch's own box as its cluster.

        ``which`` (len(rows), len(cols)) bool selects the pairs; returns their states
        (int8, in ``np.flatnonzero(which)`` order). Not stored: computed for each block.
        """
        flat = np.flatnonzero(which.ravel())
        i = np.asarray(rows, np.int64)[flat // which.shape[1]]
        j = np.asarray(cols, np.int64)[flat % which.shape[1]]
        out = np.empty(len(flat), np.int8)
        if len(flat):
            _cluster_pair_states(np.minimum(i, j), np.maximum(i, j), self.patch_lo, self.patch_hi, self.tri,
                                 self.normal, self.d0, self.tlo, self.thi, self.glo, self.cell, self.g,
                                 self.cstart, self.clist, self.tol, self.margin, out)
        return out

    def states(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(rows), len(cols)) int8: MIXED, VISIBLE or BLOCKED for each patch pair."""
        cr = self.cluster[rows]
        cc = self.cluster[cols]
        ur, uc = np.unique(cr), np.unique(cc)
        sub = self.table[np.ix_(ur, uc)]
        miss_r, miss_c = np.nonzero(sub == _UNKNOWN)
        if len(miss_r):
            a, b = ur[miss_r], uc[miss_c]
            lo_, hi_ = np.minimum(a, b), np.maximum(a, b)
            key = np.unique(lo_ * len(self.table) + hi_)
            a, b = key // len(self.table), key % len(self.table)
            out = np.empty(len(a), np.int8)
            _cluster_pair_states(a, b, self.lo, self.hi, self.tri, self.normal, self.d0, self.tlo, self.thi,
                                 self.glo, self.cell, self.g, self.cstart, self.clist, self.tol, self.margin, out)
            self.table[a, b] = out
            self.table[b, a] = out
        states = np.empty((len(cr), len(cc)), np.int8)
        _gather_states(self.table, cr, cc, states)     # NumPy's 2-D fancy index: ~10x slower
        return states

    def settle(self, F: np.ndarray, need: np.ndarray, states: np.ndarray) -> None:
        """Pairs of ``need`` whose state is VISIBLE or BLOCKED leave ``need``; blocked ones get F = 0.

        ``F``, ``need``, ``states``: (len(rows), len(cols)), changed in place; the counts go to
        :attr:`pairs_visible` and :attr:`pairs_blocked`.
        """
        counts = np.zeros((need.shape[0], 2), np.int64)
        _settle(F, need, states, counts)
        visible, blocked = counts.sum(axis=0)
        self.pairs_visible += int(visible)
        self.pairs_blocked += int(blocked)


def _octree_runs(centroids: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Z-order permutation and the starts of its clusters: runs of at most ``size`` patches in one
    octree cell, the cells of the finest level with at most n / ``size`` occupied cells."""
    codes = morton_codes(centroids)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    n = len(codes)
    shift = 0
    while shift < 3 * BITS_PER_AXIS and len(np.unique(codes >> np.uint64(shift))) > max(1, n // size):
        shift += 3
    cell = codes >> np.uint64(shift)
    new_cell = np.r_[True, cell[1:] != cell[:-1]]
    cell_start = np.flatnonzero(new_cell)
    within = np.arange(n) - np.repeat(cell_start, np.diff(np.r_[cell_start, n]))
    return order, np.flatnonzero(within % size == 0)


def full_ray_pairs_clustered(vis, clusters: ClusterVisibility, F: np.ndarray, rows: np.ndarray,
                             cols: np.ndarray, need: np.ndarray, block_states: np.ndarray) -> np.ndarray:
    """:func:`hfrad.formfactors.probing.full_ray_pairs` with cluster-decided pairs taken as known.

    Pairs (and neighbour pairs) whose cluster pair is VISIBLE or BLOCKED get
    that state instead of a probe ray; ``need`` must already be False for the
    pairs of ``rows`` x ``cols`` decided that way. Returns the pairs that get
    every ray; probe-only pairs found blocked are set to 0 in ``F``.
    ``block_states`` (len(rows), len(cols)): the states of the block's own pairs
    (with the pair-level test where it was run); neighbour pairs take their cluster pair's.
    """
    r, c = len(rows), len(cols)

    def overlay(state, R, Cc):
        cs = clusters.states(R, Cc)
        cs[:r, :c] = block_states  # R and Cc start with rows and cols
        _overlay(state, cs, np.int8(_PENDING), np.int8(_VISIBLE), np.int8(_BLOCKED))

    return full_ray_pairs(vis, F, rows, cols, need, overlay=overlay)


def costly_pairs(vis, F: np.ndarray, rows: np.ndarray, cols: np.ndarray, which: np.ndarray) -> np.ndarray:
    """The pairs of ``which`` that get every ray whatever their probe says: close (centroid distance
    below ``probe_near`` (D_i + D_j)) or large (max(F_ij, F_ji) >= ``probe_below``), the rule of
    :mod:`hfrad.formfactors.probing` (with probing off: every pair of ``which``). Symmetric in (i, j)."""
    if vis.neighbours is None:
        return which.copy()
    out = np.empty(which.shape, np.bool_)
    _costly(F, np.asarray(rows, np.int64), np.asarray(cols, np.int64), vis.centroids, vis.diameters,
            vis.probe_near, vis.areas, vis.probe_below, which, out)
    return out


@njit(parallel=True, cache=True, nogil=True)
def _costly(F, rows, cols, C, D, near, areas, below, which, out):
    for r in prange(rows.shape[0]):
        i = rows[r]
        for c in range(cols.shape[0]):
            out[r, c] = False
            if not which[r, c]:
                continue
            j = cols[c]
            dx = C[i, 0] - C[j, 0]
            dy = C[i, 1] - C[j, 1]
            dz = C[i, 2] - C[j, 2]
            out[r, c] = (dx * dx + dy * dy + dz * dz < (near * (D[i] + D[j])) ** 2
                         or F[r, c] * areas[i] >= below * min(areas[i], areas[j]))


@njit(parallel=True, cache=True, nogil=True)
def _gather_states(table, cr, cc, out):
    """out[r, c] = table[cr[r], cc[c]]."""
    for r in prange(cr.shape[0]):
        row = table[cr[r]]
        for c in range(cc.shape[0]):
            out[r, c] = row[cc[c]]


@njit(parallel=True, cache=True, nogil=True)
def _settle(F, need, states, counts):
    """Decided pairs leave ``need`` (blocked: F = 0); per row (visible, blocked) counts."""
    for r in prange(need.shape[0]):
        for c in range(need.shape[1]):
            if need[r, c] and states[r, c] != MIXED:
                need[r, c] = False
                if states[r, c] == BLOCKED:
                    F[r, c] = 0.0
                    counts[r, 1] += 1
                else:
                    counts[r, 0] += 1


@njit(parallel=True, cache=True, nogil=True)
def _overlay(state, cs, pending, visible, blocked):
    """Pending pairs whose cluster pair is decided take its state (no probe)."""
    for r in prange(state.shape[0]):
        for c in range(state.shape[1]):
            if state[r, c] == pending:
                if cs[r, c] == VISIBLE:
                    state[r, c] = visible
                elif cs[r, c] == BLOCKED:
                    state[r, c] = blocked


@njit(cache=True)
def _bin_triangles(tlo, thi, glo, cell, g):
    """CSR lists of the triangles whose boxes overlap each cell of a g^3 grid."""
    m = tlo.shape[0]
    count = np.zeros(g * g * g + 1, np.int64)
    rng = np.empty((m, 6), np.int64)
    for t in range(m):
        for a in range(3):
            rng[t, a] = min(g - 1, max(0, int(math.floor((tlo[t, a] - glo[a]) / cell[a]))))
            rng[t, 3 + a] = min(g - 1, max(0, int(math.floor((thi[t, a] - glo[a]) / cell[a]))))
        for x in range(rng[t, 0], rng[t, 3] + 1):
            for y in range(rng[t, 1], rng[t, 4] + 1):
                for z in range(rng[t, 2], rng[t, 5] + 1):
                    count[(x * g + y) * g + z + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    items = np.empty(start[-1], np.int64)
    for t in range(m):
        for x in range(rng[t, 0], rng[t, 3] + 1):
            for y in range(rng[t, 1], rng[t, 4] + 1):
                for z in range(rng[t, 2], rng[t, 5] + 1):
                    c = (x * g + y) * g + z
                    items[fill[c]] = t
                    fill[c] += 1
    return start, items


@njit(cache=True, inline="always")
def _separated(P, V, ax, ay, az, gap):
    """Projections of the points P (16, 3) and of the triangle V (3, 3) on axis (ax, ay, az) are
    apart by more than ``gap`` times the axis length (a zero axis separates nothing)."""
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    if norm < 1e-12:
        return False
    pmin = np.inf
    pmax = -np.inf
    for k in range(P.shape[0]):
        p = P[k, 0] * ax + P[k, 1] * ay + P[k, 2] * az
        pmin = min(pmin, p)
        pmax = max(pmax, p)
    qmin = np.inf
    qmax = -np.inf
    for k in range(3):
        q = V[k, 0] * ax + V[k, 1] * ay + V[k, 2] * az
        qmin = min(qmin, q)
        qmax = max(qmax, q)
    return pmax < qmin - gap * norm or qmax < pmin - gap * norm


@njit(cache=True)
def _test_triangle(P, u, V, nrm, d0, tol, margin, d):
    """0: triangle V cannot cut a segment between the boxes (corners P[:8], P[8:]); 2: it covers
    every such segment; 1: it may cut some. ``d`` (16,): scratch."""
    for k in range(16):
        d[k] = nrm[0] * P[k, 0] + nrm[1] * P[k, 1] + nrm[2] * P[k, 2] - d0
    a_front = b_front = a_back = b_back = True
    for k in range(8):
        a_front = a_front and d[k] >= -tol
        a_back = a_back and d[k] <= tol
        b_front = b_front and d[k + 8] >= -tol
        b_back = b_back and d[k + 8] <= tol
    if (a_front and b_front) or (a_back and b_back):
        return 0
    for e in range(3):
        ex = V[(e + 1) % 3, 0] - V[e, 0]
        ey = V[(e + 1) % 3, 1] - V[e, 1]
        ez = V[(e + 1) % 3, 2] - V[e, 2]
        # edge x (1,0,0), (0,1,0), (0,0,1), and edge x u
        if (_separated(P, V, 0.0, ez, -ey, tol) or _separated(P, V, -ez, 0.0, ex, tol)
                or _separated(P, V, ey, -ex, 0.0, tol)
                or _separated(P, V, ey * u[2] - ez * u[1], ez * u[0] - ex * u[2], ex * u[1] - ey * u[0], tol)):
            return 0
    if (_separated(P, V, 0.0, u[2], -u[1], tol) or _separated(P, V, -u[2], 0.0, u[0], tol)
            or _separated(P, V, u[1], -u[0], 0.0, tol)):
        return 0
    # covers: box A strictly on one side, box B strictly on the other, and every corner-to-corner
    # segment crosses the plane inside the triangle by at least `margin`
    a_pos = a_neg = b_pos = b_neg = True
    for k in range(8):
        a_pos = a_pos and d[k] > tol
        a_neg = a_neg and d[k] < -tol
        b_pos = b_pos and d[k + 8] > tol
        b_neg = b_neg and d[k + 8] < -tol
    if not ((a_pos and b_neg) or (a_neg and b_pos)):
        return 1
    for i in range(8):
        for j in range(8, 16):
            s = d[i] / (d[i] - d[j])
            x0 = P[i, 0] + s * (P[j, 0] - P[i, 0])
            x1 = P[i, 1] + s * (P[j, 1] - P[i, 1])
            x2 = P[i, 2] + s * (P[j, 2] - P[i, 2])
            for e in range(3):
                ex = V[(e + 1) % 3, 0] - V[e, 0]
                ey = V[(e + 1) % 3, 1] - V[e, 1]
                ez = V[(e + 1) % 3, 2] - V[e, 2]
                wx = x0 - V[e, 0]
                wy = x1 - V[e, 1]
                wz = x2 - V[e, 2]
                # (edge x w) . n: positive inside (counter-clockwise about n), |edge| times the distance
                inside = ((ey * wz - ez * wy) * nrm[0] + (ez * wx - ex * wz) * nrm[1]
                          + (ex * wy - ey * wx) * nrm[2])
                if inside < margin * math.sqrt(ex * ex + ey * ey + ez * ez):
                    return 1
    return 2


@njit(parallel=True, cache=True, nogil=True)
def _cluster_pair_states(A, B, lo, hi, tri, nrm, d0, tlo, thi, glo, cell, g, cstart, clist, tol, margin, out):
    """out[p]: VISIBLE, BLOCKED or MIXED for cluster pair (A[p], B[p]) (see module docstring)."""
    npairs = A.shape[0]
    m = tri.shape[0]
    chunks = min(npairs, 64)
    h = 0.5 * min(cell[0], min(cell[1], cell[2]))
    brute = m <= _BRUTE_FORCE
    for ch in prange(chunks):
        stamp = np.zeros(m, np.int64)
        P = np.empty((16, 3))
        u = np.empty(3)
        hlo = np.empty(3)
        hhi = np.empty(3)
        ca = np.empty(3)
        c0 = np.empty(3, np.int64)
        c1 = np.empty(3, np.int64)
        d = np.empty(16)
        for p in range(ch, npairs, chunks):
            a = A[p]
            b = B[p]
            for k in range(8):
                for ax in range(3):
                    bit = (k >> ax) & 1
                    P[k, ax] = hi[a, ax] if bit else lo[a, ax]
                    P[k + 8, ax] = hi[b, ax] if bit else lo[b, ax]
            rad = 0.0
            ra = 0.0
            rb = 0.0
            for ax in range(3):
                hlo[ax] = min(lo[a, ax], lo[b, ax])
                hhi[ax] = max(hi[a, ax], hi[b, ax])
                ca[ax] = 0.5 * (lo[a, ax] + hi[a, ax])
                u[ax] = 0.5 * (lo[b, ax] + hi[b, ax]) - ca[ax]
                ra += (hi[a, ax] - lo[a, ax]) ** 2
                rb += (hi[b, ax] - lo[b, ax]) ** 2
            rad = 0.5 * math.sqrt(max(ra, rb))
            length = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
            steps = int(length / h) + 1
            reach = rad + h
            result = VISIBLE
            tag = p + 1
            if brute:  # few occluders: every triangle, no grid walk
                for t in range(m):
                    if (tlo[t, 0] > hhi[0] + tol or thi[t, 0] < hlo[0] - tol
                            or tlo[t, 1] > hhi[1] + tol or thi[t, 1] < hlo[1] - tol
                            or tlo[t, 2] > hhi[2] + tol or thi[t, 2] < hlo[2] - tol):
                        continue
                    r = _test_triangle(P, u, tri[t], nrm[t], d0[t], tol, margin, d)
                    if r != 0:
                        result = BLOCKED if r == 2 else MIXED
                        break
                out[p] = result
                continue
            for s in range(steps + 1):
                if result != VISIBLE:
                    break
                f = s / steps
                for ax in range(3):
                    x = ca[ax] + f * u[ax]
                    c0[ax] = min(g - 1, max(0, int(math.floor((x - reach - glo[ax]) / cell[ax]))))
                    c1[ax] = min(g - 1, max(0, int(math.floor((x + reach - glo[ax]) / cell[ax]))))
                for cx in range(c0[0], c1[0] + 1):
                    for cy in range(c0[1], c1[1] + 1):
                        for cz in range(c0[2], c1[2] + 1):
                            c = (cx * g + cy) * g + cz
                            for q in range(cstart[c], cstart[c + 1]):
                                t = clist[q]
                                if stamp[t] == tag or result != VISIBLE:
                                    continue
                                stamp[t] = tag
                                if (tlo[t, 0] > hhi[0] + tol or thi[t, 0] < hlo[0] - tol
                                        or tlo[t, 1] > hhi[1] + tol or thi[t, 1] < hlo[1] - tol
                                        or tlo[t, 2] > hhi[2] + tol or thi[t, 2] < hlo[2] - tol):
                                    continue
                                r = _test_triangle(P, u, tri[t], nrm[t], d0[t], tol, margin, d)
                                if r == 2:
                                    result = BLOCKED
                                elif r == 1:
                                    result = MIXED
            out[p] = result
