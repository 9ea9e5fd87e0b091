"""The precomputation: scene -> Z-order -> form-factor column blocks -> HF -> Woodbury.

``factorize(scene)`` is what ``hfrad precompute`` runs. Column blocks of
``G = diag(rho_max) F`` are generated one at a time in Z-order, pushed into a
:class:`~hfrad.factorize.streaming.HFStream` and dropped, so the n x n matrix
never exists. With ``checkpoint=PATH`` the stream state is saved every
``checkpoint_interval`` seconds and a rerun resumes after the last saved block.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .defaults import DEFAULT_BLOCK_SIZE
from .errors import SceneError
from .factorize.api import check_method, lowrank_from_blocks, lowrank_from_matrix
from .factorize.hf import HFStream
from .factorize.nearfield import DEFAULT_NEAR_ENTRIES, NearFieldSplit, near_radius
from .factorize.streaming import load_checkpoint, save_checkpoint
from .progress import ProgressCallback, report
from .scene.scene import Scene
from .scene.zorder import patch_order
from .solve.nearfield import NearFieldFactorization
from .solve.woodbury import HFactorization
from .validation import check_factorize_options, check_permutation, check_reflectance

#: ``near_field="auto"`` splits the near field from this many patches on (below, it does not pay).
NEAR_FIELD_MIN_PATCHES = 3000

StatusCallback = Callable[[dict], None] | None


def _scene_key(scene: Scene, params: dict) -> str:
    """A hash of everything the factorization depends on: geometry, reflectance, parameters."""
    h = hashlib.sha256()
    for a in (scene.vertices, scene.faces, scene.occluder_vertices, scene.occluder_faces, scene.patch_of_triangle,
              scene.reflectance.max(axis=1)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


def check_factorize_args(scene: Scene, eps: float, block_size: int, dtype, relative: bool = True) -> np.dtype:
    """Validate the options of :func:`factorize` at the API boundary."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a hfrad Scene (see hfrad.load_scene); got {type(scene).__name__}")
    if scene.n_patches == 0:
        raise SceneError(f"{scene.name}: the scene has no patches")
    return check_factorize_options(scene.n_patches, eps, block_size, dtype, relative)


def factorize(scene: Scene, *, eps: float = 0.02, relative: bool = True, block_size: int | None = None,
              dtype="float32", samples: int | None = None, order: str = "zorder", leaf_share: float = 0.5,
              checkpoint: str | Path | None = None, checkpoint_interval: float = 30.0,
              blas_threads: int | None = 1, processes: int | None = 1, one_ray_tol: float | None = None,
              near_field: int | str | None = None,
              progress: ProgressCallback = None, status: StatusCallback = None) -> HFactorization:
    """Precompute a scene: form factors with visibility, HF of ``diag(rho_max) F``, Woodbury factors.

    Parameters
    ----------
    scene : Scene
        Patches with reflectance (n, 3) in [0, 1).
    eps : float in (0, 1)
        Target ``||G - Q V^T||_F``, relative to ``||G||_F`` (absolute with ``relative=False``).
    block_size : int, optional
        Column block width (patches per block); default min(256, n).
    dtype : {"float32", "float64"}
        Precision of the factors.
    samples : int, optional
        Visibility rays per patch pair (default: the form-factor engine's).
    order : {"zorder", "hilbert", "random", "input"}
        Internal patch order; Z-order is the paper's and the default. Only speed and
        rank depend on it; every input and output stays in the user's order.
    leaf_share : float in (0, 1]
        Share of the squared error budget given to the leaf SVDs.
    checkpoint : path, optional
        Save the stream state here while running; resume from it if it exists.
        Deleted when the factorization completes.
    checkpoint_interval : float, seconds
    blas_threads : int or None
        BLAS threads during the precomputation (None: leave as is). One is
        fastest while the form-factor engine uses the other cores.
    processes : int or None
        Form-factor worker processes (None: one per core from 4,000 patches on);
        the result does not depend on it. Default 1 (this process: numba threads
        plus one Embree thread), because on the shared benchmark machine (load
        ~25) two worker processes were measured 2x slower in wall time.
    one_ray_tol : float or None
        Pairs that together hold at most this share of ``||F||_F`` get one
        visibility ray instead of several (:func:`hfrad.formfactors.parallel.one_ray_threshold`);
        None: ``eps / 4`` for a relative eps, 0 (off) for an absolute one.
    near_field : "auto", int or None
        The near-field split (METHOD.md s. 8, :mod:`hfrad.factorize.nearfield`):
        pairs within a radius holding about this many neighbours per row go into
        a sparse N, HF factors only ``G - N``, and the solver is Woodbury around a
        sparse LU of ``I - D_c N`` (:class:`~hfrad.solve.nearfield.NearFieldFactorization`).
        "auto": ``DEFAULT_NEAR_ENTRIES`` from ``NEAR_FIELD_MIN_PATCHES`` patches on,
        off below; None or 0 (default): off (plain Woodbury). Off by default because,
        measured on the Cornell box at 3K-6K patches and eps 0.02, HF's rank at equal
        eps does not drop (it rises ~15% at 6K) and at equal radiosity error it drops
        only ~17% while the sparse LU set-up costs k sparse solves per channel.
    progress : callable (done, total), optional
        Column blocks done.
    status : callable (dict), optional
        Called after each block with ``blocks``, ``rank``, ``elapsed``.

    Returns
    -------
    HFactorization
        ``fac.solve(E)`` gives the radiosity for any exitance E, in O(nk).

    Notes
    -----
    Memory: one n x block_size block (float64) plus the factors (O(nk)); the
    n x n matrix is never formed. Time: dominated by the form factors.
    """
    if block_size is None and isinstance(scene, Scene):
        block_size = min(DEFAULT_BLOCK_SIZE, max(scene.n_patches, 1))
    dt = check_factorize_args(scene, eps, block_size, dtype, relative)
    from .formfactors.blocks import iter_column_blocks
    from .formfactors.kernel import settings as kernel_settings
    from .formfactors.visibility import settings as visibility_settings

    n = scene.n_patches
    perm = patch_order(scene.centroids, order)
    rho_max = scene.reflectance.max(axis=1)
    n_blocks = math.ceil(n / block_size)
    if one_ray_tol is None:
        one_ray_tol = 0.25 * eps if relative else 0.0
    params = {"eps": eps, "relative": relative, "block_size": block_size, "dtype": dt.name,
              "samples": samples, "order": order, "leaf_share": leaf_share, "one_ray_tol": one_ray_tol,
              "near_field": near_entries(near_field, n),
              # kernel version and tolerance: recorded in the .hfr, part of the checkpoint key
              "form_factors": {**kernel_settings(), **visibility_settings()}}
    key = _scene_key(scene, params)
    stream = _open_stream(checkpoint, key, n, n_blocks, eps, relative, dt, leaf_share)
    t0 = time.perf_counter()
    ff_kwargs = {} if samples is None else {"samples": samples}
    if samples != 0:
        from .formfactors.parallel import one_ray_threshold
        ff_kwargs["one_ray_below"] = one_ray_threshold(scene, one_ray_tol)
    blocks = iter_column_blocks(scene, block_size, order=perm, first_block=stream.blocks_done,
                                processes=processes, dtype=dt, **ff_kwargs)
    rows_rho = rho_max[perm][:, None].astype(dt)
    split = None
    if params["near_field"]:
        split = NearFieldSplit(scene.centroids[perm], near_radius(scene.centroids, params["near_field"]))
        if stream.extra:
            split.restore(stream.extra)
    with _blas_threads(blas_threads):
        lowrank, time_ff = _stream_blocks(blocks, stream, rows_rho, n_blocks, checkpoint, checkpoint_interval,
                                          key, progress, status, t0, split)
    lowrank.info.update({"time_formfactors": time_ff, "time_precompute": time.perf_counter() - t0})
    if split is None:
        fac = HFactorization(perm, lowrank.Q, lowrank.V, rho_max, scene.reflectance, lowrank,
                             params={**params, "backend": "local"}, scene=scene)
    else:
        t1 = time.perf_counter()
        N = split.matrix()
        lowrank.info.update({"near_radius": split.radius, "near_nnz": int(N.nnz)})
        fac = NearFieldFactorization(perm, lowrank.Q, lowrank.V, N, rho_max, scene.reflectance, lowrank,
                                     params={**params, "backend": "local"}, scene=scene)
        lowrank.info["time_nearfield_setup"] = time.perf_counter() - t1
    lowrank.info["solver"] = fac.solver
    if checkpoint is not None and Path(checkpoint).exists():
        Path(checkpoint).unlink()
    return fac


def near_entries(near_field, n: int) -> int:
    """Neighbours per row of the near field for ``factorize(near_field=...)`` (0 = no split)."""
    if near_field == "auto":
        return DEFAULT_NEAR_ENTRIES if n >= NEAR_FIELD_MIN_PATCHES else 0
    if near_field is None or near_field is False:
        return 0
    if isinstance(near_field, str) or int(near_field) != near_field or near_field < 0:
        raise ValueError(f"near_field must be 'auto', None or a number of neighbours per row (e.g. 64); "
                         f"got {near_field!r}")
    return int(near_field)


def _open_stream(checkpoint, key, n, n_blocks, eps, relative, dt, leaf_share) -> HFStream:
    if checkpoint is not None and Path(checkpoint).exists():
        return load_checkpoint(checkpoint, key)
    return HFStream(n, n_blocks, eps=eps, relative=relative, dtype=dt, leaf_share=leaf_share)


@contextlib.contextmanager
def _blas_threads(count: int | None):
    """Limit BLAS/LAPACK threads while the form-factor engine runs beside the factorization.

    The engine keeps the cores busy (numba kernel + Embree); multi-threaded
    OpenBLAS competing with it spin-waits and slows the small SVDs by 10-50x.
    """
    if count is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=count, user_api="blas"):
        yield


def _stream_blocks(blocks, stream: HFStream, rows_rho, n_blocks, checkpoint, checkpoint_interval, key,
                   progress, status, t0, split=None):
    """Push every column block into the stream (checkpointing); returns (LowRank, form-factor seconds).

    With a near-field ``split``, each block's near entries are moved out before HF sees
    it, and the error budget stays relative to the block's full norm.
    """
    last_save = time.perf_counter()
    time_ff = 0.0
    t_ff = time.perf_counter()
    for start, stop, block in blocks:
        time_ff += time.perf_counter() - t_ff
        G = rows_rho * block  # G = diag(rho_max) F, rows in internal order
        del block
        if split is None:
            stream.push(G)
        else:
            norm2 = float(np.sum(np.square(G, dtype=np.float64)))
            stream.push(split.split(G, start), norm2=norm2)
        del G
        report(progress, stream.blocks_done, n_blocks)
        if status is not None:
            status({"blocks": stream.blocks_done, "rank": stream.current_rank, "elapsed": time.perf_counter() - t0})
        if checkpoint is not None and time.perf_counter() - last_save > checkpoint_interval \
                and stream.blocks_done < n_blocks:
            if split is not None:
                stream.extra = split.state()
            save_checkpoint(stream, checkpoint, key)
            last_save = time.perf_counter()
        t_ff = time.perf_counter()
    return stream.finish(), time_ff


def factorize_matrix(F, reflectance, *, eps: float = 0.02, relative: bool = True,
                     block_size: int = DEFAULT_BLOCK_SIZE, dtype=np.float32, order=None, method: str = "hf",
                     rng=None, progress: ProgressCallback = None) -> HFactorization:
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
    rho = check_reflectance(reflectance, n)
    perm = check_permutation(order, n)
    check_method(method)
    if block_size < 1:
        raise ValueError(f"block_size must be >= 1; got {block_size}")
    rho_max = rho.max(axis=1)
    lr = lowrank_from_matrix(F, rho_max, perm, eps=eps, relative=relative, block_size=block_size, dtype=dtype,
                             method=method, rng=rng, progress=progress)
    params = {"method": method, "block_size": block_size, "dtype": np.dtype(dtype).name,
              "time_factor": lr.info["time_factor"]}
    if method == "hf":
        params["leaf_share"] = 0.5
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params)


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
        :func:`~hfrad.factorize.hf.hierarchical_factorization`
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
            raise ValueError("pass n_blocks (or block_size) when blocks is a generator") from None
    lr = lowrank_from_blocks(blocks, n, rho_max, perm, eps=eps, relative=relative, dtype=dtype,
                             n_blocks=n_blocks, leaf_share=leaf_share, progress=progress)
    params = {"method": "hf", "block_size": block_size, "dtype": np.dtype(dtype).name,
              "leaf_share": leaf_share, "time_factor": lr.info["time_factor"]}
    return HFactorization(perm, lr.Q, lr.V, rho_max, rho, lr, params=params)
