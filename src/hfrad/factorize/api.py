"""Entry points that build an :class:`~hfrad.solve.woodbury.HFactorization` from form factors."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ..progress import ProgressCallback
from .baselines import randomized_factorization, sketch_factorization, svd_factorization
from .hf import hierarchical_factorization

if TYPE_CHECKING:
    from ..solve.woodbury import HFactorization

METHODS = ("hf", "svd", "rsvd", "sketch")


def _check_reflectance(reflectance, n: int) -> np.ndarray:
    rho = np.asarray(reflectance, dtype=np.float64)
    if rho.shape != (n, 3):
        raise ValueError(f"reflectance must have shape ({n}, 3); got {rho.shape}")
    if not (np.isfinite(rho).all() and (rho >= 0).all() and (rho < 1).all()):
        raise ValueError("reflectance must be finite and in [0, 1) (a reflectance of 1 or more creates energy)")
    return rho


def _check_perm(order, n: int) -> np.ndarray:
    if order is None:
        return np.arange(n)
    perm = np.asarray(order, dtype=np.int64)
    if perm.shape != (n,) or not np.array_equal(np.sort(perm), np.arange(n)):
        raise ValueError(f"order must be a permutation of 0..{n - 1}; got shape {perm.shape}")
    return perm


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")


def factorize_matrix(F, reflectance, *, eps: float = 0.02, relative: bool = True,
                     block_size: int = 256, dtype=np.float32, order=None, method: str = "hf",
                     rng=None, progress: ProgressCallback = None) -> "HFactorization":
    """Factor an in-core form-factor matrix: ``diag(rho_max) F ~= Q V^T`` in internal order.

    Parameters
    ----------
    F : (n, n) float
        Form factors in the user's patch order (F[i, j]: fraction leaving i that reaches j).
    reflectance : (n, 3) float in [0, 1)
    eps : float
        Frobenius tolerance on ``G = diag(rho_max) F`` (relative to ``||G||_F``
        unless ``relative=False``).
    block_size : int
        Column block width streamed to the factorizer.
    dtype : float32 or float64
    order : (n,) int, optional
        Internal order (e.g. Z-order): internal index t holds user patch order[t].
    method : {"hf", "svd", "rsvd", "sketch"}
    rng : seed for the randomized methods.
    progress : callable (done, total), optional

    Returns
    -------
    HFactorization

    Raises
    ------
    ValueError
        Bad shapes, reflectance outside [0, 1), unknown method or order.
    """
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise ValueError(f"form factors must be a square (n, n) matrix; got {F.shape}")
    n = F.shape[0]
    rho = _check_reflectance(reflectance, n)
    perm = _check_perm(order, n)
    _check_method(method)
    if block_size < 1:
        raise ValueError(f"block_size must be >= 1; got {block_size}")
    rho_max = rho.max(axis=1)
    if method == "hf":
        blocks = ((s, min(s + block_size, n), F[np.ix_(perm, perm[s:s + block_size])])
                  for s in range(0, n, block_size))
        return factorize_blocks(blocks, n, rho, perm, eps=eps, relative=relative, dtype=dtype,
                                n_blocks=-(-n // block_size), block_size=block_size, progress=progress)
    t0 = time.perf_counter()
    G = (rho_max[perm, None] * F[np.ix_(perm, perm)]).astype(dtype)
    if method == "svd":
        lr = svd_factorization(G, eps=eps, relative=relative, dtype=dtype)
    elif method == "rsvd":
        lr = randomized_factorization(G, eps=eps, relative=relative, dtype=dtype, rng=rng)
    else:
        lr = sketch_factorization(G, eps=eps, relative=relative, dtype=dtype, block_size=block_size, rng=rng)
    params = {"method": method, "block_size": block_size, "dtype": np.dtype(dtype).name,
              "time_factor": time.perf_counter() - t0}
    from ..solve.woodbury import HFactorization   # lazy: solve imports factorize.lowrank
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params)


def factorize_blocks(blocks: Iterable[tuple[int, int, np.ndarray]], n: int, reflectance, perm, *,
                     eps: float = 0.02, relative: bool = True, dtype=np.float32,
                     n_blocks: int | None = None, leaf_share: float = 0.5,
                     block_size: int | None = None,
                     progress: ProgressCallback = None) -> "HFactorization":
    """Out-of-core HF: one pass over column blocks of F in internal order.

    Parameters
    ----------
    blocks : iterable of (start, stop, Fblock)
        ``Fblock = F[perm][:, perm[start:stop]]`` (n x b), rows already in
        internal order and not yet multiplied by rho_max; consecutive, left to right.
    n : int
    reflectance : (n, 3) float in [0, 1), user order
    perm : (n,) int, internal order
    eps, relative, dtype, leaf_share, progress : see
        :func:`~hfrad.factorize.hf.hierarchical_factorization`
    n_blocks : int, optional
        Number of blocks (needed for the error budget when ``blocks`` has no len);
        defaults to ``ceil(n / block_size)`` when ``block_size`` is given.

    Returns
    -------
    HFactorization
    """
    rho = _check_reflectance(reflectance, n)
    perm = _check_perm(perm, n)
    rho_max = rho.max(axis=1)
    scale = rho_max[perm][:, None].astype(dtype)
    if n_blocks is None and block_size is not None:
        n_blocks = -(-n // block_size) if n else 0
    expected = [0]

    def scaled():
        for start, stop, Fb in blocks:
            if start != expected[0]:
                raise ValueError(f"column blocks must be consecutive: expected start {expected[0]}, "
                                 f"got {start}")
            Fb = np.asarray(Fb, dtype=dtype)
            if Fb.shape != (n, stop - start):
                raise ValueError(f"block {start}:{stop} must have shape ({n}, {stop - start}); got {Fb.shape}")
            expected[0] = stop
            yield scale * Fb                       # rows of G = diag(rho_max) F

    if n_blocks is None:
        try:
            n_blocks = len(blocks)
        except TypeError:
            raise ValueError("pass n_blocks (or block_size) when blocks is a generator") from None
    lr = hierarchical_factorization(scaled(), n, eps=eps, relative=relative, dtype=dtype,
                                    leaf_share=leaf_share, n_blocks=n_blocks, progress=progress)
    if expected[0] != n:
        raise ValueError(f"column blocks cover columns 0..{expected[0]}, expected 0..{n}")
    params = {"method": "hf", "block_size": block_size, "dtype": np.dtype(dtype).name,
              "leaf_share": leaf_share, "time_factor": lr.info["time_total"]}
    from ..solve.woodbury import HFactorization   # lazy: solve imports factorize.lowrank
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params)
