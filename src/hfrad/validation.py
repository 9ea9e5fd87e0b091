"""Validation of arrays a user passes in, one helper per kind (used at API boundaries only)."""

from __future__ import annotations

import math
import os
import warnings

import numpy as np

from .errors import InputError

__all__ = ["check_permutation", "check_reflectance", "check_areas", "check_trans", "check_finite", "object_first",
           "check_factorize_options", "check_eps", "check_tolerance", "check_dtype", "as_real_array", "check_exitance", "check_form_factors", "MAX_EXITANCE",
           "clip_token"]

#: The largest exitance (W/m^2) accepted anywhere: 1e30, far above any light (the sun's surface emits
#: 6.3e7 W/m^2) and 3e8 below float32's largest number (3.4e38), in which radiosity is stored and
#: pictures are computed; the margin covers the 1 / (1 - rho) gain of many bounces and the sums of
#: a picture's exposure. Larger values would turn into inf/NaN radiosity and an all-black picture.
MAX_EXITANCE = 1e30

#: Largest row sum of a form-factor matrix given to ``factorize``: rows sum to 1 in a closed
#: scene; hfrad's own matrices exceed it by 0.2% at most (the Cornell box at 126 patches: 1.0023).
MAX_ROW_SUM = 1.05

#: Characters of an offending token quoted in an error message.
QUOTE_CHARS = 200


def clip_token(text, limit: int = QUOTE_CHARS) -> str:
    """``repr`` of ``text`` cut to about ``limit`` characters (with the length left out), for error lines.

    A bad token in a file can be megabytes long; an error line quotes its
    start only, e.g. ``'1111...' (100,005 characters)``.
    """
    text = str(text)
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}... ({len(text):,} characters)"


def as_real_array(array, name: str) -> np.ndarray:
    """``array`` as a float64 ndarray of real numbers; refuses what numpy would convert silently.

    ``np.asarray(x, dtype=float)`` drops the imaginary part of a complex
    array (a ComplexWarning at most), turns booleans into 0/1 and parses
    strings; none of these is a physical quantity, so each is refused.

    Raises
    ------
    InputError (a ValueError)
        A complex, boolean, string, object (``None``, ragged lists, mixed
        types) or date array, naming ``name`` and the dtype received.
    """
    try:
        a = array if isinstance(array, np.ndarray) else np.asarray(array)
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise InputError(f"{name} must be an array of real numbers; got {type(array).__name__} that is "
                         f"not one ({str(exc).split('.')[0]})") from None
    kind = a.dtype.kind
    if kind in "iuf":
        return np.asarray(a, dtype=np.float64)
    if kind == "c":
        raise InputError(f"{name} must be real numbers; got a complex array ({a.dtype}). hfrad does not "
                         f"drop imaginary parts silently: pass {name}.real if the imaginary part is meant to be 0")
    if kind == "b":
        raise InputError(f"{name} must be real numbers; got a boolean array (convert a mask with "
                         f".astype(float) if 1.0 and 0.0 are meant)")
    what = {"O": "Python objects (None, ragged lists or mixed types?)", "U": "strings", "S": "bytes",
            "M": "dates", "m": "time differences", "V": "structured records"}.get(kind, str(a.dtype))
    raise InputError(f"{name} must be an array of real numbers; got an array of {what} (dtype {a.dtype})")


def check_exitance(exitance, name: str = "exitance", *, signed: bool = False) -> np.ndarray:
    """``exitance`` as a float64 array of finite values, >= 0 (unless ``signed``) and at most MAX_EXITANCE.

    Shapes are the caller's to check. ``signed`` allows negative entries
    (the right-hand side of an adjoint solve); the magnitude limit holds either way.

    Raises
    ------
    InputError (a ValueError)
        Not real numbers (see :func:`as_real_array`), NaN/inf, a negative
        value, or one above ``MAX_EXITANCE`` W/m^2 (index named).
    """
    E = as_real_array(exitance, name)
    flat = E.reshape(-1)
    bad = ~np.isfinite(flat)
    if bad.any():
        where = np.unravel_index(int(np.flatnonzero(bad)[0]), E.shape)
        raise InputError(f"{name} has a NaN or infinite value at index {tuple(int(i) for i in where)}")
    if not signed and (flat < 0).any():
        where = np.unravel_index(int(np.flatnonzero(flat < 0)[0]), E.shape)
        raise InputError(f"{name} must be >= 0 (W/m^2); index {tuple(int(i) for i in where)} "
                         f"has a negative value, {float(E[where]):g}")
    big = np.abs(flat) > MAX_EXITANCE
    if big.any():
        where = np.unravel_index(int(np.flatnonzero(big)[0]), E.shape)
        raise InputError(f"{name} {float(E[where]):g} W/m^2 at index {tuple(int(i) for i in where)} is "
                         f"above the largest exitance hfrad computes with, {MAX_EXITANCE:g} W/m^2 "
                         "(radiosity is stored in float32 and would overflow); express it in a larger "
                         "unit, e.g. divide every emission by 1e6")
    return E


def check_form_factors(form_factors, name: str = "form factors") -> np.ndarray:
    """``form_factors`` as a square (n, n) float64 matrix of finite entries >= 0, rows summing to at most
    ``MAX_ROW_SUM``.

    Raises
    ------
    InputError (a ValueError)
        Not real numbers (complex, strings, objects...), not square, NaN/inf,
        a negative entry (a form factor is a fraction of energy, never negative),
        or a row summing to more than ``MAX_ROW_SUM`` (energy created).
    """
    F = as_real_array(form_factors, name)
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise InputError(f"{name} must be a square (n, n) matrix; got {F.shape}")
    if not np.isfinite(F).all():
        i, j = np.argwhere(~np.isfinite(F))[0]
        raise InputError(f"{name} have a NaN or infinite value at F[{i}, {j}]")
    if (F < 0).any():
        i, j = np.argwhere(F < 0)[0]
        raise InputError(f"{name} must be >= 0 (a fraction of the energy leaving a patch); "
                         f"F[{i}, {j}] = {F[i, j]:g}")
    rows = F.sum(axis=1)
    if len(rows) and rows.max() > MAX_ROW_SUM:
        i = int(np.argmax(rows))
        raise InputError(f"{name}: row {i} sums to {rows[i]:.6g}; a patch cannot send out more than all "
                         f"the energy it emits (rows sum to 1 in a closed scene, at most {MAX_ROW_SUM:g} is "
                         "accepted for discretisation error); with such a matrix the solution can turn "
                         "negative or grow without bound (duplicate faces double a row's sum)")
    return F


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
    rho = as_real_array(reflectance, name)
    if rho.shape != (n, 3):
        raise InputError(f"{name} must have shape ({n}, 3); got {rho.shape}")
    bad = ~(np.isfinite(rho) & (rho >= 0) & (rho < 1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{name} must be finite and in [0, 1) (a reflectance of 1 or more creates energy); "
                         f"patch {i} has {tuple(rho[i].tolist())}")
    return rho


def check_areas(areas, n: int, name: str = "areas") -> np.ndarray:
    """``areas`` as an (n,) float64 array of finite positive values (m^2)."""
    a = as_real_array(areas, name)
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
    """``array`` as a float64 array; InputError naming the first NaN/inf entry (LAPACK runs unchecked),
    or a complex/non-numeric array (:func:`as_real_array`)."""
    a = as_real_array(array, name)
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


def check_eps(eps, relative: bool = True) -> float:
    """The factorization's target error: in (0, 1) when relative, a positive finite number when absolute.

    The one check of a user's ``eps`` (every entry point, before anything reads it).
    """
    if relative and not (0.0 < eps < 1.0):
        raise InputError(f"eps must be in (0, 1) (a relative Frobenius error, e.g. 0.02); got {eps}")
    if not relative and not (eps > 0.0 and math.isfinite(eps)):
        raise InputError(f"an absolute eps must be a positive number; got {eps}")
    return float(eps)


def check_tolerance(eps) -> float:
    """A low-rank factorizer's tolerance (:mod:`hfrad.lowrank`): finite and >= 0 (0 keeps every singular value)."""
    if not (eps >= 0 and np.isfinite(eps)):
        raise InputError(f"eps must be a finite number >= 0; got {eps!r}")
    return float(eps)


def check_dtype(dtype) -> np.dtype:
    """The factors' dtype: float32 or float64."""
    dt = np.dtype(dtype)
    if dt not in (np.float32, np.float64):
        raise InputError(f"dtype must be float32 or float64; got {dt}")
    return dt


def check_factorize_options(n: int, eps: float, block_size: int, dtype, relative: bool = True) -> np.dtype:
    """The precompute's options for an n-patch scene (every backend's); returns the factor dtype.

    Raises
    ------
    InputError (a ValueError)
        eps outside (0, 1) (relative) or not positive (absolute), a block size
        outside [1, n], or a dtype other than float32/float64.
    """
    check_eps(eps, relative)
    if not (1 <= block_size <= n):
        raise InputError(f"block size must be between 1 and the patch count {n}; got {block_size}")
    return check_dtype(dtype)
