"""One probe ray per pair first; more rays only where the probes of neighbouring pairs disagree.

Visibility between two patches is piecewise constant over the space of pairs:
a patch pair deep inside a shadow, or in full view, has the same visibility as
the pairs around it. Casting many rays for every pair spends most rays where
one would do. Here each pair that needs rays (visibility.py: its unoccluded F
is positive and an occluder may cut it) first gets one *probe* segment, from
centroid to centroid (moved off the surfaces). The pair (i, j) keeps the
probe's answer (0 or 1) when the probes of its *neighbouring pairs*

    (a, j) for a in nb(i)   and   (i, b) for b in nb(j)

(nb = the ``NEIGHBOURS`` patches nearest by centroid, and any tied with them)
all say the same, and is sent to the boundary rays (visibility.py:
max(samples, BOUNDARY_SAMPLES) kernel-weighted segments, and their second
round) otherwise: the
pairs along a shadow boundary, whose visibility is partial, are exactly the
pairs whose neighbours disagree. A neighbour pair whose patches do not face
each other (a neighbour on another face, around an edge or a corner) counts as
disagreeing: where an occluder meets a receiver (contact shadows), the pairs
across the boundary do not exist, and the probe alone would miss a shadow that
covers half of the patch. Close pairs (centroid distance below
``PROBE_NEAR`` (D_i + D_j)) and large pairs (F_ij or F_ji >= PROBE_BELOW)
always get every ray. Pairs no occluder can cut say "visible".

Probes join centroids, not points near a corner of each triangle: corner
points of a whole neighbourhood can sit in one occluder's shadow while most of
each patch sees past it, so every neighbour probes "blocked", the pair keeps
0, and its row loses a visible share of its sum.

Every part of the decision is symmetric in (i, j) (the neighbour set, the
pair states, the probe segment cast in canonical order, the distance and size
tests), so V_ij == V_ji bit for bit, and it depends on the pair only, never on
the block it is computed in: blocks computed anywhere, in any order, agree.
The states of neighbour pairs are geometric (silent: the patches do not face
each other; visible: no occluder can cut the pair; else the probe), so the
block's border (neighbour columns outside it) costs probes but no kernel.

Cost: one segment per pair that needs rays, plus the boundary rays of the
flagged pairs, instead of ``samples`` segments for each; the saving grows with
the share of pairs in full view or deep shadow (benchmarks/README.md records
it). ``NEIGHBOURS`` = 8 per side: with 4, shadow boundaries between probes go
unseen more often and the row sums' worst error grows.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

from .kernel import row_chunks
from .segments import RAY_BATCH

#: Pairs with F_ij or F_ji at least this large always get every ray: a row's sum is made of
#: few such pairs, so a probe that happens to agree with its neighbours must not decide them.
PROBE_BELOW = 1e-3

#: Pairs closer than PROBE_NEAR * (D_i + D_j) (centroid distance, longest edges) always get
#: every ray: a probe between near patches says little about the pair.
PROBE_NEAR = 2.0

#: Nearest patches whose pairs a pair's probe is compared with (per side).
NEIGHBOURS = 8

# neighbour-pair states
_VISIBLE, _BLOCKED, _SILENT, _PENDING = 0, 1, 2, 3


def nearest_patches(centroids: np.ndarray, k: int = NEIGHBOURS) -> np.ndarray:
    """(n, 2k) int64: each patch's k nearest other patches by centroid, and all tied with the k-th.

    Ties are common (subdivided walls are regular grids) and rounding would
    break them differently for a translated copy of the scene; so every patch
    within (1 + 1e-6) times the k-th distance is a neighbour (up to 2k of them),
    and unused slots hold -1.
    """
    n = len(centroids)
    width = 2 * k
    q = min(width + 1, n)
    out = np.full((n, width), -1, np.int64)
    if q <= 1:
        return out
    dist, nb = cKDTree(centroids).query(centroids, q)
    dist, nb = np.atleast_2d(dist), np.atleast_2d(np.asarray(nb, np.int64))
    other = nb != np.arange(n)[:, None]
    kth = np.sort(np.where(other, dist, np.inf), axis=1)[:, min(k, q - 1) - 1]
    keep = other & (dist <= kth[:, None] * (1 + 1e-6))
    for row in range(n):  # n small loops of <= 2k + 1: cheap next to the form factors
        chosen = nb[row, keep[row]][:width]
        out[row, :len(chosen)] = chosen
    return out


@njit(cache=True, inline="always")
def cuttable(i, j, front, back, below, above):
    """Some occluder may cut a segment between patches i and j (symmetric bitwise test).

    Per occluder: not wholly in front of both patches' planes, not wholly behind
    both, and its box overlaps the box of the pair (see visibility.py).
    """
    for w in range(front.shape[1]):
        m = ~((front[i, w] & front[j, w]) | (back[i, w] & back[j, w]))
        for axis in range(3):
            m &= (below[i, axis, w] | below[j, axis, w]) & (above[i, axis, w] | above[j, axis, w])
        if m != 0:
            return True
    return False


def one_word_bits(front, back, below, above) -> np.ndarray:
    """(n, 8) uint64: each patch's front, back, below (3 axes) and above (3 axes) masks, for
    scenes with at most 64 occluders (one word per mask; see :func:`cuttable_one_word`)."""
    return np.ascontiguousarray(np.column_stack([front[:, 0], back[:, 0], below[:, :, 0], above[:, :, 0]]))


@njit(cache=True, inline="always")
def cuttable_one_word(f, b, lx, ly, lz, ax, ay, az, col_bits, c):
    """:func:`cuttable` for one-word masks: the row patch's eight words given, column c's in
    ``col_bits[:, c]`` (:func:`one_word_bits` of the columns, transposed: column index last, so
    a loop over a row's columns reads each word contiguously). The same bitwise test."""
    m = ~((f & col_bits[0, c]) | (b & col_bits[1, c]))
    m &= (lx | col_bits[2, c]) & (ax | col_bits[5, c])
    m &= (ly | col_bits[3, c]) & (ay | col_bits[6, c])
    m &= (lz | col_bits[4, c]) & (az | col_bits[7, c])
    return m != 0


@njit(cache=True, inline="always")
def _in_front(P, plane, a, b):
    """Some sample point of patch a lies in front of patch b's plane."""
    for k in range(P.shape[1]):
        if plane[b, 0] * P[a, k, 0] + plane[b, 1] * P[a, k, 1] + plane[b, 2] * P[a, k, 2] > plane[b, 3]:
            return True
    return False


def _pair_states(rows, cols, P, plane, front, back, below, above, cull, state, bits=None):
    """state[r, c]: silent (the patches do not face each other), visible (no occluder can cut
    the pair) or pending (a probe decides); a function of the pair alone, symmetric.
    ``bits``: :func:`one_word_bits` of the masks when the caller keeps them (else made here)."""
    if cull and front.shape[1] == 1:  # at most 64 occluders: one word per mask
        bits = one_word_bits(front, back, below, above) if bits is None else bits
        # the columns' points, planes and bits gathered once, column index last (vectorized loops)
        _pair_states_one_word(rows, cols, P, plane, np.ascontiguousarray(P[cols].transpose(1, 2, 0)),
                              np.ascontiguousarray(plane[cols].T), bits, np.ascontiguousarray(bits[cols].T),
                              state, row_chunks(len(rows)))
    else:
        _pair_states_words(rows, cols, P, plane, front, back, below, above, cull, state)


@njit(parallel=True, cache=True, nogil=True)
def _pair_states_one_word(rows, cols, P, plane, col_P, col_plane, bits, col_bits, state, chunks):
    """:func:`_pair_states` with one 64-bit word per mask (``bits`` from :func:`one_word_bits`).

    The columns' points ``col_P`` (s, 3, nc), planes ``col_plane`` (4, nc) and bits ``col_bits``
    (8, nc) are laid out column index last, so each test runs over a row's columns without a
    branch (SIMD): the same tests with the same roundings as :func:`_in_front` and
    :func:`cuttable`, so the same states. Rows go in ``chunks`` parts.
    """
    nr, nc = state.shape
    s = P.shape[1]
    for t in prange(chunks):
        front_ij = np.empty(nc, np.bool_)   # some point of the row patch in front of column c's plane
        front_ji = np.empty(nc, np.bool_)   # some point of column c in front of the row patch's plane
        for r in range(t * nr // chunks, (t + 1) * nr // chunks):
            i = rows[r]
            front_ij[:] = False
            front_ji[:] = False
            for k in range(s):
                x, y, z = P[i, k, 0], P[i, k, 1], P[i, k, 2]
                for c in range(nc):
                    front_ij[c] |= col_plane[0, c] * x + col_plane[1, c] * y + col_plane[2, c] * z > col_plane[3, c]
            a, b, e, d = plane[i, 0], plane[i, 1], plane[i, 2], plane[i, 3]
            for k in range(s):
                for c in range(nc):
                    front_ji[c] |= a * col_P[k, 0, c] + b * col_P[k, 1, c] + e * col_P[k, 2, c] > d
            f, bk = bits[i, 0], bits[i, 1]
            lx, ly, lz, ax, ay, az = bits[i, 2], bits[i, 3], bits[i, 4], bits[i, 5], bits[i, 6], bits[i, 7]
            for c in range(nc):
                cut = cuttable_one_word(f, bk, lx, ly, lz, ax, ay, az, col_bits, c)
                pending = np.int8(_PENDING) if cut else np.int8(_VISIBLE)
                state[r, c] = pending if front_ij[c] and front_ji[c] and cols[c] != i else np.int8(_SILENT)


@njit(parallel=True, cache=True, nogil=True)
def _pair_states_words(rows, cols, P, plane, front, back, below, above, cull, state):
    """:func:`_pair_states`, any number of words per mask (or no culling)."""
    for r in prange(rows.shape[0]):
        i = rows[r]
        for c in range(cols.shape[0]):
            j = cols[c]
            if i == j or not (_in_front(P, plane, i, j) and _in_front(P, plane, j, i)):
                state[r, c] = _SILENT
            elif cull and not cuttable(i, j, front, back, below, above):
                state[r, c] = _VISIBLE
            else:
                state[r, c] = _PENDING


def _probe(vis, R: np.ndarray, Cc: np.ndarray, state: np.ndarray) -> None:
    """Cast one probe segment for every pending pair of ``state`` (len(R), len(Cc)) in place.

    The probe joins the centroids of the two patches (the 1 x 1 design, moved
    off the surfaces; for a clustered patch the point halfway through its area),
    cast in canonical order. Rows go in
    chunks so that no more than about RAY_BATCH probes are held at once.
    """
    nc = len(Cc)
    step = max(1, RAY_BATCH // max(nc, 1))
    where = None
    for r0 in range(0, len(R), step):
        r1 = min(len(R), r0 + step)
        cap = (r1 - r0) * nc
        buf = vis.buffers.get(cap)  # reused: fresh pages cost page faults
        if where is None or len(where) < cap:
            where = np.empty(cap, np.int64)
        m = _gather_probes(state, R, Cc, r0, r1, vis.probe_points, buf[0], buf[1], buf[2], where)
        if m:
            hit = vis.cast_segments(buf[0][:m], buf[1][:m], buf[2][:m], "probe")
            _store_probes(state, where, hit, m)
            vis.rays_probe += m
            vis.rays_cast += m
        vis.buffers.put(buf)


@njit(cache=True, nogil=True)
def _gather_probes(state, R, Cc, r0, r1, P, o, d, t, where):
    """The probe segments (centroid points ``P[:, 0]``, lower patch first) of the pending pairs
    of rows r0..r1, written to o, d, t; ``where`` gets their flat positions. Returns their
    count. (One pass in numba: no index arrays gathered in NumPy; the segments are those of
    :func:`~hfrad.formfactors.segments.fill_rays`, bit for bit.)"""
    nc = Cc.shape[0]
    m = 0
    for r in range(r0, r1):
        for c in range(nc):
            if state[r, c] != _PENDING:
                continue
            a = min(R[r], Cc[c])  # canonical direction: V_ij == V_ji exactly
            b = max(R[r], Cc[c])
            dx = P[b, 0, 0] - P[a, 0, 0]
            dy = P[b, 0, 1] - P[a, 0, 1]
            dz = P[b, 0, 2] - P[a, 0, 2]
            L = math.sqrt(dx * dx + dy * dy + dz * dz)
            inv = 1.0 / L if L > 0.0 else 0.0
            o[m, 0] = P[a, 0, 0]
            o[m, 1] = P[a, 0, 1]
            o[m, 2] = P[a, 0, 2]
            d[m, 0] = dx * inv
            d[m, 1] = dy * inv
            d[m, 2] = dz * inv
            t[m] = L
            where[m] = r * nc + c
            m += 1
    return m


@njit(cache=True, nogil=True)
def _store_probes(state, where, hit, m):
    """The probes' answers into the pending pairs' states (``where``: flat positions in ``state``)."""
    flat = state.reshape(-1)   # C-contiguous: no division per probe
    for k in range(m):
        flat[where[k]] = _BLOCKED if hit[k] else _VISIBLE


def full_ray_pairs(vis, F: np.ndarray, rows: np.ndarray, cols: np.ndarray, need: np.ndarray,
                   overlay=None) -> np.ndarray:
    """The pairs of ``need`` that get every ray; the others take their probe's answer in ``F``.

    ``F`` (len(rows), len(cols)) is the unoccluded block; the probe-only pairs
    whose probe was blocked are set to 0 here. ``overlay(state, R, Cc)``, when
    given, may set the (len(R), len(Cc)) int8 states of the pairs (neighbours
    included: ``R``, ``Cc``) that another test decided before any probe is cast
    (a pending pair set to visible or blocked gets no probe ray).
    """
    nb = vis.neighbours
    r, c = len(rows), len(cols)
    R, Cc = _with_neighbours(rows, nb), _with_neighbours(cols, nb)
    state = np.empty((len(R), len(Cc)), np.int8)
    _pair_states(R, Cc, vis.points, vis.plane, vis.front_bits, vis.back_bits, vis.below_bits, vis.above_bits,
                 vis.cull, state, vis.word_bits)
    if overlay is not None:
        overlay(state, R, Cc)
    _probe(vis, R, Cc, state)
    n = len(nb)
    row_pos = np.full(n, -1, np.int64)
    row_pos[R] = np.arange(len(R))
    col_pos = np.full(n, -1, np.int64)
    col_pos[Cc] = np.arange(len(Cc))
    full = np.empty((r, c), np.bool_)
    _decide(state, row_pos, col_pos, rows, cols, nb, vis.centroids, vis.diameters, vis.probe_near,
            F, vis.areas, vis.probe_below, need, full, row_chunks(r))
    return full


def _with_neighbours(patches: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """``patches`` followed by their neighbours that are not among them (probe states are needed for both)."""
    n = len(nb)
    if len(patches) == n and np.bincount(patches, minlength=n).all():
        return patches   # every patch (a column block's rows): no neighbour is missing
    # the missing neighbours in increasing order (as np.setdiff1d gives them) by marks, not sorting
    missing = np.zeros(n + 1, np.bool_)          # slot n takes the unused neighbour slots (-1)
    missing[nb[patches].ravel()] = True
    missing[patches] = False
    return np.concatenate([patches, np.flatnonzero(missing[:n])])


@njit(parallel=True, cache=True, nogil=True)
def _decide(state, row_pos, col_pos, rows, cols, nb, C, D, near, F, areas, below, need, out, chunks):
    """out[r, c]: pair (r, c) needs rays and is close, or large (max(F_ij, F_ji) >= below), or
    unprobed, or a neighbour pair's state differs from its probe; a pair that keeps its
    probe and was found blocked gets F = 0. (A_i F_ij is symmetric, so the size test is too.)

    The neighbour tests are laid out for the block: a row's neighbour rows are compared with it
    column by column (contiguous bytes), and a column's neighbour columns are bits over
    ``state``'s columns, tested against the row's set of columns in each state. Rows go in
    ``chunks`` parts (each with its own work arrays).
    """
    nr, nc = out.shape
    k = nb.shape[1]
    words = (state.shape[1] + 63) // 64
    col_words, col_masks, col_count = _column_neighbour_bits(cols, nb, col_pos)
    for t in prange(chunks):
        in_state = np.empty((4, words), np.uint64)   # per state, the row's columns in that state
        agree = np.empty(nc, np.bool_)                # the row's neighbour rows agree, per column
        for r in range(t * nr // chunks, (t + 1) * nr // chunks):
            i = rows[r]
            own_row = state[r]
            in_state[:] = 0
            for p in range(state.shape[1]):
                in_state[own_row[p], p >> 6] |= np.uint64(1) << np.uint64(p & 63)
            agree[:] = True
            for a in range(k):
                if nb[i, a] >= 0:
                    other = state[row_pos[nb[i, a]]]
                    for c in range(nc):
                        agree[c] &= other[c] == own_row[c]
            for c in range(nc):
                if not need[r, c]:
                    out[r, c] = False
                    continue
                j = cols[c]
                own = own_row[c]
                dx = C[i, 0] - C[j, 0]
                dy = C[i, 1] - C[j, 1]
                dz = C[i, 2] - C[j, 2]
                differs = (own == _SILENT or dx * dx + dy * dy + dz * dz < (near * (D[i] + D[j])) ** 2
                           or F[r, c] * areas[i] >= below * min(areas[i], areas[j]) or not agree[c])
                for e in range(col_count[c]):
                    if differs:
                        break
                    differs = (col_masks[c, e] & ~in_state[own, col_words[c, e]]) != 0
                out[r, c] = differs
                if not differs and own == _BLOCKED:
                    F[r, c] = 0.0


@njit(cache=True, nogil=True)
def _column_neighbour_bits(cols, nb, col_pos):
    """Each column's neighbours as bits over the state's columns: its nonzero 64-bit words
    (``words[c, :count[c]]`` which, ``masks[c, :count[c]]`` the bits)."""
    nc, k = cols.shape[0], nb.shape[1]
    words = np.zeros((nc, k), np.int64)
    masks = np.zeros((nc, k), np.uint64)
    count = np.zeros(nc, np.int64)
    for c in range(nc):
        for a in range(k):
            q = nb[cols[c], a]
            if q < 0:
                continue
            p = col_pos[q]
            w, bit = p >> 6, np.uint64(1) << np.uint64(p & 63)
            e = 0
            while e < count[c] and words[c, e] != w:
                e += 1
            if e == count[c]:
                words[c, e] = w
                count[c] += 1
            masks[c, e] |= bit
    return words, masks, count
