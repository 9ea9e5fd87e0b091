"""Welding: one vertex id per distinct position.

Meshes arrive as triangle soups (every face with its own three corners),
cutting faces into patches computes a shared edge's points once per face, and
refinement, clustering and the duplicate-face check all need to know which
corners are the same point. :func:`weld_points` is the one rule they share;
:func:`weld` applies it to the corners of faces.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Default welding tolerance, relative to the size of the points' bounding box (its largest side).
REL_TOL = 1e-9

#: The grid step never falls below this many units in the last place of the largest coordinate, so
#: one point computed twice (rounded differently) still welds far from the origin.
ULPS = 64


def weld_points(points: np.ndarray, *, rel_tol: float = REL_TOL, bounds: np.ndarray | None = None) -> np.ndarray:
    """(p,) int64: one id 0..u-1 per distinct position of the (p, 3) ``points``.

    Each point is rounded to a grid of step ``h`` centred on its bounding box,

        key = rint((x - c) / h),   c = (lo + hi) / 2,
        h = max(rel_tol * max(hi - lo), ULPS * eps * max|lo, hi|),

    (``eps`` = 2.2e-16, the float64 spacing at 1; ``h = 1`` when both terms are
    zero, e.g. a single point), and points with equal keys share an id. So
    points that differ by more than ``h`` along some axis are never welded,
    and points much closer than ``h`` are welded unless a grid cell's border
    passes between them. The tolerance is relative to the scene's size and
    measured from its centre: a small scene far from the origin welds as it
    would at the origin, until coordinates are so large that float64 cannot
    resolve ``rel_tol`` of the size.

    Parameters
    ----------
    points : (p, 3) float
        Positions, in the scene's frame (metres).
    rel_tol : float
        Grid step as a fraction of the bounding box's largest side.
    bounds : (2, 3) float, optional
        (lo, hi) corners of the box that sets ``c`` and the size; default the
        points' own bounding box. Pass ``Scene.bounds`` to weld relative to the
        scene rather than to a subset of its points.

    Returns
    -------
    ids : (p,) int64
        ``ids[i] == ids[j]`` when points i and j are one vertex; ids are
        numbered in lexicographic order of the rounded positions, and
        ``ids.max() + 1`` is the number of distinct vertices.

    Examples
    --------
    >>> p = np.array([[0.0, 0, 0], [1, 0, 0], [1 + 3e-11, 0, 0], [1 + 3e-9, 0, 0], [0, 1, 0]])
    >>> weld_points(p).tolist()  # h = 1e-9: the point 3e-11 away is welded, the one 3e-9 away is not
    [0, 2, 2, 3, 1]
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return np.zeros(0, np.int64)
    lo, hi = (points.min(axis=0), points.max(axis=0)) if bounds is None else np.asarray(bounds, np.float64)
    rounding = ULPS * np.finfo(np.float64).eps * float(max(np.abs(lo).max(), np.abs(hi).max()))
    step = max(rel_tol * float(np.max(hi - lo)), rounding) or 1.0
    key = np.rint((points - 0.5 * (lo + hi)) / step).astype(np.int64)
    return row_ids(key)


def weld(vertices: np.ndarray, faces: np.ndarray, *, rel_tol: float = REL_TOL,
         bounds: np.ndarray | None = None) -> np.ndarray:
    """(t, k) int64: ``faces`` renumbered so that corners at one position share one id.

    The rule is :func:`weld_points`'s; the default ``bounds`` is the box of the
    vertices the faces use (``Scene.bounds``), so unused vertices do not change
    the tolerance.

    Parameters
    ----------
    vertices : (v, 3) float
        Positions (metres).
    faces : (t, k) int
        Indices into ``vertices`` (k = 3 for triangles).
    rel_tol, bounds
        As for :func:`weld_points`.

    Returns
    -------
    (t, k) int64
        Welded vertex ids: corners at one position have one id. Ids are
        numbered over all of ``vertices``, so unused vertices may leave gaps.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if not faces.size:
        return faces.reshape(0, faces.shape[1] if faces.ndim == 2 else 3)
    if bounds is None:
        in_use = np.zeros(len(vertices), bool)
        in_use[faces.reshape(-1)] = True
        used = vertices[in_use]
        bounds = np.array([used.min(axis=0), used.max(axis=0)])
    return weld_points(vertices, rel_tol=rel_tol, bounds=bounds)[faces]


def row_ids(table: np.ndarray) -> np.ndarray:
    """(n,) int64: equal rows of the (n, k) ``table`` get equal ids 0..u-1, in lexicographic row order.

    Same as ``np.unique(table, axis=0, return_inverse=True)[1]``, computed by
    sorting on the columns instead of sorting rows as opaque records (faster).
    Integer columns are first packed into as few int64 digits as their ranges
    allow (:func:`_packed_digits`; e.g. the three vertex ids of a face in
    one), which keeps the lexicographic order and makes most tables one or
    two sort keys.
    """
    table = np.asarray(table)
    n = len(table)
    if n == 0:
        return np.zeros(0, np.int64)
    packable = table.dtype.kind in "ib" or (table.dtype.kind == "u" and table.dtype.itemsize < 8)
    digits = _packed_digits(table) if packable else list(table.T)
    if len(digits) == 2:  # e.g. welding: sort by the major digit, then each run of equal ones by the minor
        order = np.argsort(digits[0])
        return _ids_of_runs(order, digits[0][order], digits[1][order], digits[1])
    # least significant digit first; only the later passes must be stable
    order = np.argsort(digits[-1])
    for digit in digits[-2::-1]:
        order = order[np.argsort(digit[order], kind="stable")]
    new = np.zeros(n, bool)
    new[0] = True
    for digit in digits:
        ordered = digit[order]
        new[1:] |= ordered[1:] != ordered[:-1]
    ids = np.empty(n, np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


@njit(cache=True)
def first_index(ids: np.ndarray, count: int) -> np.ndarray:
    """(count,) int64: the first index at which each id 0..count-1 occurs in the (n,) ``ids`` (-1: never)."""
    first = np.full(count, -1, np.int64)
    for f in range(ids.shape[0]):
        if first[ids[f]] < 0:
            first[ids[f]] = f
    return first


@njit(cache=True)
def grouped_order(ids: np.ndarray, count: int) -> np.ndarray:
    """(n,) int64: the indices of ``ids`` (values 0..count-1) sorted by id, equal ids in index
    order: ``np.argsort(ids, kind="stable")`` by counting, in O(n + count)."""
    start = np.zeros(count + 1, np.int64)
    for f in range(ids.shape[0]):
        start[ids[f] + 1] += 1
    for c in range(count):
        start[c + 1] += start[c]
    order = np.empty(ids.shape[0], np.int64)
    for f in range(ids.shape[0]):
        order[start[ids[f]]] = f
        start[ids[f]] += 1
    return order


def _packed_digits(table: np.ndarray) -> list[np.ndarray]:
    """The integer (n, k) ``table`` as a few (n,) int64 digits, most significant first.

    Consecutive columns c_1..c_m whose value ranges s_1..s_m multiply to less
    than 2^63 become one digit, sum_q (c_q - min c_q) * prod_{r > q} s_r, a
    mixed-radix number: comparing digits compares the rows lexicographically.
    A column whose range does not fit int64 is a digit as it is.
    """
    table = np.ascontiguousarray(table, dtype=np.int64)
    lo, hi = _column_ranges(table)
    spans = [int(h) - int(l) + 1 for l, h in zip(lo, hi)]
    digits, first, capacity = [], 0, spans[0]
    for q in range(1, len(spans) + 1):
        if q < len(spans) and capacity * spans[q] < 2 ** 63:
            capacity *= spans[q]
            continue
        if spans[first] >= 2 ** 63:  # alone in its digit (the product test above fails for it)
            lo[first] = 0
        digits.append(_pack(table, lo, np.array(spans[first:q] if q - first > 1 else [0], np.int64), first))
        if q < len(spans):
            first, capacity = q, spans[q]
    return digits


@njit(cache=True)
def _column_ranges(table):
    """Smallest and largest value of each column of the (n, k) ``table``, in one pass."""
    lo = table[0].copy()
    hi = table[0].copy()
    for r in range(table.shape[0]):
        for q in range(table.shape[1]):
            lo[q] = min(lo[q], table[r, q])
            hi[q] = max(hi[q], table[r, q])
    return lo, hi


@njit(cache=True)
def _pack(table, lo, spans, first):
    """Columns first..first+len(spans)-1 of ``table`` as one mixed-radix digit (see :func:`_packed_digits`)."""
    out = np.empty(table.shape[0], np.int64)
    for r in range(table.shape[0]):
        d = table[r, first] - lo[first]
        for q in range(1, spans.shape[0]):
            d = d * spans[q] + (table[r, first + q] - lo[first + q])
        out[r] = d
    return out


@njit(cache=True)
def _ids_of_runs(order, major_sorted, minor_sorted, minor):
    """Row ids from ``order`` (rows sorted by their major digit, ``major_sorted``; their minor
    digits ``minor_sorted``): each run of equal major digits is sorted by the minor one in
    place, and the ids counted along. Short runs (most: a point and its few copies) are
    sorted on the contiguous ``minor_sorted``, long ones through ``minor``."""
    n = order.shape[0]
    ids = np.empty(n, np.int64)
    current = -1
    a = 0
    while a < n:
        b = a + 1
        while b < n and major_sorted[b] == major_sorted[a]:
            b += 1
        if b - a > _SHORT_RUN:
            sort_run(order, a, b, minor)
            for q in range(a, b):
                minor_sorted[q] = minor[order[q]]
        else:
            for q in range(a + 1, b):  # insertion sort of the pairs (minor digit, row)
                x, m = order[q], minor_sorted[q]
                r = q - 1
                while r >= a and (minor_sorted[r] > m or (minor_sorted[r] == m and order[r] > x)):
                    order[r + 1], minor_sorted[r + 1] = order[r], minor_sorted[r]
                    r -= 1
                order[r + 1], minor_sorted[r + 1] = x, m
        for q in range(a, b):
            if q == a or minor_sorted[q] != minor_sorted[q - 1]:
                current += 1
            ids[order[q]] = current
        a = b
    return ids


#: Runs up to this long are sorted by insertion (most are one to a few points), longer ones by heapsort.
_SHORT_RUN = 16


@njit(cache=True)
def sort_run(order: np.ndarray, a: int, b: int, key: np.ndarray) -> None:
    """Sort ``order[a:b]`` in place by ``(key[x], x)``: by key, equal keys in index order (what a
    stable sort gives a run in index order). Written out, not ``np.argsort``, whose compiled
    version takes seconds to build."""
    if b - a <= _SHORT_RUN:
        for q in range(a + 1, b):
            x = order[q]
            r = q - 1
            while r >= a and _after(key, order[r], x):
                order[r + 1] = order[r]
                r -= 1
            order[r + 1] = x
        return
    n = b - a
    for root in range(n // 2 - 1, -1, -1):
        _sift_down(order, a, root, n, key)
    for end in range(n - 1, 0, -1):
        order[a], order[a + end] = order[a + end], order[a]
        _sift_down(order, a, 0, end, key)


@njit(cache=True)
def _after(key, x, y):
    """``(key[x], x) > (key[y], y)``."""
    return key[x] > key[y] or (key[x] == key[y] and x > y)


@njit(cache=True)
def _sift_down(order, a, root, n, key):
    """Restore the max-heap ``order[a:a + n]`` below ``root``."""
    while True:
        child = 2 * root + 1
        if child >= n:
            return
        if child + 1 < n and _after(key, order[a + child + 1], order[a + child]):
            child += 1
        if not _after(key, order[a + child], order[a + root]):
            return
        order[a + root], order[a + child] = order[a + child], order[a + root]
        root = child
