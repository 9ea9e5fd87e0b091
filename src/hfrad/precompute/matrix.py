"""The precompute of a form-factor matrix you already have: dense, or streamed in column blocks.

:func:`factorize_matrix` (re-exported as :func:`hfrad.factorize_matrix`) takes a dense F
and is the only entry to the dense baselines; :func:`factorize_blocks` takes column
blocks of F in internal order (out of core). Neither knows a scene: no visibility
rays, no near-field split. Both end in the same assembly step as a scene's precompute
(:func:`~hfrad.precompute.assemble.solver_object`).
"""

from __future__ import annotations

import numpy as np

from ..defaults import DEFAULT_BLOCK_SIZE
from ..errors import InputError
from ..lowrank.api import check_method, lowrank_from_blocks, lowrank_from_matrix
from ..progress import ProgressCallback
from ..scene.scene import Scene
from ..solve.stats import PassStatistics
from ..solve.woodbury import HFactorization
from ..validation import (check_areas, check_dtype, check_eps, check_form_factors, check_permutation,
                          check_reflectance)
from .assemble import solver_object

__all__ = ["factorize_matrix", "factorize_blocks"]


def factorize_matrix(F, reflectance, *, areas=None, eps: float = 0.02, relative: bool = True,
                     block_size: int | None = None, dtype="float32", order=None, method: str = "hf",
                     leaf_share: float = 0.5, rng=None, progress: ProgressCallback = None) -> HFactorization:
    """Factor the radiosity system of a form-factor matrix you already have.

    The same factorization and solver object as :func:`hfrad.factorize`, from a
    dense F instead of a scene (no visibility rays, no near-field split), and
    the only entry to the dense baselines.

    Parameters
    ----------
    F : (n, n) float array
        Form factors in the user's patch order: ``F[i, j]`` is the fraction
        of the energy leaving patch i that reaches patch j (>= 0, rows
        summing to at most 1).
    reflectance : (n, 3) float in [0, 1)
        Diffuse reflectance per patch and colour channel (or (n,) grey).
    areas : (n,) float > 0, m^2, optional
        Patch areas: the error figures are then in the area-weighted norm,
        where reciprocity gives the tight contraction bound; without them
        the plain 2-norm.
    eps : float in (0, 1)
        Target ``||G - Q V^T||_F`` relative to ``||G||_F`` (absolute with
        ``relative=False``), ``G = diag(rho_max) F``.
    block_size : int, optional
        Column block width; default ``DEFAULT_BLOCK_SIZE`` (256).
    dtype : {"float32", "float64"}
        Precision of the factors.
    order : "input" or (n,) int, optional
        Internal patch order (internal index t holds user patch order[t]);
        default the input order. Only speed and rank depend on it.
    method : {"hf", "svd", "rsvd", "sketch"}
        HF (the paper's) or a baseline on the dense matrix: truncated SVD
        (LAPACK), randomized SVD (scikit-learn), or a one-pass sketch.
    leaf_share : float in (0, 1]
        HF: share of the squared error budget given to the leaf SVDs.
    rng : None, int or numpy Generator
        Seed of the randomized baselines ("rsvd", "sketch").
    progress : callable (done, total), optional
        Column blocks done.

    Returns
    -------
    HFactorization

    Raises
    ------
    InputError (a ValueError)
        Bad shapes or values (negative entries, rows summing above 1.05,
        NaN), or options; the message names the argument.

    Notes
    -----
    Memory: F itself (n^2 float64 words) plus the factors (O(nk)).

    Examples
    --------
    >>> import numpy as np, hfrad
    >>> F = np.full((40, 40), 1 / 40)                 # a closed, uniform enclosure
    >>> fac = hfrad.factorize_matrix(F, np.full((40, 3), 0.5), eps=1e-3)
    >>> bool(np.allclose(fac.solve(np.ones(40)), 2.0))   # B = E / (1 - rho)
    True
    """
    if isinstance(F, Scene):
        raise InputError("factorize_matrix takes a form-factor matrix; for a Scene use hfrad.factorize(scene)")
    block_size = DEFAULT_BLOCK_SIZE if block_size is None else block_size
    F = check_form_factors(F)  # real, square, finite, >= 0
    if F.ndim != 2 or F.shape[0] != F.shape[1]:
        raise InputError(f"form factors must be a square (n, n) matrix; got {F.shape}")
    n = F.shape[0]
    rho = check_reflectance(reflectance, n)
    if isinstance(order, str):
        if order != "input":
            raise InputError(f"order {order!r} needs patch positions: pass a Scene, or an (n,) permutation "
                             "with a matrix")
        order = None
    perm = check_permutation(order, n)
    check_method(method)
    dt = check_dtype(dtype)
    check_eps(eps, relative)
    if block_size < 1:
        raise InputError(f"block_size must be >= 1; got {block_size}")
    rho_max = rho.max(axis=1)
    if not np.isfinite(F).all():
        i, j = np.argwhere(~np.isfinite(F))[0]
        raise InputError(f"form factors have a NaN or infinite value at F[{i}, {j}]")
    lr = lowrank_from_matrix(F, rho_max, perm, eps=eps, relative=relative, block_size=block_size, dtype=dt,
                             method=method, rng=rng, leaf_share=leaf_share, progress=progress)
    stats = PassStatistics(n, None if areas is None else check_areas(areas, n)[perm], reflectance=rho[perm])
    stats.add(0, n, F[np.ix_(perm, perm)], rho_max[perm][:, None])
    params = {"method": method, "block_size": block_size, "dtype": dt.name,
              "time_factor": lr.info["time_factor"]}
    if method == "hf":
        params["leaf_share"] = leaf_share
    return solver_object(perm, lr, rho, params, stats)


def factorize_blocks(blocks, n: int, reflectance, perm, *, eps: float = 0.02, relative: bool = True,
                     dtype=np.float32, n_blocks: int | None = None, leaf_share: float = 0.5,
                     block_size: int | None = None, progress: ProgressCallback = None) -> HFactorization:
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
        :func:`~hfrad.lowrank.hf.hierarchical_factorization`
    n_blocks : int, optional
        Number of blocks (needed for the error budget when ``blocks`` has no len);
        defaults to ``ceil(n / block_size)`` when ``block_size`` is given.

    Returns
    -------
    HFactorization
    """
    rho = check_reflectance(reflectance, n)
    perm = check_permutation(perm, n)
    rho_max = rho.max(axis=1)
    if n_blocks is None and block_size is not None:
        n_blocks = -(-n // block_size) if n else 0
    if n_blocks is None:
        try:
            n_blocks = len(blocks)
        except TypeError:
            raise InputError("pass n_blocks (or block_size) when blocks is a generator") from None
    stats = PassStatistics(n)
    rows_rho = rho_max[perm][:, None]

    def recorded():
        for start, stop, Fb in blocks:
            yield start, stop, Fb
            stats.add(start, stop, Fb, rows_rho)   # after the factorizer has checked the block

    lr = lowrank_from_blocks(recorded(), n, rho_max, perm, eps=eps, relative=relative, dtype=dtype,
                             n_blocks=n_blocks, leaf_share=leaf_share, progress=progress)
    params = {"method": "hf", "block_size": block_size, "dtype": np.dtype(dtype).name,
              "leaf_share": leaf_share, "time_factor": lr.info["time_factor"]}
    return solver_object(perm, lr, rho, params, stats)
