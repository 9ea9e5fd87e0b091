"""Adaptive cross approximation (ACA) of far blocks of the unoccluded form-factor matrix.

A block of F between two well-separated patch clusters R (rows) and C (columns)
is numerically low rank in the unoccluded kernel. ACA with partial pivoting
(Bebendorf 2000; Rjasanow & Steinbach 2007, Alg. 3.9) builds

    F[R][:, C] ~= S_k = sum_{l<k} u_l v_l^T                                   (1)

from k rows and k columns of the block only: at step k it evaluates the
residual of one row i_k, takes its largest entry (column j_k) as the pivot,
v_k = residual row / pivot, u_k = residual column j_k, and moves to the row
where |u_k| is largest among the rows not yet used. It stops when

    ||u_k|| ||v_k|| <= tol ||S_k||_F                                          (2)

with ||S_k||_F^2 updated in O(k (m + b)) a step (||S_{k-1}||^2 + 2 sum_l
(u_l . u_k)(v_l . v_k) + ||u_k||^2 ||v_k||^2), or when the residual row is zero.

Neither proves the block done. A small term does not prove a small residual, and
form factors are zero by plane pairs (a patch behind or in the other's plane):
a cluster spanning several planes (a floor and the foot of a wall) gives a block
whose non-zero entries fill sub-blocks, and ACA's pivots never leave the first
sub-block they meet (k-d far blocks of the 5K-patch Cornell box: 44 of 543
non-zero blocks more than 3 tol off, most of them 100%). So before stopping, ACA
*probes*: one row and one column of each direction class (normals within 10
degrees, :data:`DIRECTIONS` at most a side) not yet met, then :data:`PROBES`
rows and columns spread over the block (golden-ratio steps); a probe whose
residual, were every line like it, would exceed tol ||S_k||_F (m ||r||^2 >
tol^2 ||S_k||_F^2 for a row r) restarts ACA from it (with the probes: 0 of 543; at
most :data:`MAX_PROBES` probes a block). An exactly zero block (coplanar patches)
costs its probes, a few rows and columns, and comes out rank 0.

ACA overestimates the rank; the factors are recompressed (Bebendorf 2008,
sec. 2.6): U = Q_u R_u, V = Q_v R_v, R_u R_v^T = W s Z^T, truncated to the
smallest rank whose discarded singular values hold at most RECOMPRESS x tol of
the Frobenius norm; O((m + b) k^2 + k^3) a block, the order of ACA's own updates.

Entries are evaluated inside numba by the same pair functions as
:func:`hfrad.formfactors.clustered.kernel_for`'s block functions
(kernel.py's ``_triangle_pair_area_ff`` / ``_pair_area_ff``, clustered.py's
``_cluster_pair_area_ff``), so :func:`pair_values` equals the block functions
to the bit. The clustered kernel's memo is neither read nor written (far
blocks hold no memo pairs; the numbers are the same either way).

References
----------
M. Bebendorf, "Approximation of boundary element matrices", Numer. Math. 86 (2000) 565-589.
S. Rjasanow, O. Steinbach, "The Fast Solution of Boundary Integral Equations", Springer 2007, ch. 3.
M. Bebendorf, "Hierarchical Matrices", Springer 2008, sec. 2.6 (recompression), 3.4 (ACA).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numba import njit, prange

from ..errors import InputError
from ..resources import blas_threads
from .clustered import ClusterGeometry, _cluster_pair_area_ff
from .kernel import PatchGeometry, _distant_row, _pair_area_ff, _triangle_pair_area_ff

#: Probes (a row and a column each) spread over the block before it counts as done, after one
#: of each direction class (see the module docstring) ...
PROBES = 2

#: ... and most probes per block in all.
MAX_PROBES = 2 * 8 + 2

#: Most direction classes of a block's rows (and of its columns), and the cosine within which a
#: patch's normal joins a class (10 degrees).
DIRECTIONS = 8
SAME_DIRECTION = 0.985

#: The recompression may discard singular values holding up to this fraction of tol x ||S_k||_F.
RECOMPRESS = 0.5

# which pair function an entry goes through (see _evaluate)
_TRIANGLES, _CSR, _CLUSTERS = 0, 1, 2


# ---------------------------------------------------------------------------
# the geometry as two tuples of arrays: one compiled signature serves every kind (cache=True),
# the tuple of the kinds not in use is filled with empty arrays of the same types


def _f(x, ndim):
    """x as a C-ordered float64 array of ``ndim`` dimensions, (n,), (n, 3) or (n, 3, 3)."""
    return np.ascontiguousarray(x, np.float64).reshape((-1,) + (3,) * (ndim - 1)) if ndim > 1 else \
        np.ascontiguousarray(x, np.float64).ravel()


def _patch_tuple(g: PatchGeometry | None) -> tuple:
    if g is None:
        e1, e2, e3, ei = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)
        return (e3, e2, e1, e2, e1, ei, ei, e1, 0.0, 0.0, 0.0, 0.0)
    return (_f(g.triangles, 3), _f(g.normals, 2), _f(g.areas, 1), _f(g.centroids, 2), _f(g.diameters, 1),
            np.ascontiguousarray(g.start, np.int64), np.ascontiguousarray(g.index, np.int64),
            _f(g.patch_areas, 1), float(g.near), float(g.adaptive), float(g.eps), float(g.tolerance))


def _cluster_tuple(g: ClusterGeometry | None) -> tuple:
    if g is None:
        e1, e2, e3, ei = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)
        w = np.zeros((0, 4))
        return (e3, e2, ei, e1, e1, e2, e2, e1, np.zeros((0, 4, 3)), np.zeros((0, 4, 3)), np.zeros((0, 4, 3)), w,
                np.zeros((0, 4, 3)), np.zeros((0, 4, 3)), w, 0.0, 0.0, 0.0, e1, e2, e1, e1, 0.0, 0, 0.0, 0.0)
    m = g.mid_points.shape[1]
    q = g.points.shape[1]

    def pts(x, k):
        return np.ascontiguousarray(x, np.float64).reshape(-1, k, 3)

    def wts(x, k):
        return np.ascontiguousarray(x, np.float64).reshape(-1, k)
    return (_f(g.triangles, 3), _f(g.tri_normals, 2), np.ascontiguousarray(g.start, np.int64), _f(g.scale_kept, 1),
            _f(g.areas, 1), _f(g.area_vectors, 2), _f(g.centroids, 2), _f(g.diameters, 1),
            pts(g.mid_points, m), pts(g.mid_normals, m), pts(g.mid_vectors, m), wts(g.mid_weights, m),
            pts(g.points, q), pts(g.point_normals, q), wts(g.weights, q), float(g.far), float(g.near), float(g.eps),
            _f(g.tri_areas, 1), _f(g.tri_centroids, 2), _f(g.tri_diameters, 1), _f(g.touching_rules, 1),
            float(g.tolerance), int(g.exact_pairs), float(g.exact_near), float(g.point_far) ** 2)


def _kernel_args(geometry) -> tuple[int, tuple, tuple]:
    """(kind, patch tuple, cluster tuple) of a PatchGeometry or ClusterGeometry."""
    if isinstance(geometry, ClusterGeometry):
        return _CLUSTERS, _patch_tuple(None), _cluster_tuple(geometry)
    if isinstance(geometry, PatchGeometry):
        kind = _TRIANGLES if geometry.one_triangle_per_patch else _CSR
        return kind, _patch_tuple(geometry), _cluster_tuple(None)
    raise InputError(f"geometry must be a PatchGeometry or ClusterGeometry (kernel_for), got {type(geometry).__name__}")


@njit(cache=True, fastmath=False, nogil=True)
def _evaluate(kind, I, J, G, H, out):
    """out[k] = F[I[k], J[k]] without visibility, exactly as the block function of ``kind`` computes it.

    The one place where the pair functions are compiled in (numba compiles an inlined kernel
    again at every call site, tens of seconds each). The tuples are unpacked once, outside the
    loop: unpacked per pair, their ~40 arrays' reference counts cost ~0.5 us a pair.
    """
    T, N, A, C, D, start, index, PA, near, adaptive, eps, tol = G
    (T2, N2, start2, K, A2, S, C2, D2, M, MN, MS, MW, Q, QN, W, far, near2, eps2, TA, TC, TD, TR, tol2, exact,
     exact_near, far2) = H
    # one loop a kind: one loop over all three pair functions ran the distant pairs at ~100 ns each
    if kind == _CLUSTERS:
        for k in range(I.shape[0]):
            i = I[k]
            af = _cluster_pair_area_ff(i, J[k], T2, N2, start2, K, A2, S, C2, D2, M, MN, MS, MW, Q, QN, W, far,
                                       near2, eps2, TA, TC, TD, TR, tol2, exact, exact_near, far2)
            out[k] = af / A2[i] if af > 0.0 else 0.0
    elif kind == _TRIANGLES:
        for k in range(I.shape[0]):
            i = I[k]
            j = J[k]
            af = _triangle_pair_area_ff(min(i, j), max(i, j), T, N, A, C, D, near, adaptive, eps, tol)
            out[k] = af / A[i] if af > 0.0 else 0.0
    else:
        for k in range(I.shape[0]):
            i = I[k]
            af = _pair_area_ff(i, J[k], T, N, A, C, D, start, index, near, adaptive, eps, tol)
            out[k] = af / PA[i] if af > 0.0 else 0.0


@njit(parallel=True, cache=True, fastmath=False, nogil=True)
def _pairs(kind, I, J, G, H, out, chunks):
    """:func:`_evaluate` in parallel: pairs in ``chunks`` contiguous runs."""
    n = I.shape[0]
    for part in prange(chunks):
        lo = part * n // chunks
        hi = (part + 1) * n // chunks
        _evaluate(kind, I[lo:hi], J[lo:hi], G, H, out[lo:hi])


def _patch_normals(geometry) -> np.ndarray:
    """(n, 3) unit normal of each patch (area-weighted mean of its triangles' for kernel.py's CSR patches)."""
    if isinstance(geometry, ClusterGeometry) or geometry.one_triangle_per_patch:
        return np.ascontiguousarray(geometry.normals, np.float64)
    w = geometry.normals[geometry.index] * geometry.areas[geometry.index][:, None]
    s = np.add.reduceat(w, geometry.start[:-1], axis=0) if len(w) else np.zeros((0, 3))
    return np.ascontiguousarray(s / np.maximum(np.linalg.norm(s, axis=1, keepdims=True), 1e-300))


def _patch_indices(x, n: int, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 1 or (x.size and not np.issubdtype(x.dtype, np.integer)):
        raise InputError(f"{name} must be a 1-D array of patch indices, got shape {x.shape}, dtype {x.dtype}")
    x = np.ascontiguousarray(x, np.int64)
    if x.size and (x.min() < 0 or x.max() >= n):
        raise InputError(f"{name} must hold patch indices in [0, {n}), got {x.min()}..{x.max()}")
    return x


def pair_values(geometry, I, J) -> np.ndarray:
    """(len(I),) float64: the unoccluded F[I[k], J[k]] (F_ij, not A_i F_ij).

    The same numbers, to the bit, as the block function of
    :func:`hfrad.formfactors.clustered.kernel_for` gives for those pairs; in parallel over pairs.

    Parameters
    ----------
    geometry : PatchGeometry or ClusterGeometry
        The first item of ``kernel_for(scene)``.
    I, J : (p,) int
        Row and column patch indices (the scene's order).

    Raises
    ------
    InputError
        I and J of different lengths, or indices out of range.
    """
    kind, G, H = _kernel_args(geometry)
    I = _patch_indices(I, geometry.n, "I")
    J = _patch_indices(J, geometry.n, "J")
    if len(I) != len(J):
        raise InputError(f"I and J must have the same length, got {len(I)} and {len(J)}")
    out = np.empty(len(I))
    if len(I):
        _pairs(kind, I, J, G, H, out, max(1, min(len(I), 8 * numba.get_num_threads())))
    return out


# ---------------------------------------------------------------------------
# ACA


@dataclass(frozen=True)
class AcaResult:
    """Low-rank factors of many blocks: block t ~= U_t @ V_t.T.

    Attributes
    ----------
    U : (sum_t m_t r_t,) float32
        U_t = ``U[u_offsets[t]:u_offsets[t + 1]].reshape(m_t, r_t)`` (row-major).
    V : (sum_t b_t r_t,) float32
        V_t = ``V[v_offsets[t]:v_offsets[t + 1]].reshape(b_t, r_t)`` (row-major).
    u_offsets, v_offsets : (blocks + 1,) int64
    block_rows, block_cols : (blocks,) int64, m_t and b_t
    ranks : (blocks,) int64, r_t after recompression
    aca_ranks : (blocks,) int64, ACA's steps k_t before recompression (r_t <= k_t)
    ok : (blocks,) bool
        False where ACA reached ``max_rank`` with its stopping test (2) or a probe still
        failing: the factors (rank up to max_rank) are then not to be trusted, and the caller
        computes that block another way.
    evaluated : (blocks,) int64
        Entries of F evaluated for each block (pair-function calls).
    """

    U: np.ndarray
    V: np.ndarray
    u_offsets: np.ndarray
    v_offsets: np.ndarray
    block_rows: np.ndarray
    block_cols: np.ndarray
    ranks: np.ndarray
    aca_ranks: np.ndarray
    ok: np.ndarray
    evaluated: np.ndarray

    def factors(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(U_t (m_t, r_t), V_t (b_t, r_t)) float32 views of block t."""
        r = int(self.ranks[t])
        U = self.U[self.u_offsets[t]:self.u_offsets[t + 1]].reshape(int(self.block_rows[t]), r)
        V = self.V[self.v_offsets[t]:self.v_offsets[t + 1]].reshape(int(self.block_cols[t]), r)
        return U, V

    @property
    def blocks(self) -> int:
        """Number of blocks."""
        return len(self.ranks)


@njit(cache=True, fastmath=False, nogil=True)
def _directions(P, idx, cls):
    """cls[k] = the direction class of patch idx[k]: its normal P[idx[k]] within SAME_DIRECTION of the
    class's first normal (greedy; the DIRECTIONS-th class takes every normal left). Returns the count."""
    reps = np.empty((DIRECTIONS, 3))
    count = 0
    for k in range(idx.shape[0]):
        p = idx[k]
        c = -1
        for q in range(count):
            if P[p, 0] * reps[q, 0] + P[p, 1] * reps[q, 1] + P[p, 2] * reps[q, 2] >= SAME_DIRECTION:
                c = q
                break
        if c < 0:
            c = count if count < DIRECTIONS else DIRECTIONS - 1
            if count < DIRECTIONS:
                reps[count, 0], reps[count, 1], reps[count, 2] = P[p, 0], P[p, 1], P[p, 2]
                count += 1
        cls[k] = c
    return count


@njit(cache=True, fastmath=False, nogil=True)
def _unseen(q, taken, cls, seen):
    """A line not ``taken`` whose direction class is not ``seen`` (-1: none), the first in the
    golden-ratio order from its q-th step."""
    m = taken.shape[0]
    x = 0.5 + 0.6180339887498949 * q
    i = int((x - math.floor(x)) * m) % m
    for _ in range(m):
        if not taken[i] and not seen[cls[i]]:
            return i
        i = (i + 1) % m
    return -1


@njit(cache=True, fastmath=False, nogil=True)
def _spread(q, taken):
    """The q-th probe of a line list: golden-ratio steps through it, then the next line not ``taken``
    (-1: all taken). Spread over the block, so that the probes meet each part of a cluster."""
    m = taken.shape[0]
    x = 0.5 + 0.6180339887498949 * q
    i = int((x - math.floor(x)) * m) % m
    for _ in range(m):
        if not taken[i]:
            return i
        i = (i + 1) % m
    return -1


@njit(cache=True, fastmath=False, nogil=True)
def _residual_row(kind, R, C, G, H, i, U, V, k, pairs, row, gather, left):
    """row = F[R[i], C] - U[i, :k] V[:, :k]^T (``gather``, ``left``: see :func:`_row`)."""
    if kind == _TRIANGLES:
        _row(R[i], C, G, H, gather, left, pairs, row)
    else:
        pairs[:] = R[i]
        _evaluate(kind, pairs, C, G, H, row)
    _minus_terms(row, U, i, V, k)


@njit(cache=True, fastmath=False, nogil=True)
def _minus_terms(x, P, i, Q, k):
    """x -= sum_{l<k} P[i, l] Q[:, l]: the residual of row i (P = U, Q = V) or column i (P = V, Q = U)."""
    for l in range(k):
        a = P[i, l]
        for c in range(x.shape[0]):
            x[c] -= a * Q[c, l]


@njit(cache=True, fastmath=False, nogil=True)
def _row(p, C, G, H, gather, left, pairs, out):
    """out[c] = F[p, C[c]] for one-triangle patches as :func:`kernel.unoccluded_block` computes it:
    kernel.py's ``_distant_row`` (branch-free, SIMD: ~6 ns a distant pair against ~100 ns one by
    one) over the columns' data ``gather`` (8, b) (:func:`_gather`), then the pairs it leaves.
    ``left`` (b,) bool and ``pairs`` (b,) int are scratch."""
    T, N, A, Cn, D, start, index, PA, near, adaptive, eps, tol = G
    _distant_row(p, Cn[p, 0], Cn[p, 1], Cn[p, 2], N[p, 0], N[p, 1], N[p, 2], A[p], D[p], C, gather, near, eps,
                 out, left)
    q = 0
    for c in range(C.shape[0]):
        if left[c]:
            pairs[q] = C[c]
            q += 1
    if q:
        rest = np.empty(q)
        _evaluate(_TRIANGLES, np.full(q, p), pairs[:q], G, H, rest)
        q = 0
        for c in range(C.shape[0]):
            if left[c]:
                out[c] = rest[q]
                q += 1


@njit(cache=True, fastmath=False, nogil=True)
def _gather(C, G):
    """(8, b): the centroids, normals, areas and diameters of one-triangle patches C, patch last
    (the layout of kernel.py's ``_distant_row``)."""
    T, N, A, Cn, D, start, index, PA, near, adaptive, eps, tol = G
    out = np.empty((8, C.shape[0]))
    for c in range(C.shape[0]):
        j = C[c]
        out[0, c], out[1, c], out[2, c] = Cn[j, 0], Cn[j, 1], Cn[j, 2]
        out[3, c], out[4, c], out[5, c] = N[j, 0], N[j, 1], N[j, 2]
        out[6, c], out[7, c] = A[j], D[j]
    return out


@njit(cache=True, fastmath=False, nogil=True)
def _residual_col(kind, R, C, G, H, j, U, V, k, pairs, col):
    """col = F[R, C[j]] - U[:, :k] V[j, :k]^T."""
    pairs[:] = C[j]
    _evaluate(kind, R, pairs, G, H, col)
    _minus_terms(col, V, j, U, k)


@njit(cache=True, fastmath=False, nogil=True)
def _largest(x, taken, floor):
    """(index, |value|) of the largest |x[k]| above ``floor`` among the k not ``taken`` ((-1, floor): none)."""
    best = floor
    at = -1
    for k in range(x.shape[0]):
        if not taken[k] and abs(x[k]) > best:
            best = abs(x[k])
            at = k
    return at, best


@njit(cache=True, fastmath=False, nogil=True)
def _sum_squares(x):
    s = 0.0
    for v in x:
        s += v * v
    return s


@njit(cache=True, fastmath=False, nogil=True)
def _aca(kind, R, C, G, H, P, tol, cap, U, V):
    """ACA with partial pivoting of F[R][:, C] into U[:, :k], V[:, :k] (see the module docstring).

    Returns (k, converged, evaluated); ``converged`` is False when k reached ``cap`` with the
    stopping test or a probe still failing (unless cap = min(m, b): then S_k is the block itself).
    """
    m = R.shape[0]
    b = C.shape[0]
    row = np.empty(b)
    col = np.empty(m)
    row_pairs = np.empty(b, np.int64)   # the pair lists of one row and of one column
    col_pairs = np.empty(m, np.int64)
    used_row = np.zeros(m, np.bool_)
    used_col = np.zeros(b, np.bool_)    # pivot columns
    probed_col = np.zeros(b, np.bool_)
    gather = _gather(C, G) if kind == _TRIANGLES else np.empty((8, 0))
    left = np.empty(b, np.bool_)
    row_cls = np.empty(m, np.int64)      # direction classes of the rows' and columns' patches
    col_cls = np.empty(b, np.int64)
    row_seen = np.zeros(_directions(P, R, row_cls), np.bool_)
    col_seen = np.zeros(_directions(P, C, col_cls), np.bool_)
    k = 0
    norm2 = 0.0
    evaluated = 0
    probes = 0
    spread = 0
    i = m // 2      # the middle of the list: the middle of the cluster when the list is in tree order
    have_row = False
    while True:
        if k == cap:
            return k, cap == min(m, b), evaluated
        if not have_row:
            _residual_row(kind, R, C, G, H, i, U, V, k, row_pairs, row, gather, left)
            evaluated += b
            used_row[i] = True
            row_seen[row_cls[i]] = True
        have_row = False
        j, best = _largest(row, used_col, 0.0)
        done = j < 0 or best <= 1e-14 * math.sqrt(norm2)      # a zero residual row
        if not done:
            used_col[j] = True
            col_seen[col_cls[j]] = True
            pivot = row[j]
            _residual_col(kind, R, C, G, H, j, U, V, k, col_pairs, col)
            evaluated += m
            for r in range(m):
                U[r, k] = col[r]
            for c in range(b):
                V[c, k] = row[c] / pivot
            uu = _sum_squares(U[:, k])
            vv = _sum_squares(V[:, k])
            cross = 0.0      # ||S_k||^2 = ||S_{k-1}||^2 + 2 sum_l (u_l.u_k)(v_l.v_k) + |u_k|^2 |v_k|^2
            for l in range(k):
                su = 0.0
                for r in range(m):
                    su += U[r, l] * U[r, k]
                sv = 0.0
                for c in range(b):
                    sv += V[c, l] * V[c, k]
                cross += su * sv
            norm2 = max(norm2 + 2.0 * cross + uu * vv, 0.0)
            k += 1
            done = math.sqrt(uu * vv) <= tol * math.sqrt(norm2)     # eq. (2)
            i = _largest(col, used_row, -1.0)[0]   # the next row: where |u_k| is largest among those not used
            if i < 0:       # every row used: S_k is the block
                return k, True, evaluated
        if not done:
            continue
        # eq. (2) holds or the row was zero: probe rows and columns, first one of each direction class
        # not met yet (a cluster of several planes: F is zero or not by plane pairs, and ACA's pivots
        # may never leave the first such sub-block), then spread over the block; go on from the first
        # probe whose residual, were every line like it, would exceed tol ||S_k||_F
        budget = tol * tol * norm2
        found = False
        while probes < MAX_PROBES and not found:
            probes += 1
            i = _unseen(probes, used_row, row_cls, row_seen)
            j = _unseen(probes, probed_col | used_col, col_cls, col_seen)
            if i < 0 and j < 0:
                if spread >= PROBES:
                    break
                spread += 1
                i = _spread(probes, used_row)
                j = _spread(probes, probed_col | used_col)
            if i >= 0:
                _residual_row(kind, R, C, G, H, i, U, V, k, row_pairs, row, gather, left)
                evaluated += b
                used_row[i] = True
                row_seen[row_cls[i]] = True
                if m * _sum_squares(row) > budget:
                    have_row = True
                    found = True
                    continue
            if j >= 0:
                _residual_col(kind, R, C, G, H, j, U, V, k, col_pairs, col)
                evaluated += m
                probed_col[j] = True
                col_seen[col_cls[j]] = True
                if b * _sum_squares(col) > budget:
                    i = _largest(col, used_row, 0.0)[0]
                    found = i >= 0
        if not found:
            return k, True, evaluated


@njit(cache=True, fastmath=False, nogil=True)
def _recompress(U, V, k, tol):
    """(U', V', r): U[:, :k] V[:, :k]^T truncated by a QR of each factor and an SVD of R_u R_v^T."""
    Qu, Ru = np.linalg.qr(np.ascontiguousarray(U[:, :k]))
    Qv, Rv = np.linalg.qr(np.ascontiguousarray(V[:, :k]))
    W, s, Zt = np.linalg.svd(np.dot(Ru, Rv.T))
    total = 0.0
    for l in range(s.shape[0]):
        total += s[l] * s[l]
    limit = (RECOMPRESS * tol) ** 2 * total
    r = s.shape[0]
    tail = 0.0
    while r > 0 and tail + s[r - 1] * s[r - 1] <= limit:
        tail += s[r - 1] * s[r - 1]
        r -= 1
    for l in range(r):
        W[:, l] *= s[l]
    return (np.dot(np.ascontiguousarray(Qu), np.ascontiguousarray(W[:, :r])),
            np.dot(np.ascontiguousarray(Qv), np.ascontiguousarray(Zt[:r, :].T)), r)


@njit(parallel=True, cache=True, fastmath=False, nogil=True)
def _aca_blocks(kind, G, H, P, rows, row_ptr, cols, col_ptr, tol, max_rank, u_cap, v_cap, Up, Vp, ranks, aca_ranks,
                ok, evaluated, chunks):
    """ACA of every block into capacity slots of Up, Vp (float32); blocks dealt out in turn to ``chunks``
    parts (block t to part t % chunks: neighbouring blocks are often of similar cost)."""
    nb = row_ptr.shape[0] - 1
    for part in prange(chunks):
        for t in range(part, nb, chunks):
            R = rows[row_ptr[t]:row_ptr[t + 1]]
            C = cols[col_ptr[t]:col_ptr[t + 1]]
            m = R.shape[0]
            b = C.shape[0]
            cap = min(max_rank, m, b)
            if cap == 0:
                ranks[t] = 0
                aca_ranks[t] = 0
                ok[t] = True
                evaluated[t] = 0
                continue
            U = np.empty((m, cap))
            V = np.empty((b, cap))
            k, conv, ev = _aca(kind, R, C, G, H, P, tol, cap, U, V)
            aca_ranks[t] = k
            ok[t] = conv
            evaluated[t] = ev
            if k >= 2:
                U2, V2, r = _recompress(U, V, k, tol)
            else:
                U2, V2, r = U, V, k
            ranks[t] = r
            u0 = u_cap[t]
            v0 = v_cap[t]
            for a in range(m):
                for l in range(r):
                    Up[u0 + a * r + l] = U2[a, l]
            for c in range(b):
                for l in range(r):
                    Vp[v0 + c * r + l] = V2[c, l]


@njit(parallel=True, cache=True, nogil=True)
def _compact(src, src_start, dst, dst_start):
    """dst[dst_start[t]:dst_start[t + 1]] = the same length from src[src_start[t]:]."""
    for t in prange(dst_start.shape[0] - 1):
        a = src_start[t]
        for q in range(dst_start[t + 1] - dst_start[t]):
            dst[dst_start[t] + q] = src[a + q]


def _block_lists(x, ptr, n: int, name: str) -> tuple[np.ndarray, np.ndarray]:
    x = _patch_indices(x, n, name)
    ptr = np.asarray(ptr)
    if ptr.ndim != 1 or len(ptr) < 1 or (len(ptr) and not np.issubdtype(ptr.dtype, np.integer)):
        raise InputError(f"{name}_ptr must be a 1-D integer array of blocks + 1 offsets, got shape {ptr.shape}")
    ptr = np.ascontiguousarray(ptr, np.int64)
    if ptr[0] != 0 or ptr[-1] != len(x) or (np.diff(ptr) < 0).any():
        raise InputError(f"{name}_ptr must rise from 0 to len({name}) = {len(x)}, got {ptr[0]}..{ptr[-1]}")
    return x, ptr


def aca_blocks(geometry, rows, row_ptr, cols, col_ptr, tol: float, max_rank: int) -> AcaResult:
    """Low-rank factors U_t V_t^T of many blocks of the unoccluded F by ACA, in parallel over blocks.

    Block t is ``F[rows[row_ptr[t]:row_ptr[t + 1]]][:, cols[col_ptr[t]:col_ptr[t + 1]]]`` (patch
    indices, any order; m_t rows, b_t columns). Each is approximated by ACA with partial
    pivoting to relative Frobenius tolerance ``tol`` (eq. 2 of the module docstring), then
    recompressed; only the k_t rows and k_t columns ACA visits are evaluated (about
    k_t (m_t + b_t) entries, plus the probes' rows and columns: a few), each by
    :func:`pair_values`' pair function.

    Parameters
    ----------
    geometry : PatchGeometry or ClusterGeometry
        The first item of ``kernel_for(scene)``.
    rows, row_ptr : (sum m_t,) int, (blocks + 1,) int
    cols, col_ptr : (sum b_t,) int, (blocks + 1,) int
    tol : float in (0, 1)
        Relative Frobenius tolerance per block.
    max_rank : int >= 1
        Most ACA steps per block; a block that needs more is returned with ``ok`` False.

    Returns
    -------
    AcaResult

    Raises
    ------
    InputError
        Indices out of range, offsets that do not fit, ``row_ptr`` and ``col_ptr`` of different
        lengths, tol outside (0, 1) or max_rank < 1.

    Notes
    -----
    Memory: the factors are first written into slots sized by c_t = min(max_rank, m_t, b_t),
    4 sum_t (m_t + b_t) c_t bytes, then copied to the returned pools, 4 sum_t (m_t + b_t) r_t
    bytes; each thread also holds 8 (m_t + b_t) (c_t + 2) bytes of float64 scratch for the block
    it works on (plus the recompression's copies, of the same order). Pass the blocks in
    batches when the first term is too large. Work: O(k_t (m_t + b_t)) entries and O(k_t^2
    (m_t + b_t)) flops per block.
    """
    kind, G, H = _kernel_args(geometry)
    n = geometry.n
    rows, row_ptr = _block_lists(rows, row_ptr, n, "rows")
    cols, col_ptr = _block_lists(cols, col_ptr, n, "cols")
    if len(row_ptr) != len(col_ptr):
        raise InputError(f"row_ptr and col_ptr must give the same number of blocks, got {len(row_ptr) - 1} "
                         f"and {len(col_ptr) - 1}")
    if not (0.0 < tol < 1.0):
        raise InputError(f"tol must be in (0, 1), got {tol}")
    if int(max_rank) != max_rank or max_rank < 1:
        raise InputError(f"max_rank must be an integer >= 1, got {max_rank}")
    m = np.diff(row_ptr).astype(np.int64)
    b = np.diff(col_ptr).astype(np.int64)
    cap = np.minimum(np.minimum(m, b), int(max_rank))
    u_cap = np.concatenate([[0], np.cumsum(m * cap)]).astype(np.int64)
    v_cap = np.concatenate([[0], np.cumsum(b * cap)]).astype(np.int64)
    nb = len(m)
    Up = np.empty(u_cap[-1], np.float32)
    Vp = np.empty(v_cap[-1], np.float32)
    ranks = np.zeros(nb, np.int64)
    aca_ranks = np.zeros(nb, np.int64)
    ok = np.ones(nb, bool)
    evaluated = np.zeros(nb, np.int64)
    if nb:
        chunks = max(1, min(nb, 8 * numba.get_num_threads()))
        with blas_threads(1):   # the recompression's LAPACK calls run inside numba's threads (8x slower otherwise)
            _aca_blocks(kind, G, H, _patch_normals(geometry), rows, row_ptr, cols, col_ptr, float(tol),
                        int(max_rank), u_cap, v_cap, Up, Vp, ranks, aca_ranks, ok, evaluated, chunks)
    u_off = np.concatenate([[0], np.cumsum(m * ranks)]).astype(np.int64)
    v_off = np.concatenate([[0], np.cumsum(b * ranks)]).astype(np.int64)
    U = np.empty(u_off[-1], np.float32)
    V = np.empty(v_off[-1], np.float32)
    if nb:
        _compact(Up, u_cap, U, u_off)
        _compact(Vp, v_cap, V, v_off)
    return AcaResult(U, V, u_off, v_off, m, b, ranks, aca_ranks, ok, evaluated)
