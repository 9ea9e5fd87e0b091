"""Validation of arrays a user passes in, one helper per kind (used at API boundaries only)."""

from __future__ import annotations

import math
import os
import warnings

import numpy as np

from .errors import InputError

__all__ = ["check_permutation", "check_reflectance", "check_areas", "check_trans", "check_finite", "object_first",
           "check_factorize_options"]


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
        raise InputError(f"{name} must be a permutation of range({n}) as an int array of shape ({n},); "
                         f"got {perm.dtype} array of shape {perm.shape}")
    if not np.array_equal(np.sort(perm), np.arange(n)):
        raise InputError(f"{name} must be a permutation of range({n}) (each patch exactly once)")
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
        raise InputError(f"{name} must have shape ({n}, 3); got {rho.shape}")
    bad = ~(np.isfinite(rho) & (rho >= 0) & (rho < 1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{name} must be finite and in [0, 1) (a reflectance of 1 or more creates energy); "
                         f"patch {i} has {rho[i].tolist()}")
    return rho


def check_areas(areas, n: int, name: str = "areas") -> np.ndarray:
    """``areas`` as an (n,) float64 array of finite positive values (m^2)."""
    a = np.asarray(areas, dtype=np.float64)
    if a.shape != (n,):
        raise InputError(f"{name} must have shape ({n},); got {a.shape}")
    bad = ~(np.isfinite(a) & (a > 0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{name} must be finite and > 0; patch {i} has {a[i]}")
    return a


def check_trans(trans) -> bool:
    """True for an adjoint solve (``"T"``; ``"H"`` is the same for real matrices), False for ``"N"``."""
    if trans not in ("N", "T", "H"):
        raise InputError(f"trans must be 'N' (solve) or 'T' (adjoint solve), as in scipy; got {trans!r}")
    return trans != "N"


def check_finite(array, name: str) -> np.ndarray:
    """``array`` as a float64 array; InputError naming the first NaN/inf entry (LAPACK runs unchecked)."""
    a = np.asarray(array, dtype=np.float64)
    if not np.isfinite(a).all():
        where = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise InputError(f"{name} has a NaN or infinite value at index {where}")
    return a


def object_first(obj, path, call: str):
    """``(obj, path)`` for writers that take the object first; an old path-first call is swapped with a warning.

    Every hfrad writer is ``write(object, path)``; until the 0.2 release a
    call in the old order (path first) still works but emits a
    DeprecationWarning naming the new spelling ``call``.
    """
    if isinstance(obj, (str, os.PathLike)) and not isinstance(path, (str, os.PathLike)):
        warnings.warn(f"the object comes first, then the path: {call}", DeprecationWarning, stacklevel=3)
        return path, obj
    return obj, path


def check_factorize_options(n: int, eps: float, block_size: int, dtype, relative: bool = True) -> np.dtype:
    """The precompute's options for an n-patch scene (every backend's); returns the factor dtype.

    Raises
    ------
    InputError (a ValueError)
        eps outside (0, 1) (relative) or not positive (absolute), a block size
        outside [1, n], or a dtype other than float32/float64.
    """
    if relative and not (0.0 < eps < 1.0):
        raise InputError(f"eps must be in (0, 1) (a relative Frobenius error, e.g. 0.02); got {eps}")
    if not relative and not (eps > 0.0 and math.isfinite(eps)):
        raise InputError(f"an absolute eps must be a positive number; got {eps}")
    if not (1 <= block_size <= n):
        raise InputError(f"block size must be between 1 and the patch count {n}; got {block_size}")
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise InputError(f"dtype must be float32 or float64; got {dt}")
    return dt
