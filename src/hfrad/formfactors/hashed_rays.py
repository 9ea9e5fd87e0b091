"""Rays between hashed points of patch pairs, made, traced and counted a chunk at a time.

The H-matrix's build (:mod:`hfrad.formfactors.hmatrix`) decides visibility with short runs of
segments between points of two patches' probe designs (:meth:`Visibility.hashed_ray_points`), each
point picked by a hash of the pair and the ray (:func:`unit_hash`: the same pair and ray, the
same segment, whichever block or thread asks):

- :func:`probe_counts`: a row patch against a column node, ``k`` rays to targets spread over
  the node (the probes that find shadow edges);
- :func:`scale_by_edge_visibility`: every pair of a block across a shadow edge, ``k`` rays each,
  its form factor scaled by the unblocked share.

Both fill small reused buffers with the segments whose patches face each other (only those
reach Embree), trace them, and count per row or pair before the next chunk. Made whole
(four index arrays, then origins and directions, of every ray of a probe round) the rays took
more time than Embree's tracing of them: each round paged in fresh memory, 60 bytes a ray,
and 58% of the probes' segments join patches that do not face each other (Cornell box,
39,482 patches).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .segments import ray_buffers, segment_into

__all__ = ["unit_hash", "probe_counts", "scale_by_edge_visibility", "CHUNK_RAYS"]

#: Segments made and traced at a time (about 4 MB of buffers): two of the ray caster's
#: smallest hand-offs, so that a caster with threads splits each chunk between two of them.
CHUNK_RAYS = 1 << 17


@njit(cache=True, nogil=True)
def unit_hash(a, b, k):  # pragma: no cover (numba)
    """A uniform number in [0, 1) from three integers (a splitmix64 step): the same (a, b, k), the same number."""
    x = (np.uint64(a) * np.uint64(0x9E3779B97F4A7C15) ^ np.uint64(b) * np.uint64(0xBF58476D1CE4E5B9)
         ^ np.uint64(k) * np.uint64(0x94D049BB133111EB))
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    x = x ^ (x >> np.uint64(31))
    return np.float64(x >> np.uint64(11)) / 9007199254740992.0


def _buffers(rays: int):
    """Origins, directions, lengths (float32) and owners (int64) for ``rays`` segments."""
    o, d, t, w = ray_buffers(rays)
    return o, d, t, w.view(np.int64)


def probe_counts(vis, rows: np.ndarray, c: np.ndarray, node_start: np.ndarray, node_size: np.ndarray,
                 perm: np.ndarray, first: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(facing, blocked) counts (len(rows),) int64 of rays ``first .. first + k - 1`` from each row
    position ``rows[a]`` to column node ``c[a]``: ray s goes to the node's patch at a hashed place in
    the s-th of k equal parts of its range (positions ``node_start``, ``node_size`` of the tree order
    ``perm``), from a hashed point of the row patch's probe design to one of the target's."""
    P, normals = vis.hashed_ray_points()
    rows, c = np.asarray(rows, np.int64), np.asarray(c, np.int64)
    n_facing, n_blocked = np.zeros(len(rows), np.int64), np.zeros(len(rows), np.int64)
    o, d, t, owner = _buffers(max(CHUNK_RAYS, k))
    a = 0
    while a < len(rows):
        a, q = _fill_probes(rows, c, node_start, node_size, perm, int(first), int(k), P.shape[1], P, normals, a,
                            o, d, t, owner)
        hit = vis.cast_segments(o[:q], d[:q], t[:q])
        _count(owner, hit, q, n_facing, n_blocked)
    vis.rays_cast += int(n_facing.sum())
    return n_facing, n_blocked


def scale_by_edge_visibility(vis, F: np.ndarray, rows: np.ndarray, cols: np.ndarray, k: int) -> None:
    """Multiply each positive ``F[a, b]`` (C-contiguous; patches ``rows[a]``, ``cols[b]``) by the
    unblocked share of ``k`` segments between hashed points of the two patches' probe designs (left as
    it is where none of them faces both patches)."""
    if not F.flags.c_contiguous:
        raise ValueError("F must be C-contiguous: it is scaled in place through a flat view")
    P, normals = vis.hashed_ray_points()
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    rays = max(CHUNK_RAYS, len(cols) * k)
    o, d, t, owner = _buffers(rays)
    pair_at = np.empty(rays, np.int64)
    n_facing, n_blocked = np.empty(rays, np.int64), np.empty(rays, np.int64)
    a = cast = 0
    while a < F.shape[0]:
        a, q, p = _fill_pairs(F, rows, cols, int(k), P.shape[1], P, normals, a, o, d, t, owner, pair_at)
        hit = vis.cast_segments(o[:q], d[:q], t[:q])
        _scale_pairs(F.reshape(-1), pair_at, p, owner, hit, q, n_facing, n_blocked)
        cast += q
    vis.rays_cast += cast


@njit(cache=True, nogil=True)
def _fill_probes(rows, c, node_start, node_size, perm, first, k, points, P, normals, a, o, d, t,
                 owner):  # pragma: no cover (numba)
    """The facing segments of :func:`probe_counts` for rows ``a, a + 1, ...`` while k more fit; ``owner``
    their row. Returns (the next row, segments written)."""
    q, cap, m = 0, t.shape[0], rows.shape[0]
    while a < m and q + k <= cap:
        r, node = rows[a], c[a]
        size = node_size[node]
        for s in range(k):
            ray = first + s
            target = node_start[node] + min(int((s + unit_hash(r, node, ray)) * size / k), size - 1)
            ki, kj = int(unit_hash(r, target, ray) * points), int(unit_hash(target, r, ray) * points)
            if segment_into(P, normals, perm[r], ki, perm[target], kj, o, d, t, q):
                owner[q] = a
                q += 1
        a += 1
    return a, q


@njit(cache=True, nogil=True)
def _count(owner, hit, q, n_facing, n_blocked):  # pragma: no cover (numba)
    for x in range(q):
        n_facing[owner[x]] += 1
        if hit[x]:
            n_blocked[owner[x]] += 1


@njit(cache=True, nogil=True)
def _fill_pairs(F, rows, cols, k, points, P, normals, a, o, d, t, owner, pair_at):  # pragma: no cover (numba)
    """The facing segments of :func:`scale_by_edge_visibility` for rows ``a, a + 1, ...`` of F while a
    whole row's fit; ``pair_at`` the flat index of each pair with F > 0, ``owner`` each segment's pair.
    Returns (the next row, segments, pairs)."""
    q = p = 0
    cap, b_, m = t.shape[0], cols.shape[0], F.shape[0]
    while a < m and q + b_ * k <= cap and p + b_ <= cap:
        for b in range(b_):
            if F[a, b] > 0:
                i, j = rows[a], cols[b]
                pair_at[p] = a * b_ + b
                for s in range(k):
                    if segment_into(P, normals, i, int(unit_hash(i, j, s) * points), j,
                                    int(unit_hash(j, i, s) * points), o, d, t, q):
                        owner[q] = p
                        q += 1
                p += 1
        a += 1
    return a, q, p


@njit(cache=True, nogil=True)
def _scale_pairs(flat, pair_at, p, owner, hit, q, n_facing, n_blocked):  # pragma: no cover (numba)
    n_facing[:p] = 0
    n_blocked[:p] = 0
    _count(owner, hit, q, n_facing, n_blocked)
    for y in range(p):
        if n_facing[y] > 0:
            flat[pair_at[y]] *= 1.0 - n_blocked[y] / n_facing[y]
