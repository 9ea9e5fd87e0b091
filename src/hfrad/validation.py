"""Validation of arrays a user passes in, one helper per kind (used at API boundaries only)."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["check_permutation", "check_reflectance", "check_factorize_options"]


def check_permutation(order, n: int, name: str = "order") -> np.ndarray:
    """``order`` as an (n,) int64 permutation of ``range(n)``; ``None`` gives the identity.

    Raises
    ------
    ValueError
        Not an integer array of shape (n,), or some patch missing or repeated.
    """
    if order is None:
        return np.arange(n, dtype=np.int64)
    perm = np.asarray(order)
    if perm.shape != (n,) or not (np.issubdtype(perm.dtype, np.integer) or perm.size == 0):
        raise ValueError(f"{name} must be a permutation of range({n}) as an int array of shape ({n},); "
                         f"got {perm.dtype} array of shape {perm.shape}")
    if not np.array_equal(np.sort(perm), np.arange(n)):
        raise ValueError(f"{name} must be a permutation of range({n}) (each patch exactly once)")
    return perm.astype(np.int64)


def check_reflectance(reflectance, n: int, name: str = "reflectance") -> np.ndarray:
    """``reflectance`` as an (n, 3) float64 array, finite and in [0, 1).

    Raises
    ------
    ValueError
        Wrong shape, NaN/inf, or a value outside [0, 1) (names the first bad patch).
    """
    rho = np.asarray(reflectance, dtype=np.float64)
    if rho.shape != (n, 3):
        raise ValueError(f"{name} must have shape ({n}, 3); got {rho.shape}")
    bad = ~(np.isfinite(rho) & (rho >= 0) & (rho < 1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} must be finite and in [0, 1) (a reflectance of 1 or more creates energy); "
                         f"patch {i} has {rho[i].tolist()}")
    return rho


def check_factorize_options(n: int, eps: float, block_size: int, dtype, relative: bool = True) -> np.dtype:
    """The precompute's options for an n-patch scene (every backend's); returns the factor dtype.

    Raises
    ------
    ValueError
        eps outside (0, 1) (relative) or not positive (absolute), a block size
        outside [1, n], or a dtype other than float32/float64.
    """
    if relative and not (0.0 < eps < 1.0):
        raise ValueError(f"eps must be in (0, 1) (a relative Frobenius error, e.g. 0.02); got {eps}")
    if not relative and not (eps > 0.0 and math.isfinite(eps)):
        raise ValueError(f"an absolute eps must be a positive number; got {eps}")
    if not (1 <= block_size <= n):
        raise ValueError(f"block size must be between 1 and the patch count {n}; got {block_size}")
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64; got {dt}")
    return dt
