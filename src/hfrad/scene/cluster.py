"""Patches that are clusters of triangles: a real mesh at the patch count asked for.

Game-level and CAD meshes are made of many small triangles (mouldings,
railings, chair legs) whose light matters in aggregate. When ``--patches N``
asks for fewer patches than the scene has faces, :func:`cluster` grows
adjacent triangles into patches of roughly equal area instead of giving each
triangle its own patch (the "target mesh / detail mesh" split of production
radiosity systems):

1. Target area A* = total area / N (times a factor found by a few secant
   steps so that the patch count comes out within ~5 % of N).
1b. Faces longer than PRESPLIT_EDGE sqrt(A*) are first cut by longest-edge
   bisection until no piece is (:func:`presplit`), and the pieces are grown
   like any small face: a long thin face (Sponza's floor strips) would otherwise be a
   long thin patch, one radiosity value along a strip; now its pieces join
   their neighbours across the strip into compact patches.
2. Faces larger than A* are split m x m, m = round(sqrt(area / A*)), as
   :func:`hfrad.scene.patches.subdivide` does; each piece is a patch.
3. The other faces are grown into clusters. Seeds are taken along the Z-order
   curve of the face centroids; a cluster absorbs the unassigned neighbour
   (sharing a vertex, welded by position) nearest to its seed while its area
   is below A*, if the neighbour has the same material, group, reflectance
   and emission, its normal is within ``normal_tolerance`` of the cluster's
   mean normal, and it lies within ``1.5 sqrt(A*)`` of the seed (compact
   patches); a patch holds at most MAX_TRIANGLES triangles (this bounds the
   form-factor cost of a pair of patches).
4. Leftover slivers smaller than A*/4 join a compatible adjacent cluster;
   clusters under A*/2 that touch none (separate small parts, gaps, T-joints)
   join a compatible one among the nearest within 1.5 sqrt(A*) if the union
   stays within the normal tolerance; crumbs under A*/100 join the nearest
   one of their material whatever its normal (a patch of almost no area
   would make the columns of F, A_j F_ji / A_i, huge).

With ``max_edge=L`` faces longer than L are split as before and faces shorter
than L/2 are grown into patches no wider than L (no area limit).

Each triangle belongs to exactly one patch (``Scene.triangle_patch``); the
patch's area is the sum of its triangles' areas, so area per material is
conserved exactly, and its normal is the area-weighted mean normal
(``Scene.non_flatness`` measures how far from flat it is). The occluder mesh
is the original mesh, untouched.
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from numba import njit

from .patches import split_faces
from .scene import Scene
from .zorder import zorder_permutation

#: Default largest angle between a triangle's normal and its patch's mean normal, degrees.
NORMAL_TOLERANCE = 30.0

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

#: Accept a patch count within this relative distance of the one asked for.
COUNT_TOLERANCE = 0.05

#: Faces longer than this times sqrt(target area) are cut before growing (compact patches).
PRESPLIT_EDGE = 1.5


def weld(vertices: np.ndarray, faces: np.ndarray, *, rel_tol: float = 1e-9) -> np.ndarray:
    """(n, 3) int: face corners renumbered so coincident vertices share one id.

    Positions are rounded to ``rel_tol`` times the largest coordinate, so
    triangle soups (every face with its own three vertices) become meshes.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if not len(faces):
        return faces.reshape(0, 3)
    scale = float(np.abs(vertices).max(initial=0.0)) or 1.0
    key = np.rint(vertices / (scale * rel_tol)).astype(np.int64)
    return row_ids(key)[faces]


def row_ids(table: np.ndarray) -> np.ndarray:
    """(n,) int64: equal rows of the (n, k) ``table`` get equal ids 0..u-1 (in sorted row order).

    Same as ``np.unique(table, axis=0, return_inverse=True)[1]``, several times faster
    (a lexsort on the columns instead of sorting rows as opaque records).
    """
    table = np.asarray(table)
    n = len(table)
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort(table.T[::-1])
    ordered = table[order]
    new = np.empty(n, bool)
    new[0] = True
    np.any(ordered[1:] != ordered[:-1], axis=1, out=new[1:])
    ids = np.empty(n, np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


def compatibility_classes(scene: Scene) -> np.ndarray:
    """(n,) int: patches that may share a cluster have equal values.

    Same material, group, reflectance and emission (a patch has one of each).
    """
    table = np.column_stack([scene.material, scene.group, scene.reflectance, scene.emission])
    return row_ids(table)


def _vertex_stars(welded: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR vertex -> triangles touching it: (start (v + 1,), triangles)."""
    corner_tri = np.repeat(np.arange(len(welded)), 3)
    v = welded.reshape(-1)
    order = np.argsort(v, kind="stable")
    start = np.zeros(n_vertices + 1, np.int64)
    np.cumsum(np.bincount(v, minlength=n_vertices), out=start[1:])
    return start, corner_tri[order].astype(np.int64)


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
                    heapq.heappush(heap, (math.sqrt(dx * dx + dy * dy + dz * dz), u))
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
    """Renumber the labels >= 0 as 0..k-1 in place; returns k."""
    used, inverse = np.unique(label[label >= 0], return_inverse=True)
    label[label >= 0] = inverse.reshape(-1)
    return len(used)


class _Mesh:
    """Per-face arrays of an unclustered scene that the growing needs (computed once)."""

    def __init__(self, scene: Scene) -> None:
        tri = scene.triangles
        self.welded = weld(scene.vertices, scene.faces)
        n_vertices = int(self.welded.max(initial=-1)) + 1
        self.vstart, self.vtris = _vertex_stars(self.welded, n_vertices)
        self.centroids = np.ascontiguousarray(scene.centroids)
        self.normals = np.ascontiguousarray(scene.normals)
        self.areas = np.ascontiguousarray(scene.areas)
        self.reach = np.linalg.norm(tri - self.centroids[:, None], axis=2).max(axis=1) if len(tri) else np.zeros(0)
        self.longest = _longest_edges(tri)
        self.key = compatibility_classes(scene)
        self.seeds = zorder_permutation(self.centroids)

    def grow(self, eligible: np.ndarray, cos_tol: float, a_max: float, r_max: float,
             merge: bool, max_triangles: int = 0) -> tuple[np.ndarray, int]:
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

        ok = label >= 0
        lab = label[ok]
        c_area = np.bincount(lab, weights=self.areas[ok], minlength=count)
        c_cen = np.stack([np.bincount(lab, weights=self.areas[ok] * self.centroids[ok, k], minlength=count)
                          for k in range(3)], axis=1) / np.maximum(c_area, 1e-300)[:, None]
        c_key = np.zeros(count, np.int64)
        c_key[lab] = self.key[ok]
        c_vec = np.stack([np.bincount(lab, weights=self.areas[ok] * self.normals[ok, k], minlength=count)
                          for k in range(3)], axis=1)
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
            label[ok] = target[lab]
        return moved

    def _nearby(self, label: np.ndarray, count: int, cos_tol: float, a_max: float, r_max: float,
                max_triangles: int) -> int:
        from scipy.spatial import cKDTree

        ok = label >= 0
        lab = label[ok]
        c_area = np.bincount(lab, weights=self.areas[ok], minlength=count)
        c_vec = np.stack([np.bincount(lab, weights=self.areas[ok] * self.normals[ok, k], minlength=count)
                          for k in range(3)], axis=1)
        c_cen = np.stack([np.bincount(lab, weights=self.areas[ok] * self.centroids[ok, k], minlength=count)
                          for k in range(3)], axis=1) / c_area[:, None]
        c_key = np.zeros(count, np.int64)
        c_key[lab] = self.key[ok]
        k = min(NEARBY_CANDIDATES + 1, count)
        if k < 2:
            return 0
        dist, cand = cKDTree(c_cen).query(c_cen, k=k, distance_upper_bound=r_max)
        cand = np.where(np.isfinite(dist), cand, -1)[:, 1:].astype(np.int64)
        cos_pair = math.cos(2 * math.acos(cos_tol))
        c_count = np.bincount(lab, minlength=count).astype(np.int64)
        s_cen, s_rad = _cluster_spheres(label, count, self.centroids, self.reach, self.areas)
        return _merge_nearby(label, c_area, c_vec, c_key, c_count, s_cen, s_rad, np.ascontiguousarray(cand),
                             NEARBY_BELOW * a_max, CRUMB * a_max, a_max, cos_tol, cos_pair, max_triangles, 2.0 * r_max)


def cluster(scene: Scene, *, patches: int | None = None, max_edge: float | None = None,
            normal_tolerance: float = NORMAL_TOLERANCE) -> Scene:
    """Group a scene's faces into patches of about equal area (see the module docstring).

    Parameters
    ----------
    scene : Scene
        Unclustered (one triangle per patch), degenerate faces already dropped.
    patches : int, optional
        Patch count to aim for (met within ~5 % where the mesh allows it).
    max_edge : float, metres, optional
        Instead of ``patches``: split faces longer than this, and grow faces
        shorter than half of it into patches no wider than it.
    normal_tolerance : float, degrees
        Largest angle between a triangle's normal and its patch's mean normal.

    Returns
    -------
    Scene
        ``faces`` are the detail triangles (the input faces, large ones split),
        ``triangle_patch`` maps each to its patch; patches are in Z-order of
        their centroids and each patch's triangles are contiguous. When the
        request cannot be met (fewer patches than materials and separate
        surfaces allow), the scene carries a warning saying so.

    Raises
    ------
    ValueError
        Both or neither of ``patches`` and ``max_edge``; bad values; an
        already clustered scene.

    Examples
    --------
    >>> from hfrad.scene.builtin import cornell_box
    >>> from hfrad.scene.patches import subdivide
    >>> fine = subdivide(cornell_box(), patches=4000)
    >>> coarse = cluster(fine, patches=1000)
    >>> bool(abs(coarse.n_patches - 1000) <= 100), coarse.n_triangles == fine.n_patches
    (True, True)
    >>> bool(np.isclose(coarse.total_area, fine.total_area, rtol=1e-12))
    True
    """
    if (patches is None) == (max_edge is None):
        raise ValueError("give either patches or max_edge to cluster, not both or neither")
    if scene.is_clustered:
        raise ValueError(f"{scene.name}: the scene is already clustered")
    if not (0.0 < normal_tolerance < 90.0):
        raise ValueError(f"normal_tolerance must be in (0, 90) degrees, got {normal_tolerance}")
    if patches is not None and (int(patches) != patches or patches < 1):
        raise ValueError(f"patches must be a whole number >= 1, got {patches}")
    if max_edge is not None and not (max_edge > 0 and math.isfinite(max_edge)):
        raise ValueError(f"max_edge must be a positive length, got {max_edge}")
    if scene.n_patches == 0:
        return scene
    if patches is not None:
        scene = presplit(scene, PRESPLIT_EDGE * math.sqrt(scene.total_area / patches))
    mesh = _Mesh(scene)
    cos_tol = math.cos(math.radians(normal_tolerance))
    if max_edge is not None:
        splits = np.maximum(1, np.ceil(mesh.longest / max_edge - 1e-9)).astype(np.int64)
        eligible = mesh.longest < 0.5 * max_edge
        label, count = mesh.grow(eligible, cos_tol, np.inf, 0.5 * max_edge, merge=False)
        return _build(scene, splits, label, count, note=None)
    label, splits, count = _fit_count(mesh, int(patches), cos_tol)
    total = int((splits[splits > 1] ** 2).sum()) + count
    note = None
    if total > (1 + COUNT_TOLERANCE) * patches:
        floor = _fewest(mesh, cos_tol)
        why = (f"clusters cannot cross materials or groups, bend more than {normal_tolerance:g} degrees, "
               f"bridge gaps wider than {REACH:g} sqrt(patch area) or hold more than {MAX_TRIANGLES} triangles, "
               f"so this mesh needs at least about {max(floor, -(-mesh.areas.size // MAX_TRIANGLES)):,}")
        note = (f"--patches {patches:,} cannot be met: got {total:,} patches; " + why if floor > patches else
                f"--patches {patches:,} was met only to {total:,} patches (small separate parts limit the merging; "
                + why + ")")
    return _build(scene, splits, label, count, note=note)


def presplit(scene: Scene, max_edge: float) -> Scene:
    """The unclustered scene with every face longer than ``max_edge`` bisected until none is.

    Longest-edge bisection (cut at the midpoint of the longest edge, again and
    again): a sliver of length L becomes ~2 L / max_edge pieces, not the
    (L / max_edge)^2 of an m x m split, and a well-shaped face gets
    well-shaped pieces. Area and orientation are kept exactly; coincident
    points are merged (the growing welds by position anyway); ``parent``
    still names the input face. Unchanged when no face is that long.
    """
    tri = scene.triangles
    owner = np.arange(len(tri))
    long = _longest_edges(tri) > max_edge
    if not long.any():
        return scene
    done_tri, done_owner = [tri[~long]], [owner[~long]]
    tri, owner = tri[long], owner[long]
    while len(tri):
        # rotate each triangle so that its longest edge is (corner 0, corner 1), then cut it there
        k = np.argmax(np.linalg.norm(np.roll(tri, -1, axis=1) - tri, axis=2), axis=1)
        rot = (k[:, None] + np.arange(3)[None]) % 3
        a, b, c = (tri[np.arange(len(tri)), rot[:, q]] for q in range(3))
        mid = 0.5 * (a + b)
        tri = np.concatenate([np.stack([a, mid, c], axis=1), np.stack([mid, b, c], axis=1)])
        owner = np.concatenate([owner, owner])
        long = _longest_edges(tri) > max_edge
        done_tri.append(tri[~long])
        done_owner.append(owner[~long])
        tri, owner = tri[long], owner[long]
    tri = np.concatenate(done_tri)
    owner = np.concatenate(done_owner)
    order = np.argsort(owner, kind="stable")  # pieces of one face together, in face order
    tri, owner = tri[order], owner[order]
    points = tri.reshape(-1, 3)
    ids = weld(points, np.arange(len(points)).reshape(-1, 1)).reshape(-1)  # coincident points share an id
    vertices = np.empty((int(ids.max()) + 1, 3))
    vertices[ids] = points
    faces = ids.reshape(-1, 3)
    return Scene(vertices=vertices, faces=faces, material=scene.material[owner], materials=scene.materials,
                 group=scene.group[owner], groups=scene.groups, reflectance=scene.reflectance[owner],
                 emission=scene.emission[owner], parent=scene.parent[owner],
                 occluder_vertices=scene.occluder_vertices, occluder_faces=scene.occluder_faces,
                 name=scene.name, warnings=scene.warnings)


def _longest_edges(tri: np.ndarray) -> np.ndarray:
    """(t,) longest edge of each of (t, 3, 3) triangles."""
    if not len(tri):
        return np.zeros(0)
    return np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)


def _fit_count(mesh: _Mesh, patches: int, cos_tol: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Secant steps on the target area until the patch count is within COUNT_TOLERANCE."""
    total_area = float(mesh.areas.sum())
    factor = 1.0
    best = None
    for _ in range(8):
        a_max = factor * total_area / patches
        splits = np.maximum(1, np.rint(np.sqrt(mesh.areas / a_max))).astype(np.int64)
        eligible = splits == 1
        label, count = mesh.grow(eligible, cos_tol, a_max, REACH * math.sqrt(a_max), merge=True)
        total = int((splits[~eligible] ** 2).sum()) + count
        if best is None or abs(total - patches) < abs(best[0] - patches):
            best = (total, label, splits, count)
        if abs(total - patches) <= COUNT_TOLERANCE * patches:
            break
        # patch count ~ 1 / target area where clustering works; damp the step
        factor *= (total / patches) ** 0.9
    return best[1], best[2], best[3]


def _fewest(mesh: _Mesh, cos_tol: float) -> int:
    """Patches left when clusters may grow without limit (materials, groups, creases, gaps)."""
    eligible = np.ones(len(mesh.areas), bool)
    total = float(mesh.areas.sum())
    return mesh.grow(eligible, cos_tol, total, float(np.ptp(mesh.centroids, axis=0).max()), merge=True,
                     max_triangles=len(mesh.areas))[1]


def _build(scene: Scene, splits: np.ndarray, label: np.ndarray, count: int, note: str | None) -> Scene:
    """The clustered scene: split faces become one patch per piece, clusters one patch each."""
    split_scene, owner = split_faces(scene, splits)
    # a piece of a split face, or a face that was not grown (too long), is a patch on its own
    single = (splits[owner] > 1) | (label[owner] < 0)
    tri_patch = np.empty(len(owner), np.int64)
    tri_patch[~single] = label[owner[~single]]
    tri_patch[single] = count + np.arange(int(single.sum()))
    n = count + int(single.sum())
    # one face -> one patch: per-patch material etc. from any of its triangles
    first = np.full(n, -1, np.int64)
    first[tri_patch[::-1]] = np.arange(len(tri_patch))[::-1]
    # patches in Z-order of their centroids, triangles grouped by patch
    draft = split_scene.replace(material=split_scene.material[first], group=split_scene.group[first],
                                reflectance=split_scene.reflectance[first], emission=split_scene.emission[first],
                                triangle_patch=tri_patch)
    rank = np.empty(n, np.int64)
    rank[zorder_permutation(draft.centroids)] = np.arange(n)
    tri_patch = rank[tri_patch]
    tri_order = np.argsort(tri_patch, kind="stable")
    first_sorted = first[np.argsort(rank)]
    warnings = split_scene.warnings + ((note,) if note else ())
    return Scene(
        vertices=split_scene.vertices, faces=split_scene.faces[tri_order],
        material=split_scene.material[first_sorted], materials=scene.materials,
        group=split_scene.group[first_sorted], groups=scene.groups,
        reflectance=split_scene.reflectance[first_sorted], emission=split_scene.emission[first_sorted],
        parent=split_scene.parent[tri_order], triangle_patch=tri_patch[tri_order],
        occluder_vertices=scene.occluder_vertices, occluder_faces=scene.occluder_faces,
        name=scene.name, warnings=warnings)


def patch_diameters(scene: Scene) -> np.ndarray:
    """(n,) metres: twice the largest distance of a patch's corners from its centroid.

    At least the patch's diameter and at most twice it (a disk: exactly it).
    """
    start, index = scene.patch_triangles
    if not len(index):
        return np.zeros(scene.n_patches)
    owner = np.repeat(np.arange(scene.n_patches), np.diff(start))
    reach = np.linalg.norm(scene.triangles[index] - scene.centroids[owner][:, None], axis=2).max(axis=1)
    return 2.0 * np.maximum.reduceat(reach, start[:-1])


def compactness(scene: Scene) -> np.ndarray:
    """(n,) D^2 / A per patch, D from :func:`patch_diameters`: 4 / pi for a disk, about 2.3 to 5 for
    squares and equilateral triangles, ~ length / width for a long strip."""
    if not scene.n_patches:
        return np.zeros(0)
    return patch_diameters(scene) ** 2 / np.maximum(scene.areas, 1e-300)


def cluster_summary(scene: Scene) -> dict:
    """What clustering did: patches, triangles per patch, worst non-flatness, compactness."""
    per = np.bincount(scene.patch_of_triangle, minlength=scene.n_patches) if scene.n_patches else np.zeros(0, int)
    nf = scene.non_flatness
    q = compactness(scene)
    return {
        "clustered": scene.is_clustered,
        "triangles": scene.n_triangles,
        "triangles_per_patch": {"mean": float(per.mean()) if per.size else 0.0,
                                "max": int(per.max(initial=0)), "median": float(np.median(per)) if per.size else 0.0},
        "worst_non_flatness": float(nf.max(initial=0.0)),
        "area_cv": float(scene.areas.std() / scene.areas.mean()) if per.size else 0.0,
        "compactness": {"median": float(np.median(q)) if q.size else 0.0,
                        "p99": float(np.percentile(q, 99)) if q.size else 0.0, "max": float(q.max(initial=0.0))},
    }
