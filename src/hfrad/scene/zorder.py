"""Z-order (Morton) sorting of patches (Aguerre & Fernández 2016, section 3).

Neighbouring patches see the scene alike, so neighbouring columns of RF are
alike; sorting rows and columns along a space-filling curve makes each column
block low rank. The permutation is internal: public inputs and outputs stay in
the user's patch order.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

BITS_PER_AXIS = 21  # 3 x 21 = 63 bits fit in an unsigned 64-bit code


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 21 bits of ``v`` (uint64)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def morton_codes(points: np.ndarray, bits: int = BITS_PER_AXIS) -> np.ndarray:
    """Morton codes of points quantised on their bounding cube.

    Parameters
    ----------
    points : (n, 3) float
    bits : int, 1..21
        Quantisation bits per axis.

    Returns
    -------
    (n,) uint64
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not 1 <= bits <= BITS_PER_AXIS:
        raise InputError(f"bits must be in 1..{BITS_PER_AXIS}, got {bits}")
    if len(points) == 0:
        return np.zeros(0, np.uint64)
    lo = points.min(axis=0)
    side = float((points.max(axis=0) - lo).max())  # a cube, so the curve is not stretched
    cells = (1 << bits) - 1
    q = np.zeros_like(points) if side == 0 else (points - lo) / side * cells
    q = np.clip(np.rint(q), 0, cells).astype(np.uint64)
    return (_spread_bits(q[:, 0]) << np.uint64(2)) | (_spread_bits(q[:, 1]) << np.uint64(1)) | _spread_bits(q[:, 2])


def zorder_permutation(points: np.ndarray, bits: int = BITS_PER_AXIS) -> np.ndarray:
    """Stable permutation sorting points along the Z-order curve.

    ``points[perm]`` is in Z-order; ties keep the input order.
    """
    return np.argsort(morton_codes(points, bits), kind="stable")


def random_permutation(n: int, rng=None) -> np.ndarray:
    """A random order, the baseline the paper compares Z-order against."""
    return np.random.default_rng(rng).permutation(n)


def _quantise(points: np.ndarray, bits: int) -> np.ndarray:
    """(n, 3) uint64 cell coordinates on the points' bounding cube."""
    lo = points.min(axis=0)
    side = float((points.max(axis=0) - lo).max())
    cells = (1 << bits) - 1
    q = np.zeros_like(points) if side == 0 else (points - lo) / side * cells
    return np.clip(np.rint(q), 0, cells).astype(np.uint64)


def hilbert_codes(points: np.ndarray, bits: int = BITS_PER_AXIS) -> np.ndarray:
    """Hilbert-curve indices of points on their bounding cube (Skilling 2004, vectorised).

    Unlike Z-order, consecutive cells of the Hilbert curve are always face
    neighbours; the benchmarks compare both orders.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, np.uint64)
    X = [c.copy() for c in _quantise(points, bits).T]
    one = np.uint64(1)
    top = one << np.uint64(bits - 1)
    q = top
    while q > one:  # inverse undo of the excess work
        p = q - one
        for i in range(3):
            has = (X[i] & q) != 0
            t = (X[0] ^ X[i]) & p
            X[0] = np.where(has, X[0] ^ p, X[0] ^ t)
            if i:
                X[i] = np.where(has, X[i], X[i] ^ t)
        q >>= one
    for i in (1, 2):  # Gray encode
        X[i] ^= X[i - 1]
    t = np.zeros_like(X[0])
    q = top
    while q > one:
        t = np.where((X[2] & q) != 0, t ^ (q - one), t)
        q >>= one
    X = [x ^ t for x in X]
    return (_spread_bits(X[0]) << np.uint64(2)) | (_spread_bits(X[1]) << np.uint64(1)) | _spread_bits(X[2])


ORDERS = ("zorder", "hilbert", "random", "input")


def patch_order(points: np.ndarray, order: str = "zorder", *, rng=0) -> np.ndarray:
    """Internal patch order by name: ``zorder`` (the paper's), ``hilbert``, ``random``, ``input``."""
    n = len(points)
    if order == "zorder":
        return zorder_permutation(points)
    if order == "hilbert":
        return np.argsort(hilbert_codes(points), kind="stable")
    if order == "random":
        return random_permutation(n, rng)
    if order == "input":
        return np.arange(n)
    raise InputError(f"order must be one of {ORDERS}; got {order!r}")
