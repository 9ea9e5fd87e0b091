"""Segments between sample points, ready for Embree: which are valid, their end points and
kernel weights, and the reusable buffers that hold them.

Shared by the visibility rounds (visibility.py) and the probes (probing.py), which need the
same segments: one module below both, so neither imports the other. The second round's segments
are picked in proportion to their kernel weight among all pairs of two point designs
(:func:`importance_picks`, :func:`fill_picked`): each ray then stands for one or more equal picks
instead of carrying its own weight.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Rays per Embree call and per temporary buffer (bounds memory: 36 bytes a ray).
RAY_BATCH = 1 << 21


class RayJob:
    """One batch of segments: origins o, unit directions d, lengths t (float32), kernel weights w.

    ``buf`` and ``pool``: the buffers (o, d, t, w are views of them) and the pool to hand them back to.
    """

    __slots__ = ("pairs", "first", "o", "d", "t", "w", "buf", "pool", "r_idx", "c_idx", "final", "round")

    def __init__(self, pairs, first, o, d, t, w, buf, pool, r_idx, c_idx, final, round="") -> None:
        self.pairs, self.first, self.o, self.d, self.t, self.w = pairs, first, o, d, t, w
        self.buf, self.pool = buf, pool
        self.final = final  # no second round: its fraction is the pair's V
        self.r_idx, self.c_idx = r_idx, c_idx  # patch indices of each pair
        self.round = round  # the visibility round's name, for its counters (Visibility.rounds)


def ray_buffers(r: int):
    """Fresh buffers for ``r`` segments (at least one): origins, unit directions (r, 3) and lengths (r,)
    float32, and an (r,) float64 array (kernel weights, or 8-byte owners seen through ``view``)."""
    r = max(r, 1)
    return (np.empty((r, 3), np.float32), np.empty((r, 3), np.float32), np.empty(r, np.float32),
            np.empty(r, np.float64))


class RayBuffers:
    """A free list of ray buffers: fresh pages are slow to fault in, so reuse them."""

    def __init__(self) -> None:
        self._free: list = []

    def get(self, r: int):
        for k, buf in enumerate(self._free):
            if len(buf[2]) >= r:
                return self._free.pop(k)
        return ray_buffers(r)

    def put(self, buf) -> None:
        self._free.append(buf)


@njit(cache=True, nogil=True, inline="always")
def _in_front(P, plane, a, i, b, j):
    """Point i of patch a is in front of patch b's plane and point j of b in front of a's."""
    fa = (plane[b, 0] * P[a, i, 0] + plane[b, 1] * P[a, i, 1] + plane[b, 2] * P[a, i, 2]) > plane[b, 3]
    fb = (plane[a, 0] * P[b, j, 0] + plane[a, 1] * P[b, j, 1] + plane[a, 2] * P[b, j, 2]) > plane[a, 3]
    return fa and fb


@njit(cache=True, nogil=True, inline="always")
def _valid_by_planes(P, plane, ka, kb, a, b, valid):
    """valid[k]: segment k (point ka[k] of a to kb[k] of b) has both ends in front of the other
    patch's plane; all True if none has. Returns the count of valid segments."""
    m = 0
    for k in range(ka.shape[0]):
        valid[k] = _in_front(P, plane, a, ka[k], b, kb[k])
        if valid[k]:
            m += 1
    if m == 0:
        valid[:] = True
        m = ka.shape[0]
    return m


@njit(cache=True, nogil=True, inline="always")
def _put_segment(P, a, i, b, j, na, nb, o, d, t, w, row):
    """Row ``row`` of o, d, t, w: the segment from point i of patch a to point j of b, weighted by
    cos_a cos_b / L^2 with the normals na at its start and nb at its end."""
    dx = P[b, j, 0] - P[a, i, 0]
    dy = P[b, j, 1] - P[a, i, 1]
    dz = P[b, j, 2] - P[a, i, 2]
    L2 = dx * dx + dy * dy + dz * dz
    L = math.sqrt(L2)
    inv = 1.0 / L if L > 0.0 else 0.0
    o[row, 0] = P[a, i, 0]
    o[row, 1] = P[a, i, 1]
    o[row, 2] = P[a, i, 2]
    d[row, 0] = dx * inv
    d[row, 1] = dy * inv
    d[row, 2] = dz * inv
    t[row] = L
    ca = (na[0] * dx + na[1] * dy + na[2] * dz) * inv
    cb = -(nb[0] * dx + nb[1] * dy + nb[2] * dz) * inv
    w[row] = max(ca, 0.0) * max(cb, 0.0) / L2 if L2 > 0.0 else 0.0


@njit(parallel=True, cache=True, nogil=True)
def valid_rays(P, plane, partner, r_idx, c_idx, valid, counts):
    """A ray is valid if each end point is in front of the other patch's plane.

    The kernel already gives zero weight to points behind the other patch, so
    rays from them must not count as blocked a second time. A pair with no
    valid ray (a sliver only the near-field rule sees) keeps all of its rays.
    """
    own = np.arange(P.shape[1])
    for p in prange(r_idx.shape[0]):
        counts[p] = _valid_by_planes(P, plane, own, partner, min(r_idx[p], c_idx[p]), max(r_idx[p], c_idx[p]),
                                     valid[p])


@njit(parallel=True, cache=True, nogil=True)
def fill_rays(P, plane, partner, r_idx, c_idx, valid, first, o, d, t, w):
    """The valid segments of each pair, lower patch index first (V_ij == V_ji exactly), and each
    segment's weight w = cos_a cos_b / L^2 (the point-to-point kernel; patch plane normals)."""
    s = P.shape[1]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])  # canonical direction: V_ij == V_ji exactly
        b = max(r_idx[p], c_idx[p])
        row = first[p]
        for k in range(s):
            if valid[p, k]:
                _put_segment(P, a, k, b, partner[k], plane[a], plane[b], o, d, t, w, row)
                row += 1


@njit(cache=True, nogil=True, inline="always")
def segment_into(P, normals, a, pa, b, pb, o, d, t, k):  # pragma: no cover (numba)
    """Slot ``k`` of ``o``, ``d``, ``t``: the segment from point ``P[a, pa]`` to ``P[b, pb]`` (origin, unit
    direction, length) where patches a and b face each other along it (normals ``normals``), and True;
    elsewhere the length 0 (Embree finds no hit) and False."""
    vx, vy, vz = P[b, pb, 0] - P[a, pa, 0], P[b, pb, 1] - P[a, pa, 1], P[b, pb, 2] - P[a, pa, 2]
    length = math.sqrt(vx * vx + vy * vy + vz * vz)
    front = normals[a, 0] * vx + normals[a, 1] * vy + normals[a, 2] * vz
    back = normals[b, 0] * vx + normals[b, 1] * vy + normals[b, 2] * vz
    o[k, 0], o[k, 1], o[k, 2] = P[a, pa, 0], P[a, pa, 1], P[a, pa, 2]
    if front > 0.0 and back < 0.0 and length > 0.0:
        d[k, 0], d[k, 1], d[k, 2] = vx / length, vy / length, vz / length
        t[k] = length
        return True
    d[k, 0], d[k, 1], d[k, 2] = 1.0, 0.0, 0.0
    t[k] = 0.0
    return False


@njit(cache=True, parallel=True, nogil=True)
def probe_segments(P, normals, i, ki, j, kj, o, d, t, facing):  # pragma: no cover (numba)
    """One segment from point ``P[i[k], ki[k]]`` to ``P[j[k], kj[k]]`` for each k (``P`` (n, s, 3): s
    points a patch), where the two patches face each other (normals ``normals``): origins, unit
    directions and lengths into ``o``, ``d``, ``t`` (float32); elsewhere ``facing[k]`` is False and
    the length 0 (Embree finds no hit)."""
    for k in prange(i.size):
        facing[k] = segment_into(P, normals, i[k], ki[k], j[k], kj[k], o, d, t, k)


@njit(parallel=True, cache=True, nogil=True)
def valid_rays_on_triangles(P, N, plane, ka, kb, r_idx, c_idx, valid, counts, flat_pair):
    """:func:`valid_rays` for pairs with a patch that is not flat (points on triangles of normals
    ``N``, same shape as ``P``); segment k joins point ``ka[k]`` of the lower patch to ``kb[k]`` of
    the other.

    A segment is valid where it leaves the front of the triangle at each end (both cosines
    positive): the clustered kernel integrates each triangle with its own clamped cosines
    (clustered.py, eq. 3), so those are the segments its integrand weighs. A segment that passes
    through the patch's own other triangles is kept, and Embree finds it blocked (a curved or
    saw-toothed cluster shading itself). Testing the ends against the other patch's mean plane
    instead (:func:`valid_rays`) throws away exactly those. A pair with no such segment falls back
    to the mean planes' test, and ``flat_pair[p]`` says so.
    """
    s = ka.shape[0]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])
        b = max(r_idx[p], c_idx[p])
        m = 0
        for k in range(s):
            i, j = ka[k], kb[k]
            dx = P[b, j, 0] - P[a, i, 0]
            dy = P[b, j, 1] - P[a, i, 1]
            dz = P[b, j, 2] - P[a, i, 2]
            ok = (N[a, i, 0] * dx + N[a, i, 1] * dy + N[a, i, 2] * dz > 0.0
                  and N[b, j, 0] * dx + N[b, j, 1] * dy + N[b, j, 2] * dz < 0.0)
            valid[p, k] = ok
            if ok:
                m += 1
        flat_pair[p] = m == 0
        counts[p] = _valid_by_planes(P, plane, ka, kb, a, b, valid[p]) if m == 0 else m


@njit(parallel=True, cache=True, nogil=True)
def fill_rays_on_triangles(P, N, plane, ka, kb, r_idx, c_idx, valid, first, flat_pair, o, d, t, w):
    """:func:`fill_rays` for the segments of :func:`valid_rays_on_triangles`, each weighted by the
    cosines of the triangles its ends lie on (normals ``N``), or of the patch planes where
    ``flat_pair[p]``."""
    s = ka.shape[0]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])
        b = max(r_idx[p], c_idx[p])
        row = first[p]
        for k in range(s):
            if not valid[p, k]:
                continue
            i, j = ka[k], kb[k]
            if flat_pair[p]:
                _put_segment(P, a, i, b, j, plane[a], plane[b], o, d, t, w, row)
            else:
                _put_segment(P, a, i, b, j, N[a, i], N[b, j], o, d, t, w, row)
            row += 1


@njit(cache=True, nogil=True, inline="always")
def _plane_weight(P, plane, a, i, b, j, uniform):
    """The kernel weight of candidate segment (point i of patch a, point j of b) with the patch
    planes' normals: cos_a cos_b / L^2 (0 unless both are positive), or 1 if ``uniform``."""
    if uniform:
        return 1.0
    dx = P[b, j, 0] - P[a, i, 0]
    dy = P[b, j, 1] - P[a, i, 1]
    dz = P[b, j, 2] - P[a, i, 2]
    L2 = dx * dx + dy * dy + dz * dz
    ca = plane[a, 0] * dx + plane[a, 1] * dy + plane[a, 2] * dz
    cb = -(plane[b, 0] * dx + plane[b, 1] * dy + plane[b, 2] * dz)
    if ca <= 0.0 or cb <= 0.0 or not L2 > 0.0:
        return 0.0
    return ca * cb / (L2 * L2)  # (ca / L) (cb / L) / L^2


@njit(cache=True, nogil=True)
def _triangle_weights(Pa, Na, Pb, Nb, W, rows):
    """W[i, j] = the kernel weight cos_a cos_b / L^2 (0 unless both are positive) from point i of ``Pa``
    (s, 3) to point j of ``Pb`` (3, s: coordinates first, so that the inner loop vectorises), with
    the normals ``Na`` (s, 3) and ``Nb`` (3, s), then each row's cumulative sum; rows[i] the row's
    sum. Returns the total. No fastmath: the sums in order, the same bits on every machine."""
    s = Pa.shape[0]
    total = 0.0
    for i in range(s):
        ax, ay, az = Pa[i, 0], Pa[i, 1], Pa[i, 2]
        nx, ny, nz = Na[i, 0], Na[i, 1], Na[i, 2]
        for j in range(s):
            dx = Pb[0, j] - ax
            dy = Pb[1, j] - ay
            dz = Pb[2, j] - az
            L2 = dx * dx + dy * dy + dz * dz
            ca = max(nx * dx + ny * dy + nz * dz, 0.0)
            cb = max(-(Nb[0, j] * dx + Nb[1, j] * dy + Nb[2, j] * dz), 0.0)
            W[i, j] = ca * cb / max(L2 * L2, 1e-300)  # ca cb = 0 where L2 = 0
        row = 0.0
        for j in range(s):  # each row becomes its cumulative sum (the picks search it)
            row += W[i, j]
            W[i, j] = row
        rows[i] = row
        total += row
    return total


#: The second coordinate of pick k is frac(1/2 + k / golden ratio): with (k + 1/2) / m as the first,
#: the m picks form a Fibonacci-like lattice in the unit square, even in both directions.
_GOLDEN = 0.6180339887498949


@njit(parallel=True, cache=True, nogil=True)
def importance_picks(P, N, plane, r_idx, c_idx, picks, counts, modes):
    """Segments of each pair picked in proportion to their kernel weight, deterministically.

    The candidates are all s x s segments from point i of the lower patch a to point j of the
    other b (``P`` (patches, s, 3)). Pick k (of m = ``picks.shape[1]``) takes the point i where the
    cumulative weight of a's points (each summed over b's) first exceeds (k + 1/2) / m of the total,
    then the point j where the cumulative weight along i's row first exceeds frac(1/2 + k / golden
    ratio) of that row's: a two-dimensional low-discrepancy set pushed through the weight's
    marginal and conditional distributions, so the picks spread over both patches in proportion to
    the kernel. No random numbers, and a and b in canonical order: the picks of (i, j) and (j, i)
    are the same. The share of picks whose segment is free estimates the kernel-weighted visibility
    of the whole candidate set; each pick counts alike, so a few short heavy segments no longer
    carry the estimate alone (the fixed pairing's weakness on close pairs).

    Weights are cos cos / L^2 with the normals of the points' triangles ``N`` (``modes[p]`` = 0);
    where no candidate leaves the front of both triangles, the patch planes' normals (1); where
    none faces that way either, every candidate alike (2).

    Parameters
    ----------
    P, N : (patches, s, 3) float64
        Points (frame units) and the unit normals of the triangles they lie on.
    plane : (patches, 4) float64
        Patch planes (unit normal, offset).
    r_idx, c_idx : (k,) int64
        The two patches of each pair (indices into ``P``; either order).
    picks : (k, m) int64, out
        Candidate index i * s + j of each pick, sorted along a row.
    counts : (k,) int64, out
        Distinct candidates picked (the rays the pair needs).
    modes : (k,) int8, out
        The weights used (0, 1, 2 above).
    """
    s = P.shape[1]
    n = r_idx.shape[0]
    chunks = (n + _PICK_CHUNK - 1) // _PICK_CHUNK
    for c in prange(chunks):  # buffers once a chunk of pairs, not once a pair
        W = np.empty((s, s))
        rows = np.empty(s)
        Pb = np.empty((3, s))
        Nb = np.empty((3, s))
        for p in range(c * _PICK_CHUNK, min(n, (c + 1) * _PICK_CHUNK)):
            a = min(r_idx[p], c_idx[p])
            b = max(r_idx[p], c_idx[p])
            Pb[:] = P[b].T
            Nb[:] = N[b].T
            total = _triangle_weights(P[a], N[a], Pb, Nb, W, rows)
            mode = 0
            while not total > 0.0 and mode < 2:  # rare: the general (slower) loop with the next weights
                mode += 1
                total = _plane_weights(P, plane, a, b, mode == 2, W, rows)
            modes[p] = mode
            counts[p] = _pick(W, rows, total, picks[p])


#: Pairs a thread takes at a time in :func:`importance_picks`.
_PICK_CHUNK = 64


@njit(cache=True, nogil=True)
def _plane_weights(P, plane, a, b, uniform, W, rows):
    """:func:`_triangle_weights` with the weights of :func:`_plane_weight` (a slower loop)."""
    s = P.shape[1]
    total = 0.0
    for i in range(s):
        row = 0.0
        for j in range(s):
            row += _plane_weight(P, plane, a, i, b, j, uniform)
            W[i, j] = row
        rows[i] = row
        total += row
    return total


@njit(cache=True, nogil=True)
def _pick(W, rows, total, out):
    """The picks of :func:`importance_picks` from the rows' cumulative weights ``W`` (s, s), their
    sums ``rows`` and ``total``, into ``out`` (m,), sorted; returns how many are distinct."""
    s = W.shape[0]
    m = out.shape[0]
    i = 0
    cum = rows[0]
    for k in range(m):
        target = (k + 0.5) / m * total
        while cum <= target and i < s - 1:  # the targets grow with k: one sweep over the rows
            i += 1
            cum += rows[i]
        while rows[i] <= 0.0 and i > 0:  # rounding ran past the last row with weight
            i -= 1
        u = (0.5 + k * _GOLDEN) % 1.0 * rows[i]
        lo, hi = 0, s - 1  # the first j with W[i, j] > u (W[i]: the row's cumulative weight)
        while lo < hi:
            mid = (lo + hi) // 2
            if W[i, mid] > u:
                hi = mid
            else:
                lo = mid + 1
        j = lo
        while j > 0 and W[i, j] <= W[i, j - 1]:  # rounding ran past the row's last weight
            j -= 1
        out[k] = i * s + j
        q = k  # insertion sort: i never decreases with k, so a pick moves only past its row's
        while q > 0 and out[q - 1] > out[q]:
            out[q - 1], out[q] = out[q], out[q - 1]
            q -= 1
    distinct = 1
    for k in range(1, m):
        if out[k] != out[k - 1]:
            distinct += 1
    return distinct


@njit(parallel=True, cache=True, nogil=True)
def fill_picked(P, N, plane, r_idx, c_idx, picks, modes, first, o, d, t, w):
    """The distinct picked segments of each pair (:func:`importance_picks`), lower patch first, into
    rows first[p]:first[p + 1] of o, d, t; ``w`` the number of picks each stands for, so that the
    weighted free share of :func:`~hfrad.formfactors.visibility._scale_by_visibility` is the share
    of free picks."""
    s = P.shape[1]
    m = picks.shape[1]
    for p in prange(r_idx.shape[0]):
        a = min(r_idx[p], c_idx[p])
        b = max(r_idx[p], c_idx[p])
        row = first[p] - 1
        last = -1
        for k in range(m):
            c = picks[p, k]
            if c == last:
                w[row] += 1.0
                continue
            last = c
            row += 1
            i, j = c // s, c % s
            if modes[p] == 0:
                _put_segment(P, a, i, b, j, N[a, i], N[b, j], o, d, t, w, row)
            else:
                _put_segment(P, a, i, b, j, plane[a], plane[b], o, d, t, w, row)
            w[row] = 1.0
