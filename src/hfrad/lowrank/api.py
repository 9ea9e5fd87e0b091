"""Low-rank factorizations of ``G = diag(rho_max) F`` from an in-core F or from its column blocks.

These return a :class:`~hfrad.lowrank.factors.LowRank` in the internal patch
order; :func:`hfrad.factorize` (the pipeline layer) validates the user's input
and wraps the result into the solver object. Inputs here are trusted.
"""

from __future__ import annotations

import time
from typing import Iterable

import numpy as np

from ..errors import InputError
from ..progress import ProgressCallback
from .baselines import randomized_factorization, sketch_factorization, svd_factorization
from .hf import hierarchical_factorization
from .factors import LowRank

METHODS = ("hf", "svd", "rsvd", "sketch")


def check_method(method: str) -> None:
    """InputError unless ``method`` is one of :data:`METHODS`."""
    if method not in METHODS:
        raise InputError(f"method must be one of {METHODS}; got {method!r}")


def lowrank_from_matrix(F: np.ndarray, rho_max: np.ndarray, perm: np.ndarray, *, eps: float, relative: bool,
                        block_size: int, dtype, method: str, rng=None, leaf_share: float = 0.5,
                        progress: ProgressCallback = None) -> LowRank:
    """``G_int = diag(rho_max) F`` in internal order ``perm``, factored by ``method``.

    Parameters
    ----------
    F : (n, n) float, user order
    rho_max : (n,) float, user order
    perm : (n,) int, internal order (internal index t holds user patch perm[t])
    eps, relative, block_size, dtype, rng, leaf_share, progress
        As in :func:`hfrad.factorize`.
    method : {"hf", "svd", "rsvd", "sketch"}

    Returns
    -------
    LowRank
        ``info["time_factor"]`` holds the seconds spent.
    """
    n = F.shape[0]
    if method == "hf":
        blocks = ((s, min(s + block_size, n), F[np.ix_(perm, perm[s:s + block_size])])
                  for s in range(0, n, block_size))
        return lowrank_from_blocks(blocks, n, rho_max, perm, eps=eps, relative=relative, dtype=dtype,
                                   n_blocks=-(-n // block_size), leaf_share=leaf_share, progress=progress)
    t0 = time.perf_counter()
    G = (rho_max[perm, None] * F[np.ix_(perm, perm)]).astype(dtype)
    if method == "svd":
        lr = svd_factorization(G, eps=eps, relative=relative, dtype=dtype)
    elif method == "rsvd":
        lr = randomized_factorization(G, eps=eps, relative=relative, dtype=dtype, rng=rng)
    else:
        lr = sketch_factorization(G, eps=eps, relative=relative, dtype=dtype, block_size=block_size, rng=rng)
    lr.info["time_factor"] = time.perf_counter() - t0
    return lr


def lowrank_from_blocks(blocks: Iterable[tuple[int, int, np.ndarray]], n: int, rho_max: np.ndarray,
                        perm: np.ndarray, *, eps: float, relative: bool, dtype, n_blocks: int,
                        leaf_share: float = 0.5, progress: ProgressCallback = None) -> LowRank:
    """One HF pass over column blocks ``F[perm][:, perm[start:stop]]`` (rows not yet scaled by rho_max).

    Raises
    ------
    ValueError
        Blocks not consecutive from column 0 to n, or of the wrong shape.
    """
    scale = rho_max[perm][:, None].astype(dtype)
    expected = [0]

    def scaled():
        for start, stop, Fb in blocks:
            if start != expected[0]:
                raise InputError(f"column blocks must be consecutive: expected start {expected[0]}, "
                                 f"got {start}")
            Fb = np.asarray(Fb, dtype=dtype)
            if Fb.shape != (n, stop - start):
                raise InputError(f"block {start}:{stop} must have shape ({n}, {stop - start}); got {Fb.shape}")
            if not np.isfinite(Fb).all():   # LAPACK runs unchecked: a NaN would give a silent rank-0 node
                i, j = np.argwhere(~np.isfinite(Fb))[0]
                raise InputError(f"column block {start}:{stop} has a NaN or infinite value at row {i}, "
                                 f"column {start + j}")
            expected[0] = stop
            yield scale * Fb                       # rows of G = diag(rho_max) F

    lr = hierarchical_factorization(scaled(), n, eps=eps, relative=relative, dtype=dtype,
                                    leaf_share=leaf_share, n_blocks=n_blocks, progress=progress)
    if expected[0] != n:
        raise InputError(f"column blocks cover columns 0..{expected[0]}, expected 0..{n}")
    lr.info["time_factor"] = lr.info["time_total"]
    return lr
