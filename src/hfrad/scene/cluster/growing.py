"""Region growing: faces of an unclustered scene grown into clusters of about a target area.

:class:`FaceGraph` holds the per-face arrays (welded corners, vertex stars,
centroids, normals, areas, compatibility classes, Z-order seeds) and
:meth:`FaceGraph.grow` runs the three passes of step 3 and 4 of
:mod:`hfrad.scene.cluster`: greedy growing from seeds along the Z-order
curve, merging small clusters into an adjacent one, and merging the ones
still small into a nearby one (or, for crumbs, the nearest one).

The passes are compiled loops over faces and clusters (per-cluster sums in
one pass, in the order ``np.bincount`` adds them; each small cluster judges
each neighbouring cluster once), and only the clusters that may still merge
ask the k-d tree for partners: the conference room (308,000 faces after the
pre-split) clusters in under half the time it took, into the same patches.
"""

from __future__ import annotations

import heapq
import math
from functools import cached_property

import numpy as np
from numba import njit

from ...resources import cores
from ..patches import longest_edges
from ..scene import Scene
from ..weld import first_index, row_ids, weld
from ..zorder import zorder_permutation

#: A cluster may reach this far from its seed, in units of sqrt(target area).
REACH = 1.5

#: Most triangles in one patch (bounds the form-factor cost of a patch pair).
MAX_TRIANGLES = 128

#: Clusters smaller than this fraction of the target area are merged into a neighbour.
MERGE_BELOW = 0.25

#: Clusters smaller than this fraction of the target area look for a nearby (not adjacent) partner.
NEARBY_BELOW = 0.5

#: Clusters below this fraction of the target area join the nearest compatible one whatever its normal.
CRUMB = 0.01

#: A crumb joins a patch whatever its normal if it adds at most this fraction of the patch's area.
CRUMB_SHARE = 0.02

#: A crumb may hold up to this many times MAX_TRIANGLES (micro-triangle details).
CRUMB_CAP = 4

#: Nearest clusters considered, and rounds of nearby merging.
NEARBY_CANDIDATES = 8
NEARBY_ROUNDS = 4


def compatibility_classes(scene: Scene) -> np.ndarray:
    """(n,) int: patches that may share a cluster have equal values.

    Same material, group, reflectance and emission (a patch has one of each):
    the ids of the rows (material, group, reflectance, emission) in
    lexicographic order (:func:`~hfrad.scene.weld.row_ids`).
    """
    ids = row_ids(np.column_stack([scene.material, scene.group]))
    first = first_index(ids, int(ids.max(initial=-1)) + 1)
    values = np.column_stack([scene.reflectance, scene.emission])
    if np.array_equal(values, values[first[ids]]):
        # colours follow (material, group), as they do unless set per patch: the same ids
        # and order as of the whole rows, from two integer columns instead of eight floats
        return ids
    return row_ids(np.column_stack([scene.material, scene.group, values]))


def _vertex_stars(welded: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR vertex -> triangles touching it: (start (v + 1,), triangles in increasing order)."""
    start = np.zeros(n_vertices + 1, np.int64)
    np.cumsum(np.bincount(welded.reshape(-1), minlength=n_vertices), out=start[1:])
    return start, _star_members(welded, start)


@njit(cache=True)
def _star_members(welded, start):
    """The triangles around each vertex, a counting sort of the corners by vertex (stable)."""
    fill = start[:-1].copy()
    out = np.empty(start[-1], np.int64)
    for t in range(welded.shape[0]):
        for k in range(welded.shape[1]):
            v = welded[t, k]
            out[fill[v]] = t
            fill[v] += 1
    return out


@njit(cache=True)
def _reach(tri, cent):
    """(t,) float: each triangle's largest corner distance from its centroid (as np.linalg.norm sums)."""
    out = np.zeros(tri.shape[0])
    for t in range(tri.shape[0]):
        for k in range(3):
            dx, dy, dz = tri[t, k, 0] - cent[t, 0], tri[t, k, 1] - cent[t, 1], tri[t, k, 2] - cent[t, 2]
            out[t] = max(out[t], math.sqrt((dx * dx + dy * dy) + dz * dz))
    return out


@njit(cache=True)
def _grow(seeds, eligible, key, welded, vstart, vtris, cent, nrm, area, reach, cos_tol, a_max, r_max,
          max_triangles, crumb, label):
    """Greedy region growing from seeds in order; returns the number of clusters.

    A cluster takes the unassigned compatible neighbour nearest to its seed
    (a heap keyed on the distance) until its area reaches ``a_max``.
    """
    n_clusters = 0
    stamp = np.full(label.shape[0], -1, np.int64)
    for s in seeds:
        if label[s] >= 0 or not eligible[s]:
            continue
        c = n_clusters
        n_clusters += 1
        label[s] = c
        acc = area[s]
        count = 1
        sx, sy, sz = nrm[s, 0] * area[s], nrm[s, 1] * area[s], nrm[s, 2] * area[s]
        heap = [(0.0, s)]
        heap.pop()
        stamp[s] = c
        t = s
        first = True
        while first or (len(heap) > 0 and acc < a_max):
            if first:
                first = False
            else:
                d, t = heapq.heappop(heap)
                if label[t] >= 0:
                    continue
                # the triangle must lie within the tolerance of the mean normal it would give
                ax, ay, az = sx + nrm[t, 0] * area[t], sy + nrm[t, 1] * area[t], sz + nrm[t, 2] * area[t]
                ln = math.sqrt(ax * ax + ay * ay + az * az)
                if ln <= 0.0 or (nrm[t, 0] * ax + nrm[t, 1] * ay + nrm[t, 2] * az) < cos_tol * ln:
                    continue
                if (nrm[s, 0] * ax + nrm[s, 1] * ay + nrm[s, 2] * az) < cos_tol * ln:
                    continue
                # the triangle cap bounds the kernel's cost; a crumb of micro-triangles may pass it
                if d + reach[t] > r_max or acc + area[t] > 1.25 * a_max or count >= CRUMB_CAP * max_triangles or (
                        count >= max_triangles and acc >= crumb * a_max):
                    continue
                label[t] = c
                count += 1
                acc += area[t]
                sx += nrm[t, 0] * area[t]
                sy += nrm[t, 1] * area[t]
                sz += nrm[t, 2] * area[t]
            for k in range(3):
                v = welded[t, k]
                for q in range(vstart[v], vstart[v + 1]):
                    u = vtris[q]
                    if label[u] >= 0 or stamp[u] == c or not eligible[u] or key[u] != key[s]:
                        continue
                    stamp[u] = c
                    dx = cent[u, 0] - cent[s, 0]
                    dy = cent[u, 1] - cent[s, 1]
                    dz = cent[u, 2] - cent[s, 2]
                    d = math.sqrt(dx * dx + dy * dy + dz * dz)
                    if d + reach[u] > r_max:
                        continue  # out of reach: it would be popped and refused (stamped all the same)
                    heapq.heappush(heap, (d, u))
    return n_clusters


@njit(cache=True)
def _cluster_spheres(label, n_clusters, cent, reach, area):
    """(centres (c, 3), radii (c,)): a sphere around each cluster's triangles (area-weighted centre)."""
    c_cen = np.zeros((n_clusters, 3))
    c_area = np.zeros(n_clusters)
    for t in range(label.shape[0]):
        c = label[t]
        if c >= 0:
            c_area[c] += area[t]
            for k in range(3):
                c_cen[c, k] += area[t] * cent[t, k]
    for c in range(n_clusters):
        if c_area[c] > 0.0:
            for k in range(3):
                c_cen[c, k] /= c_area[c]
    rad = np.zeros(n_clusters)
    for t in range(label.shape[0]):
        c = label[t]
        if c >= 0:
            d = math.sqrt((cent[t, 0] - c_cen[c, 0]) ** 2 + (cent[t, 1] - c_cen[c, 1]) ** 2
                          + (cent[t, 2] - c_cen[c, 2]) ** 2) + reach[t]
            rad[c] = max(rad[c], d)
    return c_cen, rad


@njit(cache=True)
def _union_sphere(cen, rad, a, b):
    """Smallest sphere around spheres a and b: (x, y, z, radius)."""
    dx = cen[b, 0] - cen[a, 0]
    dy = cen[b, 1] - cen[a, 1]
    dz = cen[b, 2] - cen[a, 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d + rad[b] <= rad[a]:
        return cen[a, 0], cen[a, 1], cen[a, 2], rad[a]
    if d + rad[a] <= rad[b]:
        return cen[b, 0], cen[b, 1], cen[b, 2], rad[b]
    r = 0.5 * (d + rad[a] + rad[b])
    f = (r - rad[a]) / d
    return cen[a, 0] + f * dx, cen[a, 1] + f * dy, cen[a, 2] + f * dz, r


@njit(cache=True)
def _set_sphere(cen, rad, o, x, y, z, r):
    cen[o, 0], cen[o, 1], cen[o, 2], rad[o] = x, y, z, r


@njit(cache=True)
def _merge_small(label, n_clusters, key, welded, vstart, vtris, nrm, area, cent, reach, cos_tol, a_small, a_tiny,
                 a_max, max_triangles, d_max):
    """Merge clusters smaller than ``a_small`` into a compatible neighbour; relabels in place.

    The union must fit in a sphere of diameter ``d_max`` (no strips chained into long patches).
    """
    t_count = label.shape[0]
    c_area = np.zeros(n_clusters)
    c_vec = np.zeros((n_clusters, 3))
    for t in range(t_count):
        c = label[t]
        if c < 0:
            continue
        c_area[c] += area[t]
        for k in range(3):
            c_vec[c, k] += nrm[t, k] * area[t]
    # triangles of each cluster (CSR)
    start = np.zeros(n_clusters + 1, np.int64)
    for t in range(t_count):
        if label[t] >= 0:
            start[label[t] + 1] += 1
    for c in range(n_clusters):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(t_count, np.int64)
    for t in range(t_count):
        if label[t] >= 0:
            members[fill[label[t]]] = t
            fill[label[t]] += 1
    c_count = start[1:] - start[:-1]
    s_cen, s_rad = _cluster_spheres(label, n_clusters, cent, reach, area)
    parent = np.arange(n_clusters)
    seen = np.full(n_clusters, -1, np.int64)  # seen[o] == c: neighbour o already judged for c
    order = np.argsort(c_area)
    for c in order:
        if c_area[c] >= a_small:
            break
        best = -1
        best_area = np.inf
        for q in range(start[c], start[c + 1]):
            t = members[q]
            for k in range(3):
                v = welded[t, k]
                for r in range(vstart[v], vstart[v + 1]):
                    u = vtris[r]
                    if key[u] != key[t] or label[u] < 0:
                        continue
                    o = label[u]
                    while parent[o] != o:
                        o = parent[o]
                    # nothing changes while c's neighbours are judged: the first verdict on o stands
                    if seen[o] == c:
                        continue
                    seen[o] = c
                    if o == c or c_area[o] >= best_area or c_area[o] + c_area[c] > 1.5 * a_max:
                        continue
                    if c_count[o] + c_count[c] > (max_triangles if c_area[c] >= a_tiny else CRUMB_CAP * max_triangles):
                        continue
                    if 2.0 * _union_sphere(s_cen, s_rad, o, c)[3] > d_max:
                        continue
                    lo = math.sqrt(c_vec[o, 0] ** 2 + c_vec[o, 1] ** 2 + c_vec[o, 2] ** 2)
                    lc = math.sqrt(c_vec[c, 0] ** 2 + c_vec[c, 1] ** 2 + c_vec[c, 2] ** 2)
                    dot = c_vec[o, 0] * c_vec[c, 0] + c_vec[o, 1] * c_vec[c, 1] + c_vec[o, 2] * c_vec[c, 2]
                    if lo > 0.0 and lc > 0.0 and dot >= cos_tol * lo * lc:
                        best = o
                        best_area = c_area[o]
        if best >= 0:
            x, y, z, r = _union_sphere(s_cen, s_rad, best, c)
            _set_sphere(s_cen, s_rad, best, x, y, z, r)
            parent[c] = best
            c_area[best] += c_area[c]
            c_count[best] += c_count[c]
            for k in range(3):
                c_vec[best, k] += c_vec[c, k]
    _to_roots(label, parent)


@njit(cache=True)
def _merge_nearby(label, c_area, c_vec, c_key, c_count, s_cen, s_rad, cand, a_small, a_tiny, a_max, cos_tol,
                  cos_pair, max_triangles, d_max):
    """Merge small clusters into a nearby compatible one (gaps, T-junctions, separate small parts).

    ``cand[c]`` lists cluster c's nearest clusters (by centroid, -1 = none).
    A merge must keep the non-flatness 1 - |S| / A of the union within
    1 - cos_tol, the two mean normals within acos(cos_pair) and the union in a
    sphere of diameter ``d_max`` (``s_cen``, ``s_rad``: each cluster's sphere).
    """
    n = c_area.shape[0]
    parent = np.arange(n)
    order = np.argsort(c_area)
    merged = 0
    for c in order:
        if c_area[c] >= a_small or parent[c] != c:
            continue
        for q in range(cand.shape[1]):
            o = cand[c, q]
            if o < 0:
                continue
            while parent[o] != o:
                o = parent[o]
            if o == c or c_key[o] != c_key[c] or c_area[o] + c_area[c] > a_max:
                continue
            if c_count[o] + c_count[c] > (max_triangles if c_area[c] >= a_tiny else CRUMB_CAP * max_triangles):
                continue
            x, y, z, r = _union_sphere(s_cen, s_rad, o, c)
            if 2.0 * r > d_max:
                continue
            sx = c_vec[o, 0] + c_vec[c, 0]
            sy = c_vec[o, 1] + c_vec[c, 1]
            sz = c_vec[o, 2] + c_vec[c, 2]
            if math.sqrt(sx * sx + sy * sy + sz * sz) < 0.5 * (c_area[o] + c_area[c]):
                continue  # never a patch whose triangles cancel (two opposed crumbs)
            # a crumb (below a_tiny) joins whatever is nearest: its light is negligible, but a
            # patch of almost no area makes the columns of F huge (A_j F_ji / A_i)
            if c_area[c] >= a_tiny:
                if math.sqrt(sx * sx + sy * sy + sz * sz) < cos_tol * (c_area[o] + c_area[c]):
                    continue
                lo = math.sqrt(c_vec[o, 0] ** 2 + c_vec[o, 1] ** 2 + c_vec[o, 2] ** 2)
                lc = math.sqrt(c_vec[c, 0] ** 2 + c_vec[c, 1] ** 2 + c_vec[c, 2] ** 2)
                dot = c_vec[o, 0] * c_vec[c, 0] + c_vec[o, 1] * c_vec[c, 1] + c_vec[o, 2] * c_vec[c, 2]
                if dot < cos_pair * lo * lc:
                    continue
            parent[c] = o
            _set_sphere(s_cen, s_rad, o, x, y, z, r)
            c_area[o] += c_area[c]
            c_count[o] += c_count[c]
            c_vec[o, 0], c_vec[o, 1], c_vec[o, 2] = sx, sy, sz
            merged += 1
            break
    _to_roots(label, parent)
    return merged


@njit(cache=True)
def _to_roots(label, parent):
    """Relabel every assigned triangle with the cluster its cluster was merged into."""
    for t in range(label.shape[0]):
        o = label[t]
        if o < 0:
            continue
        while parent[o] != o:
            o = parent[o]
        label[t] = o


def _relabel(label: np.ndarray) -> int:
    """Renumber the labels >= 0 as 0..k-1 in place, keeping their order; returns k."""
    ok = label >= 0
    used = np.zeros(int(label.max(initial=-1)) + 1, bool)
    used[label[ok]] = True
    label[ok] = (np.cumsum(used) - 1)[label[ok]]  # labels are small integers: a table, not a sort
    return int(used.sum())


@njit(cache=True)
def _cluster_sums(label, count, key, area, nrm, cent):
    """Per cluster (labels 0..count-1; -1: none): area (c,), area-weighted normal sum (c, 3),
    area-weighted centroid sum (c, 3), triangle count (c,) and compatibility class (c,).

    Summed in triangle order, as ``np.bincount`` with these weights sums (the same bits).
    """
    c_area = np.zeros(count)
    c_vec = np.zeros((count, 3))
    c_sum = np.zeros((count, 3))
    c_count = np.zeros(count, np.int64)
    c_key = np.zeros(count, np.int64)
    for t in range(label.shape[0]):
        c = label[t]
        if c < 0:
            continue
        c_area[c] += area[t]
        for k in range(3):
            c_vec[c, k] += area[t] * nrm[t, k]
            c_sum[c, k] += area[t] * cent[t, k]
        c_count[c] += 1
        c_key[c] = key[t]
    return c_area, c_vec, c_sum, c_count, c_key


class FaceGraph:
    """Per-face arrays of an unclustered scene that the growing needs (computed once).

    Faces are adjacent when they share a corner, corners being welded by
    position (:func:`hfrad.scene.weld.weld`), so triangle soups grow too.
    """

    def __init__(self, scene: Scene) -> None:
        tri = self._triangles = scene.triangles
        self.welded = weld(scene.vertices, scene.faces)
        n_vertices = int(self.welded.max(initial=-1)) + 1
        self.vstart, self.vtris = _vertex_stars(self.welded, n_vertices)
        self.centroids = np.ascontiguousarray(scene.centroids)
        self.normals = np.ascontiguousarray(scene.normals)
        self.areas = np.ascontiguousarray(scene.areas)
        self.reach = _reach(np.ascontiguousarray(tri), self.centroids)
        self.key = compatibility_classes(scene)
        self.seeds = zorder_permutation(self.centroids)

    @cached_property
    def longest(self) -> np.ndarray:
        """(t,) metres: each face's longest edge (only ``max_edge`` clustering asks)."""
        return longest_edges(self._triangles)

    def grow(self, eligible: np.ndarray, cos_tol: float, a_max: float, r_max: float,
             merge: bool, max_triangles: int = 0) -> tuple[np.ndarray, int]:
        """Grow the ``eligible`` faces into clusters.

        Parameters
        ----------
        eligible : (t,) bool
            Faces that may join a cluster (the others keep label -1).
        cos_tol : float
            Cosine of the largest angle between a face's normal and its cluster's mean normal.
        a_max : float, m^2
            Target cluster area: growing stops at it (``np.inf``: no area limit).
        r_max : float, metres
            Largest distance of a face's corners from its cluster's seed.
        merge : bool
            Then merge clusters below ``MERGE_BELOW * a_max`` into an adjacent one,
            those below ``NEARBY_BELOW * a_max`` into a nearby one, crumbs into the nearest.
        max_triangles : int
            Most faces in a cluster (0: ``MAX_TRIANGLES``).

        Returns
        -------
        label : (t,) int64
            Cluster of each face, 0..count-1, or -1 for faces not eligible.
        count : int
            Number of clusters.
        """
        max_triangles = max_triangles or MAX_TRIANGLES
        label = np.full(len(self.areas), -1, np.int64)
        count = _grow(self.seeds, eligible, self.key, self.welded, self.vstart, self.vtris, self.centroids,
                      self.normals, self.areas, self.reach, cos_tol, a_max, r_max, max_triangles, CRUMB, label)
        if merge:
            d_max = 2.0 * r_max
            _merge_small(label, count, self.key, self.welded, self.vstart, self.vtris, self.normals,
                         self.areas, self.centroids, self.reach, cos_tol, MERGE_BELOW * a_max, CRUMB * a_max, a_max,
                         max_triangles, d_max)
            count = _relabel(label)
            for _ in range(NEARBY_ROUNDS):
                if not self._nearby(label, count, cos_tol, a_max, r_max, max_triangles):
                    break
                count = _relabel(label)
            if self._absorb_crumbs(label, count, CRUMB * a_max, r_max, cos_tol):
                count = _relabel(label)
        return label, count

    def _absorb_crumbs(self, label: np.ndarray, count: int, a_tiny: float, r_max: float, cos_tol: float) -> int:
        """Clusters still below ``a_tiny`` (parts made of micro-triangles: screws, hinges) join the
        nearest cluster of their class that is not one, within ``r_max``, whatever its normal or
        triangle count; returns how many did.

        Their light is negligible, but patch areas spanning 10^6 make the plain 2-norm of F
        large (a column of F sums the shares F_ij <= 1 of every crumb i that sees patch j), and
        the kernel leaves out a patch's tiniest triangles (``hfrad.formfactors.clustered``).
        """
        from scipy.spatial import cKDTree

        c_area, c_vec, c_sum, _, c_key = _cluster_sums(label, count, self.key, self.areas, self.normals,
                                                       self.centroids)
        c_cen = c_sum / np.maximum(c_area, 1e-300)[:, None]
        crumb = c_area < a_tiny
        target = np.arange(count)
        for k in np.unique(c_key[crumb]):
            hosts = np.flatnonzero((c_key == k) & ~crumb)
            small = np.flatnonzero((c_key == k) & crumb)
            if not len(hosts):
                continue
            dist, near = cKDTree(c_cen[hosts]).query(c_cen[small], k=min(NEARBY_CANDIDATES, len(hosts)),
                                                     distance_upper_bound=r_max)
            dist, near = dist.reshape(len(small), -1), near.reshape(len(small), -1)
            for q in np.argsort(c_area[small])[::-1]:
                c = small[q]
                for d, h in zip(dist[q], near[q]):
                    if not np.isfinite(d):
                        break
                    h = hosts[h]
                    union = c_vec[h] + c_vec[c]
                    # a share of the host's area too small to matter, or the union stays flat enough
                    if (c_area[c] <= CRUMB_SHARE * c_area[h]
                            or np.linalg.norm(union) >= cos_tol * (c_area[h] + c_area[c])):
                        target[c] = h
                        c_area[h] += c_area[c]
                        c_vec[h] = union
                        break
        moved = int((target != np.arange(count)).sum())
        if moved:
            ok = label >= 0
            label[ok] = target[label[ok]]
        return moved

    def _nearby(self, label: np.ndarray, count: int, cos_tol: float, a_max: float, r_max: float,
                max_triangles: int) -> int:
        from scipy.spatial import cKDTree

        c_area, c_vec, c_sum, c_count, c_key = _cluster_sums(label, count, self.key, self.areas, self.normals,
                                                             self.centroids)
        c_cen = c_sum / c_area[:, None]
        k = min(NEARBY_CANDIDATES + 1, count)
        if k < 2:
            return 0
        # only clusters small now look for partners (a cluster's area only grows in the merging),
        # so only they are queried: each query is answered alike in any batch
        small = np.flatnonzero(c_area < NEARBY_BELOW * a_max)
        dist, near = cKDTree(c_cen).query(c_cen[small], k=k, distance_upper_bound=r_max, workers=cores())
        cand = np.full((count, k - 1), -1, np.int64)
        cand[small] = np.where(np.isfinite(dist), near, -1)[:, 1:]
        cos_pair = math.cos(2 * math.acos(cos_tol))
        s_cen, s_rad = _cluster_spheres(label, count, self.centroids, self.reach, self.areas)
        return _merge_nearby(label, c_area, c_vec, c_key, c_count, s_cen, s_rad, np.ascontiguousarray(cand),
                             NEARBY_BELOW * a_max, CRUMB * a_max, a_max, cos_tol, cos_pair, max_triangles, 2.0 * r_max)
